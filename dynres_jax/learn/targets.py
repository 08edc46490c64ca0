"""Training targets of the dynamics model f, from the shards ``dynres_jax.learn.data`` writes.

Training samples. ``load_shards`` reads shards into one ``Dataset`` (pieces padded to the largest count, with a
mask); the held-out split is by episode: global id ``% val_every == val_every - 1`` is validation, so it never
depends on shard layout or resuming. ``windows`` cuts (episode, t) windows of ``horizon + 1`` frames; ``make_sample``
(pure JAX, vmap it) samples particles at frame t with perception h at resolution ω, attaches each particle to the
piece it lies on (``attach_particles``) and moves it with that piece (``particle_trajectory``): the targets are
rigid-body tracks, never re-matched by nearest neighbours.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import SimConfig, check_kind_names
from dynres_jax.errors import InputError
from dynres_jax.io.shards import SHARD_GLOB, iter_shards
from dynres_jax.learn.data import KIND_NAMES, PER_EPISODE
from dynres_jax.perception import sample_particles
from dynres_jax.sim.camera import Camera, Observation


# ---------------------------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Dataset:
    """Episodes of all loaded shards, pieces padded to the largest count Nmax (E episodes, F frames):
    depth [E, F, H, W] float16 (m), piece [E, F, H, W] int16, pos [E, F, Nmax, 3], mat [E, F, Nmax, 3, 3] (padding:
    0 and identity), piece_mask [E, Nmax] bool, kind [E, Nmax] int16 index into KIND_NAMES (-1 padding), action
    [E, F - 1, 4], broken [E, F], episode [E] global ids; camera: the shards' common camera."""

    depth: np.ndarray
    piece: np.ndarray
    pos: np.ndarray
    mat: np.ndarray
    piece_mask: np.ndarray
    kind: np.ndarray
    action: np.ndarray
    broken: np.ndarray
    episode: np.ndarray
    camera: Camera

    @property
    def pushes(self) -> int:
        return self.action.shape[1]

    def __len__(self) -> int:
        return len(self.episode)


def is_validation(episode, val_every: int = 10):
    """The held-out split by global episode id: every ``val_every``-th episode -> bool (same shape)."""
    return np.asarray(episode) % val_every == val_every - 1


def load_shards(data_dir: str | Sequence[str], split: str = "all", val_every: int = 10) -> Dataset:
    """Read every shard of ``data_dir`` (a folder, or several: one data set of all their episodes, which must share
    camera and pushes per episode) into a Dataset. split: "all", "train" or "val" (``is_validation``)."""
    if split not in ("all", "train", "val"):
        raise ValueError(f"split must be 'all', 'train' or 'val', got {split!r}")
    folders = [data_dir] if isinstance(data_dir, str) else list(data_dir)
    parts, camera, pushes = [], None, None
    for path, s in (shard for folder in folders for shard in iter_shards(folder)):
        sim = SimConfig.from_json(str(s["sim_config"]))
        cam = Camera.top_down(sim.camera)
        if camera is not None and (cam != camera or s["action"].shape[1] != pushes):
            raise ValueError(f"{path}: its camera or pushes per episode differ from the earlier shards'")
        camera, pushes = cam, s["action"].shape[1]
        val = is_validation(s["episode"], val_every)
        keep = np.ones_like(val) if split == "all" else (val if split == "val" else ~val)
        kind = np.array([KIND_NAMES.index(str(name)) for name in s["kind_names"]], np.int16)[s["kind"]]
        parts.append({**{k: s[k][keep] for k in PER_EPISODE}, "kind": kind})
    if not parts:
        raise InputError(f"no shards ({SHARD_GLOB}) in {', '.join(folders)}")
    n_max = max(p["pos"].shape[2] for p in parts)

    def pad_poses(pos, mat):  # pieces axis -2 of pos padded to n_max with 0, of mat with the identity
        n, lead = pos.shape[-2], pos.shape[:-2]
        full = np.broadcast_to(np.eye(3, dtype=np.float32), lead + (n_max, 3, 3)).copy()
        full[..., :n, :, :] = mat
        return np.pad(pos, [(0, 0)] * len(lead) + [(0, n_max - n), (0, 0)]), full

    def pad(p):
        e, n = len(p["episode"]), p["pos"].shape[2]
        p = dict(p, piece_mask=np.broadcast_to(np.arange(n_max) < n, (e, n_max)),
                 kind=np.broadcast_to(np.pad(p["kind"], (0, n_max - n), constant_values=-1), (e, n_max)))
        p["pos"], p["mat"] = pad_poses(p["pos"], p["mat"])
        return p

    parts = [pad(p) for p in parts]
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    if not len(cat["episode"]):
        raise InputError(f"the {split!r} split of {', '.join(folders)} is empty: validation takes every "
                         f"{val_every}th episode (is_validation), so it needs at least {val_every} episodes")
    return Dataset(**cat, camera=camera)


