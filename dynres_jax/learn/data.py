"""Training data for the dynamics model f: batched episodes of random pushes, written as resumable shards.

Generation (``generate``). The run is cut into shards; shard ``i`` holds ``DataConfig.worlds`` episodes simulated as one
batch of worlds, on one ``SimConfig`` drawn for that shard (piece kind(s), piece count, pile layout) from the ranges in
``DataConfig``. The engine (``DataConfig.backend``): C MuJoCo worker processes (default), MuJoCo Warp on one GPU, or MJX
on the device, on the fast scene (``SceneConfig.fast``) or the given one. Everything random in a shard (its scene and
its worlds) comes from ``(seed, i)`` alone, so shards can be made in any order, and a killed run resumes by skipping the
shard files that exist: the result is the one an uninterrupted run writes. Several processes of one job
(``dynres_jax.distributed``: a launcher, or ``--coordinator``) share a run: process I makes shards I, I + K, ... into
the same folder. An episode is ``pushes`` random pushes through the pile (``PileEnv.sample_push``) from a freshly reset
pile (with ``DataConfig.planned`` > 0, a share of them chosen by the closed loop's planner instead:
``learn.on_policy``); frame 0 is the settled pile, frame ``t + 1`` the pile after action ``t``. The worlds of an MJX
batch are sharded over the process's devices (a 1-D ``Mesh`` named ``"worlds"``), so more GPUs go faster. Results are
bit-identical for the same seed, machine and device count (with another, to float32 rounding, then chaos).

On-disk format: ``DIR/shard_00000.npz`` ... (one zip of ``.npy`` members, deflated, fixed timestamps, so equal
content gives equal bytes), ``DIR/config.json`` (the DataConfig, checked on resume), ``DIR/summary.json``. Shard
members, with E kept episodes, F = pushes + 1 frames, N pieces, H x W pixels:

    depth   [E, F, H, W] float16   z-depth (m); table at ``camera.distance`` (1 m): below 1 m the step is 0.49 mm
    piece   [E, F, H, W] int16     segmentation: piece index, -1 background
    pos     [E, F, N, 3] float32   piece (geom) centres, world frame (m)
    mat     [E, F, N, 3, 3] float32  piece rotations (columns: the piece's axes in the world frame)
    action  [E, F - 1, 4] float32  pushes (x_start, y_start, x_end, y_end), m
    broken  [E, F] bool            the world broke (NaN, a piece through the table or out of the bin); sticky
    episode [E] int64              global episode id, shard * worlds + world
    kind    [N] int16              each piece's kind, an index into kind_names
    kind_names [K] str; sim_config [] str (the shard's SimConfig as JSON); engine [] str (the engine that made it);
    shard, simulated, dropped [] int64

Colour images are not stored: ``Renderer`` redraws them from the poses. Broken episodes are dropped by default
(``DataConfig.drop_broken``): ``dropped`` counts them per shard and the summary in total. Loading: ``learn.targets``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import glob
import json
import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from dynres_jax import distributed
from dynres_jax.config import KINDS, PushConfig, SimConfig, check_fields, check_kind_names, replace
from dynres_jax.errors import InputError
from dynres_jax.io.files import leftovers, read_json, write_json, write_text
from dynres_jax.io.shards import SHARD_GLOB, fill, read_shard, save_npz, shard_path
from dynres_jax.learn import on_policy
from dynres_jax.progress import bar as progress_bar
from dynres_jax.sim import engines
from dynres_jax.sim import pool as pools
from dynres_jax.sim.camera import MAX_IMAGE, MIN_IMAGE
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import process_pool, random_episode

KIND_NAMES = tuple(KINDS)  # global kind index used by Dataset.kind and Sample.kind
LAYOUTS = ("blob", "two_blobs", "spread")
PER_EPISODE = ("depth", "piece", "pos", "mat", "action", "broken", "episode")  # shard members with an episode axis
MAX_SHARD_BYTES = 16 * 2**30  # one shard is gathered in host memory before it is written


@dataclass(frozen=True)
class DataConfig:
    """A data generation run.

    episodes: episodes to keep before dropping broken ones (reference 2,000); the last shard is cut to fit.
    pushes: random pushes per episode (reference 10; training windows need pushes >= the rollout horizon, 5).
    worlds: worlds simulated together, one shard; must divide by the number of devices. Large batches pay on a GPU
      (MJX peaks at about 1,024 worlds of 100 pieces on an H200), but every shard is one scene: more shards, more
      scene variety.
    kinds: piece kinds a shard's scene is drawn from. pieces: (min, max) piece count of a shard, drawn on a grid of
      ``pieces_step`` (each distinct scene compiles once; a coarse grid means fewer compiles).
    scenes: how many scenes the run draws, shard i taking scene i mod ``scenes``; 0 (default): a scene per shard. A
      JAX engine builds and compiles each distinct scene once (MuJoCo Warp: 5-70 s a new scene, docs/warp), so a run
      of many shards on few scenes pays few compiles, for less variety of kinds, counts and layouts (and with
      ``planned``, an S divisible by 3 plans each scene at one ω only).
    layouts: pile layouts to draw from. two_kinds: probability that a shard mixes two kinds (half the pieces each),
      for Sort. image_size: square image side (pixels). seed: everything random derives from (seed, shard index).
    drop_broken: drop episodes whose world broke (else keep them with their ``broken`` flags).
    backend: "mjx" simulates a shard's worlds as one batch sharded over the JAX devices, "warp" as one batch in MuJoCo
      Warp (the C engine's algorithms on one GPU: docs/warp; ``pip install "dynres-jax[warp]"``), "mjx-fast" as "mjx" on
      the fast scene (``SceneConfig.fast`` physics for the shard's kinds: about 3.5x C MuJoCo on all 16 cores of an H200
      host, where the default scene runs at 0.2x; docs/performance.md, "Speed"); "mujoco" runs them in the C engine, one
      world per host process (``generate``'s ``workers``), and renders the frames on the JAX device (default); "auto" is
      "mjx-fast" where JAX has a GPU and "mujoco" elsewhere (``concrete``: a run's config.json records the engine it
      used). Why C is the default: on one H200 "mjx-fast" made the same data set 2.8x faster, but the model trained on
      it gathered coffee in the C scene in 48 % of episodes against 75 % for the model trained on C data
      (docs/performance.md, "Data from MJX").
    planned: the share of pushes the closed loop's planner chooses (on-policy data, ``learn.on_policy``; shard i
      plans at ω = ``on_policy.OMEGAS[i % 3]``); 0: every push random. policy: the checkpoint folder of the model it
      plans with ("shipped": checkpoints/dynamics).
    sim: the rest of the simulator (physics, push, camera distance); kinds, pieces, layout and image size above
      override its fields per shard.
    """

    episodes: int = 2000
    pushes: int = 10
    worlds: int = 128
    kinds: tuple[str, ...] = ("coffee", "almond", "rice", "mnm", "granola", "candy")
    pieces: tuple[int, int] = (40, 100)
    pieces_step: int = 10
    scenes: int = 0
    layouts: tuple[str, ...] = LAYOUTS
    two_kinds: float = 0.25
    image_size: int = 128
    seed: int = 0
    drop_broken: bool = True
    backend: str = "mujoco"
    planned: float = 0.0
    policy: str = "shipped"
    sim: SimConfig = field(default_factory=SimConfig)

    def __post_init__(self):
        check_fields(self)
        for name in ("episodes", "pushes", "worlds", "pieces_step"):
            value = getattr(self, name)
            if value < 1:  # an int: check_fields
                raise ValueError(f"DataConfig.{name} must be a positive int, got {value!r}")
        if self.scenes < 0:  # an int: check_fields
            raise ValueError(f"DataConfig.scenes must be 0 (a scene per shard) or a positive count, got {self.scenes}")
        if not self.kinds:
            raise ValueError("DataConfig.kinds must name at least one piece kind")
        check_kind_names(self.kinds, "DataConfig.kinds")
        if len(self.pieces) != 2 or not 1 <= self.pieces[0] <= self.pieces[1]:
            raise ValueError(f"DataConfig.pieces must be (min, max) with 1 <= min <= max, got {self.pieces}")
        if not self.layouts or any(lay not in LAYOUTS for lay in self.layouts):
            raise ValueError(f"DataConfig.layouts must be non-empty names from {LAYOUTS}, got {self.layouts}")
        if not 0.0 <= self.two_kinds <= 1.0 or (self.two_kinds > 0 and len(set(self.kinds)) < 2):
            raise ValueError(f"DataConfig.two_kinds must be in [0, 1], and 0 unless two distinct kinds are given; "
                             f"got {self.two_kinds} with kinds {self.kinds}")
        if self.backend not in engines.NAMES:
            raise ValueError(f"DataConfig.backend must be one of {', '.join(engines.NAMES)}, got {self.backend!r}")
        if not 0.0 <= self.planned <= 1.0:
            raise ValueError(f"DataConfig.planned must be a share in [0, 1], got {self.planned}")
        if not MIN_IMAGE <= self.image_size <= MAX_IMAGE:
            raise ValueError(f"DataConfig.image_size must be in [{MIN_IMAGE}, {MAX_IMAGE}] pixels, "
                             f"got {self.image_size}")
        if self.shard_bytes > MAX_SHARD_BYTES:
            raise ValueError(f"DataConfig: a shard ({self.worlds} worlds x {self.pushes + 1} frames of "
                             f"{self.image_size}² pixels and {self.pieces[1]} pieces) takes "
                             f"{self.shard_bytes / 2**30:.0f} GiB in memory, over {MAX_SHARD_BYTES // 2**30} GiB: "
                             "fewer pushes, worlds or pixels")

    @property
    def shard_bytes(self) -> int:
        """The bytes one shard's members take in memory (the table above: depth, piece, pos, mat per frame)."""
        per_frame = self.image_size**2 * (2 + 2) + self.pieces[1] * (3 + 9) * 4
        return self.worlds * (self.pushes + 1) * per_frame

    @property
    def n_shards(self) -> int:
        return math.ceil(self.episodes / self.worlds)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=1, sort_keys=True)


def quick_config(**overrides) -> DataConfig:
    """Tiny sizes for smoke tests on a CPU: 6 coffee beans in a blob, 48 x 48 images, 2 short pushes, 10 episodes
    (the 10th held out for validation) in shards of 4 worlds; ``train_dynamics --recipe quick`` trains on them.
    ``overrides``: DataConfig fields by name."""
    quick = DataConfig(episodes=10, pushes=2, worlds=4, kinds=("coffee",), pieces=(6, 6), layouts=("blob",),
                       two_kinds=0.0, image_size=48, backend="mjx",
                       sim=SimConfig(push=PushConfig(max_length=0.08, settle_time=0.04)))
    return replace(quick, **overrides)


def concrete(config: DataConfig) -> DataConfig:
    """``config`` with its engine made concrete (``engines.resolve``: "auto" is "mjx-fast" on a GPU, else
    "mujoco")."""
    return replace(config, backend=engines.resolve(config.backend))


def shard_sim_config(config: DataConfig, shard: int) -> SimConfig:
    """The scene of shard ``shard``: kind(s), piece count and layout drawn from ``np.random.default_rng((seed, j))``
    with j the shard's scene (``shard``, or ``shard % scenes``); image size from the DataConfig, everything else from
    ``config.sim``, as the run's engine simulates it (``engines.sim_config``: the fast scene's physics for
    "mjx-fast")."""
    rng = np.random.default_rng((config.seed, shard % config.scenes if config.scenes else shard))
    lo, hi = config.pieces
    n = int(rng.choice(np.arange(lo, hi + 1, config.pieces_step)))
    layout = str(rng.choice(config.layouts))
    if rng.uniform() < config.two_kinds and n >= 2:
        kinds = tuple(str(k) for k in rng.choice(sorted(set(config.kinds)), 2, replace=False))
        pieces = (n // 2, n - n // 2)
    else:
        kinds, pieces = (str(rng.choice(config.kinds)),), (n,)
    sim = config.sim
    drawn = replace(sim, scene=replace(sim.scene, kinds=kinds, pieces=pieces), pile=replace(sim.pile, layout=layout),
                    camera=replace(sim.camera, width=config.image_size, height=config.image_size))
    return engines.sim_config(drawn, config.backend)


# ---------------------------------------------------------------------------------------------------------------
# Generation
# ---------------------------------------------------------------------------------------------------------------
def check_devices(config: DataConfig, devices=None) -> list:
    """The devices a run shards its worlds over (default this process's); ValueError unless worlds divides (MJX;
    "mujoco" simulates on host processes and renders on the first device)."""
    devices, engine = list(devices or jax.local_devices()), engines.ENGINES[concrete(config).backend]
    if engine.one_device and len(devices) > 1:
        raise ValueError(f"backend {engine.name!r} simulates a shard on one device, but {len(devices)} are visible; "
                         "pick one (CUDA_VISIBLE_DEVICES=0) or run one process per GPU (--coordinator)")
    if not engine.workers and config.worlds % len(devices):
        raise ValueError(f"DataConfig.worlds={config.worlds} must be a multiple of the device count "
                         f"{len(devices)} (worlds are split evenly over devices); use e.g. worlds="
                         f"{math.ceil(config.worlds / len(devices)) * len(devices)}")
    return devices


def frame_record(s) -> dict:
    """The arrays a shard keeps of one frame (State, or States with a leading world axis): depth (float16), piece
    (int16), pos, mat, broken."""
    return dict(depth=s.obs.depth.astype(jnp.float16), piece=s.obs.piece.astype(jnp.int16), pos=s.pos, mat=s.mat,
                broken=s.broken)


@functools.lru_cache(maxsize=4)
def _episode_fn(sim: SimConfig, pushes: int, devices: tuple, backend: str, worlds: int):
    """(env, fn, sharding): jitted fn keys [W, 2] -> per-world episode arrays (leading axis W), the worlds axis
    sharded over ``devices``; a physics with capacities (Warp) adds ``overflow`` [W, F]. Cached: one compile a scene."""
    env = PileEnv(sim, backend=engines.physics(backend), worlds=worlds)

    def record(s):  # a physics with capacities (MuJoCo Warp) gives States their bits (``overflow``); others None
        return frame_record(s) if s.overflow is None else dict(frame_record(s), overflow=s.overflow)

    def episode(key):
        frames, actions = random_episode(env, key, pushes, record)
        return dict(frames, action=actions)

    sharding = NamedSharding(Mesh(np.array(devices), ("worlds",)), PartitionSpec("worlds"))
    return env, jax.jit(jax.vmap(episode), in_shardings=sharding, out_shardings=sharding), sharding


def simulate_shard(config: DataConfig, shard: int, devices=None, pool=None) -> dict:
    """Simulate shard ``shard`` (all ``worlds`` episodes, nothing dropped) -> dict of NumPy arrays with a leading
    world axis (see the module docstring) plus the shard's metadata. ``pool``: worker processes for backend
    "mujoco" (``pool.process_pool``); without one the C episodes run in this process. Planned shards on a pool run
    in ``on_policy.HOST_LANES`` lanes (one group of worlds pushes while another plans)."""
    config = concrete(config)
    devices = check_devices(config, devices)
    sim = shard_sim_config(config, shard)
    keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(config.seed), shard), config.worlds)
    if config.planned > 0:
        worlds = pools.make_pool(sim, config.backend, pool)
        env = worlds.env
        lanes = min(on_policy.HOST_LANES, config.worlds) if pool is not None else 1
        out = on_policy.planned_episodes(worlds, keys, config.pushes, config.planned, on_policy.policy_dynamics(
            config.policy, sim.scene.plate_half_width), on_policy.OMEGAS[shard % len(on_policy.OMEGAS)],
                                         frame_record, lanes)
    elif engines.uses_workers(config.backend):
        worlds = pools.make_pool(sim, config.backend, pool)
        env, out = worlds.env, worlds.random_episodes(keys, config.pushes)
    else:
        env, fn, sharding = _episode_fn(sim, config.pushes, tuple(devices), config.backend, config.worlds)
        out = jax.device_get(fn(jax.device_put(keys, sharding)))
        if "overflow" in out:
            env.physics.check_batch(out.pop("overflow")[:, -1], env.scene.n_pieces)  # sticky: the last has all
    out["episode"] = shard * config.worlds + np.arange(config.worlds, dtype=np.int64)
    out["kind"] = env.scene.kind.astype(np.int16)
    out["kind_names"] = np.array(sim.scene.kinds)
    out["sim_config"] = np.array(sim.to_json())
    out["shard"] = np.int64(shard)
    out["engine"] = np.array(config.backend)
    return out