def without_kinds(dataset: Dataset, kinds) -> Dataset:
    """The episodes of ``dataset`` with no piece of any of ``kinds`` (names from KIND_NAMES): a data set on which a
    model never sees those kinds, to measure how it does on them. ValueError for an unknown name or when nothing is
    left."""
    check_kind_names(kinds, "kinds")
    if not kinds:
        return dataset
    drop = np.isin(dataset.kind, [KIND_NAMES.index(k) for k in kinds]).any(axis=1)
    if drop.all():
        raise ValueError(f"every episode has a piece of {', '.join(kinds)}: nothing is left to train on")
    return _episodes(dataset, ~drop)


def _episodes(dataset: Dataset, keep) -> Dataset:
    """The episodes where keep [E] bool is True."""
    per_episode = [f.name for f in dataclasses.fields(Dataset) if f.name != "camera"]
    return Dataset(**{name: getattr(dataset, name)[keep] for name in per_episode}, camera=dataset.camera)


# ---------------------------------------------------------------------------------------------------------------
# Training targets
# ---------------------------------------------------------------------------------------------------------------
def attach_particles(particles, mask, piece_pos, piece_mat, piece_id_image, camera: Camera, piece_mask=None):
    """Attach each particle to the piece it lies on. particles [n, 3] world (m), mask [n] bool, piece_pos [N, 3],
    piece_mat [N, 3, 3] (columns: piece axes), piece_id_image [H, W] (piece index, negative for background),
    piece_mask [N] bool (padding pieces False; default all real) -> (piece_index [n] int32, -1 where masked;
    local [n, 3] piece-frame offsets R^T (p - c), 0 where masked).

    The piece is the one in the segmentation pixel the particle projects to; where that pixel is background (or
    outside the image) the piece with the nearest centre. Pure JAX."""
    particles = jnp.asarray(particles, jnp.float32)
    ids = jnp.asarray(piece_id_image).astype(jnp.int32)
    n_pieces = piece_pos.shape[0]
    piece_mask = jnp.ones(n_pieces, bool) if piece_mask is None else jnp.asarray(piece_mask, bool)
    uv, _ = camera.world_to_pixel(particles)
    u, v = jnp.floor(uv[:, 0]).astype(jnp.int32), jnp.floor(uv[:, 1]).astype(jnp.int32)
    inside = (u >= 0) & (u < ids.shape[1]) & (v >= 0) & (v < ids.shape[0])
    seen = jnp.where(inside, ids[jnp.clip(v, 0, ids.shape[0] - 1), jnp.clip(u, 0, ids.shape[1] - 1)], -1)
    seen_ok = (seen >= 0) & (seen < n_pieces) & piece_mask[jnp.clip(seen, 0, n_pieces - 1)]
    d2 = jnp.sum(jnp.square(particles[:, None] - piece_pos[None]), -1)
    nearest = jnp.argmin(jnp.where(piece_mask[None], d2, jnp.inf), axis=1).astype(jnp.int32)
    index = jnp.where(mask, jnp.where(seen_ok, seen, nearest), -1)
    safe = jnp.maximum(index, 0)
    local = jnp.einsum("nji,nj->ni", piece_mat[safe], particles - piece_pos[safe])
    return index, jnp.where(mask[:, None], local, 0.0)


def particle_trajectory(piece_index, local, pos_seq, mat_seq):
    """Particles moved rigidly with their pieces: piece_index [n] (-1: none), local [n, 3], pos_seq [K, N, 3],
    mat_seq [K, N, 3, 3] -> positions [K, n, 3] = R_k local + c_k (0 where piece_index is -1). Pure JAX."""
    safe = jnp.maximum(piece_index, 0)
    traj = pos_seq[:, safe] + jnp.einsum("knij,nj->kni", mat_seq[:, safe], local)
    return jnp.where((piece_index >= 0)[None, :, None], traj, 0.0)


class Window(NamedTuple):
    """One training window of ``horizon`` pushes from frame t (NumPy or JAX; batch axes in front): depth [H, W] f32
    (m) and piece [H, W] int32 at frame t; pos [horizon + 1, N, 3], mat [horizon + 1, N, 3, 3] at frames t..t+horizon;
    piece_mask [N] bool; kind [N] int32 (KIND_NAMES index, -1 padding); action [horizon, 4] (m)."""

    depth: np.ndarray
    piece: np.ndarray
    pos: np.ndarray
    mat: np.ndarray
    piece_mask: np.ndarray
    kind: np.ndarray
    action: np.ndarray


def windows(data: Dataset, rows, t, horizon: int = 5) -> Window:
    """Batched windows: rows [B] (Dataset rows, not episode ids), t [B] start frames, 0 <= t <= pushes - horizon."""
    rows, t = np.asarray(rows), np.asarray(t)
    if horizon < 1 or horizon > data.pushes:
        raise ValueError(f"horizon={horizon} must be in [1, pushes per episode = {data.pushes}]")
    if rows.shape != t.shape or np.any(t < 0) or np.any(t > data.pushes - horizon):
        raise ValueError(f"t must match rows in shape and lie in [0, {data.pushes - horizon}] (pushes - horizon)")
    return _cut(data, rows, t, horizon)


def _cut(data, rows, t, horizon: int) -> Window:
    """The windows at rows [B] and start frames t [B] of a Dataset or Frames (NumPy in, NumPy out; JAX in, JAX out)."""
    span = t[:, None] + np.arange(horizon + 1)
    r = rows[:, None]
    return Window(data.depth[rows, t].astype(np.float32), data.piece[rows, t].astype(np.int32), data.pos[r, span],
                  data.mat[r, span], data.piece_mask[rows], data.kind[rows].astype(np.int32),
                  data.action[r, span[:, :-1]])


def window_count(data: Dataset, horizon: int) -> int:
    """How many different windows of ``horizon`` pushes the data hold: episodes x start frames."""
    return len(data) * max(data.pushes - horizon + 1, 0)


def random_windows(data: Dataset, rng: np.random.Generator, batch: int, horizon: int = 5) -> Window:
    """``batch`` different windows (row, start frame), drawn uniformly without replacement; ValueError where the data
    hold fewer (``window_count``)."""
    starts, total = data.pushes - horizon + 1, window_count(data, horizon)
    if batch > total:
        raise ValueError(f"the data hold {total} different windows of {horizon} pushes ({len(data)} episodes x "
                         f"{starts} start frames), fewer than {batch}")
    flat = rng.choice(total, batch, replace=False)
    return windows(data, flat // starts, flat % starts, horizon)


class Frames(NamedTuple):
    """A Dataset's arrays (``Dataset``'s shapes), as NumPy or on the devices (``train.resident``): what
    ``draw_windows`` cuts windows from inside a jitted step."""

    depth: jax.Array
    piece: jax.Array
    pos: jax.Array
    mat: jax.Array
    piece_mask: jax.Array
    kind: jax.Array
    action: jax.Array


def draw_windows(frames: Frames, key, batch: int, horizon: int) -> Window:
    """``batch`` windows of ``horizon`` pushes, rows and start frames uniform from ``key``; pure JAX (the ``windows``
    of rows and starts drawn on the device)."""
    episodes, pushes = frames.action.shape[:2]
    k_rows, k_t = jax.random.split(key)
    rows = jax.random.randint(k_rows, (batch,), 0, episodes)
    t = jax.random.randint(k_t, (batch,), 0, pushes - horizon + 1)
    return _cut(frames, rows, t, horizon)


class Sample(NamedTuple):
    """A training sample: positions [horizon + 1, n_max, 3] of the particles at frames t..t+horizon (m, 0 where
    masked); mask [n_max] (the first ω); kind [n_max] int32 (KIND_NAMES index of each particle's piece, -1 masked);
    action [horizon, 4]; radius [] the FPS covering radius (m); error [] perception error flags (0 = ok; else the
    mask is all False)."""

    positions: jax.Array
    mask: jax.Array
    kind: jax.Array
    action: jax.Array
    radius: jax.Array
    error: jax.Array


def make_sample(window: Window, omega, key, camera: Camera, n_max: int, **perception_kw) -> Sample:
    """One Window + resolution ω + key -> Sample: h(y_t, ω) with ``n_max`` slots, each particle attached to its
    piece at frame t and carried rigidly to t + horizon. Pure JAX; ``jax.vmap`` over (window, omega, key).
    perception_kw: keyword arguments of ``sample_particles`` (max_points, r_center, kind with a KIND_NAMES index)."""
    piece = jnp.asarray(window.piece, jnp.int32)
    kind = jnp.asarray(window.kind, jnp.int32)
    kind_image = jnp.where(piece >= 0, kind[jnp.maximum(piece, 0)], -1)
    obs = Observation(jnp.asarray(window.depth, jnp.float32), piece, kind_image,
                      jnp.zeros(piece.shape + (3,), jnp.uint8))
    p = sample_particles(obs, camera, omega, key, n_max, **perception_kw)
    index, local = attach_particles(p.positions, p.mask, window.pos[0], window.mat[0], piece, camera,
                                    window.piece_mask)
    positions = particle_trajectory(index, local, jnp.asarray(window.pos), jnp.asarray(window.mat))
    return Sample(positions, p.mask, jnp.where(index >= 0, kind[jnp.maximum(index, 0)], -1),
                  jnp.asarray(window.action), p.radius, p.error)