def finish_shard(arrays: dict, n_keep: int, drop_broken: bool) -> dict:
    """Keep the first ``n_keep`` worlds (the run's last shard is cut to ``episodes``) and drop the broken ones
    when ``drop_broken``; adds ``simulated`` and ``dropped`` counts."""
    keep = np.arange(len(arrays["episode"])) < n_keep
    broken = keep & arrays["broken"][:, -1]
    if drop_broken:
        keep &= ~broken
    out = {k: (v[keep] if k in PER_EPISODE else v) for k, v in arrays.items()}
    out["simulated"] = np.int64(n_keep)
    out["dropped"] = np.int64(broken.sum() if drop_broken else 0)
    return out


def check_helpers(config: DataConfig, cpu_workers: int) -> DataConfig | None:
    """The C engine's DataConfig for ``cpu_workers`` helper processes beside ``config``'s engine (None for none);
    ValueError unless that engine is a JAX engine of C's physics and the data are random pushes."""
    helper = engines.beside(config, cpu_workers)
    if helper is not None and config.planned > 0:
        raise ValueError(f"C workers ({cpu_workers}) fill shards of random pushes only; got planned {config.planned}")
    return helper


def shards_todo(out_dir: str, n_shards: int, part: tuple[int, int] | None = None) -> list[int]:
    """This process's shard indices whose files are not written yet (a rerun resumes where a killed one stopped).
    part (I, K): shards I, I + K, ... (default ``distributed.part()``: this process of the job)."""
    i, k = part or distributed.part()
    return [s for s in range(i, n_shards, k) if not os.path.exists(shard_path(out_dir, s))]


def by_scene(config: DataConfig, todo: list[int]) -> list[int]:
    """``todo``'s shards grouped by scene, in shard order within a scene and by first shard across scenes: an engine
    taking them in turn meets each scene in one stretch, so it builds and compiles each once (``_episode_fn`` keeps
    only the last few)."""
    scene, first = {i: shard_sim_config(config, i).to_json() for i in todo}, {}
    for i in todo:
        first.setdefault(scene[i], i)
    return sorted(todo, key=lambda i: (first[scene[i]], i))


def generate(config: DataConfig, out_dir: str, devices=None, progress: bool = True, workers: int | None = None,
             part: tuple[int, int] | None = None, cpu_workers: int = 0) -> dict:
    """Simulate ``config`` into ``out_dir`` (shards, config.json, summary.json), resuming a killed run (shard files
    that exist are kept). Returns the summary (also summary.json): totals over all shards, and this run's shards
    written, seconds and ``samples_per_s`` (frames a second, compiles included). InputError when ``out_dir`` holds a
    run of another DataConfig or a damaged config.json; ValueError when worlds does not divide by the device count.
    ``workers``: C processes for "mujoco" (default every core). ``part`` (I, K): only the shards I modulo K (default
    ``distributed.part()``); in a job every process waits for the others before the summary, which process 0 writes.
    ``cpu_workers`` K > 0: C MuJoCo on K processes fills shards beside a JAX engine of C's physics (Warp), each shard
    taken by whichever engine is free; a shard depends on (seed, shard) alone and records its ``engine``."""
    config = concrete(config)
    devices = check_devices(config, devices)
    helper = check_helpers(config, cpu_workers)
    part = part or distributed.part()
    os.makedirs(out_dir, exist_ok=True)
    for leftover in leftovers(shard_path(out_dir, shard) for shard in range(part[0], config.n_shards, part[1])):
        os.unlink(leftover)  # half-written shards of a killed run of this part
    config_path = os.path.join(out_dir, "config.json")
    if os.path.exists(config_path):
        try:  # a field added since the run began counts as its default
            with open(config_path) as f:
                same = {**json.loads(DataConfig().to_json()), **json.load(f)} == json.loads(config.to_json())
        except (OSError, ValueError, TypeError) as e:
            raise InputError(f"{out_dir}: config.json damaged ({type(e).__name__}); write to a new folder") from None
        if not same:
            raise InputError(f"{out_dir} holds data of another DataConfig (see its config.json); resume with the same "
                             "config or write to a new folder")
    else:
        write_text(config_path, config.to_json())

    todo = by_scene(config, shards_todo(out_dir, config.n_shards, part))
    mine = len(range(part[0], config.n_shards, part[1]))
    start, lock, frames = time.perf_counter(), threading.Lock(), []
    made = {config.backend: 0, **({helper.backend: 0} if helper else {})}
    bar = progress_bar(total=mine, initial=mine - len(todo), unit="shard", desc="generate", quiet=not progress)

    def producer(cfg: DataConfig, pool):  # an engine's shards, each written while its next one simulates
        pending = []

        def produce(i: int) -> None:
            arrays = finish_shard(simulate_shard(cfg, i, devices, pool), min(cfg.worlds, cfg.episodes - i * cfg.worlds),
                                  cfg.drop_broken)
            while pending:
                pending.pop().result()
            pending.append(writer.submit(save_npz, shard_path(out_dir, i), arrays))
            with lock:
                frames.append(arrays["broken"].size)
                made[cfg.backend] += 1
                bar.update()
                bar.set_postfix(kinds="+".join(arrays["kind_names"]), pieces=len(arrays["kind"]), **made)

        return produce, pending

    pool = process_pool(workers) if engines.uses_workers(config.backend) and todo else None
    helpers = process_pool(cpu_workers) if helper and todo else None
    with (ThreadPoolExecutor(2) as writer, pool or contextlib.nullcontext(), helpers or contextlib.nullcontext()):
        producers = [producer(config, pool)] + ([producer(helper, helpers)] if helpers else [])
        try:
            fill(todo, [produce for produce, _ in producers])
        finally:
            for _, pending in producers:
                for write in pending:
                    write.result()
    bar.close()
    written_frames = sum(frames)
    seconds = time.perf_counter() - start
    distributed.barrier(f"generate {os.path.abspath(out_dir)}")

    written = [read_shard(path, ("broken", "simulated", "dropped"))  # those written so far (a lone part: its own)
               for path in sorted(glob.glob(os.path.join(out_dir, SHARD_GLOB)))]
    totals = dict(shards=len(written), episodes=sum(len(s["broken"]) for s in written),
                  frames=sum(s["broken"].size for s in written), broken_dropped=sum(int(s["dropped"]) for s in written),
                  simulated=sum(int(s["simulated"]) for s in written))
    summary = dict(totals, episodes_requested=config.episodes, pushes=config.pushes, shards_written=len(todo),
                   shards_skipped=mine - len(todo), seconds=seconds,
                   samples_per_s=written_frames / seconds if todo else 0.0,
                   devices=len(devices), device_kind=devices[0].device_kind, backend=config.backend,
                   shards_by_engine=made, process=part[0], processes=part[1])
    if distributed.is_writer():  # a rerun that added nothing changes no file (the folder's hash is a run's input)
        earlier = read_json(os.path.join(out_dir, "summary.json")) or {}
        if any(earlier.get(k) != v for k, v in totals.items()):
            write_json(os.path.join(out_dir, "summary.json"), summary)
    return summary
