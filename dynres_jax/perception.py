"""Perception h(y, ω): depth image -> point cloud -> foreground -> farthest point sampling -> re-centred particles.

Every function is pure JAX over padded arrays with masks; no shape depends on the data, so one compiled function
serves every resolution ω and ``jax.vmap`` works over observations, keys and ω alike.

- ``point_cloud``: every pixel is a candidate point (P = H * W, foreground mask alongside), or, with ``max_points``,
  the foreground pixels are packed into a fixed P = max_points slots; when there are more foreground pixels than
  slots, the ones kept are a uniform random subset drawn by one fixed pixel permutation (the same on every call).
  Foreground: a depth reading (``sim.sensor.is_reading``: 0, NaN, ±inf and ``NO_READING`` are none), more than
  ``margin`` (3 mm) above the table, inside the bin's workspace (so the bin walls never count), optionally one object
  kind (segmentation) or one colour (chromaticity distance, for Sort).
- ``fps``: farthest point sampling as a ``lax.fori_loop`` keeping a running min-distance [P] (no [P, P] matrix).
  The first k indices are the size-k FPS sample, so one call to N_max gives every ω <= N_max as a prefix mask.
- ``recentre``: each particle moves to the mean of the cloud points within ``r_center`` of it (paper supplement).
- ``sample_particles``: the whole h. Bad input is reported in ``Particles.error`` (bit flags) when traced, and as a
  ValueError naming the problem when called with concrete values.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.sim.camera import Camera, Observation, neighbourhoods, rotation_about
from dynres_jax.sim.sensor import NO_READING, is_reading, readings

FOREGROUND_MARGIN = 0.003  # m: a pixel is foreground when its point is this far above the table (z = 0)
PILE_CEILING = 0.15  # m: and at most this far: higher is no pile (an arm, a hand, a reading next to the lens)
WALL_BAND = 0.01  # m: with real_depth, the workspace shrinks by this much: calibration errors bring wall tops inside
TABLE_BAND = 0.004  # m: ``table_height`` fits the plane through points this close to the median height
WORKSPACE_HALF_WIDTH = 0.199  # m: default bin half-width (0.2) less 1 mm, so wall tops and inner faces never count
COLOUR_TOL = 0.05  # chromaticity distance (r, g, b) / (r + g + b) to the reference colour; shading-invariant
R_CENTER_MAX = 0.008  # m: the reference's 0.02 normalised units of its 1-unit bin, on our 0.4 m bin
WALL_SEARCH = 0.02  # m: ``calibrate`` looks for the bin's walls this close to where they should be
MIN_WALL_POINTS = 10  # ``calibrate`` needs this many points on each wall
MAX_CAPACITY = 4096  # particle slots a call of h may ask for (the models take at most OMEGA_MAX = 100)
PERMUTATION_SEED = 0  # seed of the fixed pixel permutation that subsamples the foreground under ``max_points``

# Bit flags of ``Particles.error``.
NO_DEPTH = 1  # the depth image has no reading at all (every pixel 0, NaN, infinite or NO_READING)
NAN_DEPTH = NO_DEPTH  # its former name: NaN pixels were an error; now, as 0, they are no reading
EMPTY_FOREGROUND = 2  # no foreground point
BAD_OMEGA = 4  # ω < 1 or ω > capacity
TOO_FEW_POINTS = 8  # fewer foreground points than ω (and at least one)


class Particles(NamedTuple):
    """The output of h in ``capacity`` particle slots (a resolution bucket). positions [capacity, 3] world (m), zero
    where masked; mask [capacity] bool, the first ω entries (all False on bad input); radius []: covering radius (m)
    of the ω-sample over the cloud (0 on bad input); n_points [] int32: foreground points in the cloud; error []
    int32: bit flags (0 = ok, see module constants)."""

    positions: jax.Array
    mask: jax.Array
    radius: jax.Array
    n_points: jax.Array
    error: jax.Array

    @property
    def ok(self) -> jax.Array:
        return self.error == 0


def median_depth(depth):
    """depth [H, W] -> its 3 x 3 median [H, W] (edges replicated) over the readings a real camera gave, missing ones
    (``sim.sensor.is_reading``) left out (``NO_READING`` where all nine are missing): isolated noisy and flying pixels
    removed, depth edges kept, and a small piece whose edge readings went missing not voted away by them."""
    near = neighbourhoods(depth)
    near = jnp.where(is_reading(near), near, jnp.nan)
    median = jnp.nanmedian(near, axis=0)
    return jnp.where(jnp.isnan(median), NO_READING, median)


def table_height(points, candidates):
    """The table's height under each point, fitted from the frame itself: points [P, 3] (m), candidates [P] bool
    (the points that may be table) -> [P] m. A plane z = a x + b y + c by least squares through the candidates within
    TABLE_BAND of their median height (the table is most of the workspace, so the median is on it): a real camera's
    calibration error tilts and lifts the table by about the foreground margin, which the fit takes out."""
    z = jnp.where(candidates, points[:, 2], jnp.nan)
    near = candidates & (jnp.abs(points[:, 2] - jnp.nanmedian(z)) < TABLE_BAND)
    a = jnp.concatenate([points[:, :2], jnp.ones_like(points[:, :1])], axis=1) * near[:, None]
    plane = jnp.linalg.solve(a.T @ a + 1e-9 * jnp.eye(3), a.T @ jnp.where(near, points[:, 2], 0.0))
    return points[:, :2] @ plane[:2] + plane[2]


def foreground(observation: Observation, camera: Camera, *, margin: float = FOREGROUND_MARGIN,
               workspace: float = WORKSPACE_HALF_WIDTH, kind=None, colour=None, colour_tol: float = COLOUR_TOL,
               real_depth: bool = False):
    """All pixels as world points and their foreground mask: (points [H*W, 3] m, zero where not foreground,
    valid [H*W] bool): inside the workspace, more than ``margin`` and at most PILE_CEILING above the table. kind:
    keep only pixels of this kind index (``observation.kind``); colour: keep only pixels whose chromaticity is within
    ``colour_tol`` of this RGB's (any scale: [0, 1] or [0, 255]); real_depth: a real camera's depth
    (``sim.sensor``): its 3 x 3 median first (``median_depth``), heights over the table plane fitted from the frame
    (``table_height``) instead of over z = 0, and a workspace WALL_BAND narrower (a few millimetres of calibration
    error put wall tops inside it)."""
    depth = readings(jnp.asarray(observation.depth, jnp.float32))  # the one rule of what is a reading
    depth = (median_depth(depth) if real_depth else depth).reshape(-1)
    uv = jnp.asarray(camera.pixel_centres(), jnp.float32).reshape(-1, 2)
    seen = is_reading(depth)
    points = camera.pixel_to_world(uv, jnp.where(seen, depth, 0.0)).astype(jnp.float32)
    inside = seen & jnp.all(jnp.abs(points[:, :2]) <= workspace - (WALL_BAND if real_depth else 0.0), axis=-1)
    height = points[:, 2] - table_height(points, inside) if real_depth else points[:, 2]
    valid = inside & (height > margin) & (height <= PILE_CEILING)
    if kind is not None:
        valid &= jnp.asarray(observation.kind).reshape(-1) == kind
    if colour is not None:
        rgb = jnp.asarray(observation.rgb, jnp.float32).reshape(-1, 3)
        ref = jnp.asarray(colour, jnp.float32)
        chroma = rgb / jnp.maximum(jnp.sum(rgb, -1, keepdims=True), 1e-6)
        ref_chroma = ref / jnp.maximum(jnp.sum(ref), 1e-6)
        valid &= jnp.linalg.norm(chroma - ref_chroma, axis=-1) <= colour_tol
    return jnp.where(valid[:, None], points, 0.0), valid


def point_cloud(observation: Observation, camera: Camera, *, max_points: int | None = None, **foreground_kw):
    """Depth + camera -> (points [P, 3] world m, zero where invalid; valid [P] bool). P = H * W (every pixel a
    candidate) when ``max_points`` is None, else P = max_points (``pack``). ``foreground_kw``: margin, workspace,
    kind, colour, colour_tol, real_depth of ``foreground``."""
    return pack(*foreground(observation, camera, **foreground_kw), max_points)


def visible_count(observation: Observation, camera: Camera, max_points: int | None, real_depth: bool = False):
    """How many foreground points a frame gives perception to sample from (``point_cloud``'s valid count, at most
    max_points; real_depth: read as a real camera's, ``foreground``): the largest ω it can sample. Traceable: -> []
    int."""
    return jnp.sum(point_cloud(observation, camera, max_points=max_points, real_depth=real_depth)[1])


def visible_points(observation: Observation, camera: Camera, max_points: int | None, real_depth: bool = False) -> int:
    """``visible_count`` of one concrete frame, as a Python int."""
    return int(visible_count(observation, camera, max_points, real_depth))


def pack(points, valid, max_points: int | None):
    """The foreground (points [H*W, 3], valid [H*W]) in max_points slots: foreground pixels packed first, a uniform
    random subset (one fixed permutation, ``PERMUTATION_SEED``) when there are more than max_points; unchanged when
    max_points is None."""
    if max_points is None:
        return points, valid
    perm = jnp.asarray(np.random.default_rng(PERMUTATION_SEED).permutation(valid.shape[0]), jnp.int32)
    (slot,) = jnp.nonzero(valid[perm], size=max_points, fill_value=0)
    kept = jnp.arange(max_points) < jnp.sum(valid)
    return jnp.where(kept[:, None], points[perm[slot]], 0.0), kept


def calibrate(observation: Observation, camera: Camera, *, bin_half_width: float, wall_height: float) -> Camera:
    """The camera's pose refined from one frame of the bin, the way a robot checks its extrinsic calibration (a real
    camera's error, ``sim.sensor``): the table plane fitted inside the bin gives the tilt and the height, and the bin's
    walls, which stand symmetric about the origin, give the sideways offset: the two opposite walls' top points (in
    the top tenth of the wall height) have x (and y) of opposite sign and equal size in the true frame, so half their
    sum is the offset. Medians throughout make it robust to noisy, flying and missing readings; yaw is not estimated.
    observation: its depth [H, W] (m); bin_half_width, wall_height: the bin's inner half-width and wall height (m,
    ``SceneConfig``). Returns the camera whose world frame is the table's, bin centred. ValueError when a wall is not
    in view."""
    depth = np.asarray(observation.depth, np.float64).reshape(-1)
    seen = is_reading(depth)
    points = np.asarray(camera.pixel_to_world(camera.pixel_centres().reshape(-1, 2)[seen], depth[seen]), np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    inner = np.all(np.abs(points[:, :2]) < bin_half_width - WALL_SEARCH, axis=1)
    near = inner & (np.abs(points[:, 2] - np.median(points[inner, 2])) < TABLE_BAND)
    a, b, _ = np.linalg.lstsq(np.c_[points[near, :2], np.ones(near.sum())], points[near, 2], rcond=None)[0]
    normal = np.array([-a, -b, 1.0]) / np.sqrt(a * a + b * b + 1)
    axis = np.cross(normal, [0.0, 0.0, 1.0])  # turn the table's normal onto z
    level = rotation_about(axis, np.arctan2(np.linalg.norm(axis), normal[2]))
    levelled = points @ level.T
    offset = np.zeros(3)
    offset[2] = np.median(levelled[near, 2])
    high = levelled[:, 2] - offset[2] > 0.9 * wall_height  # wall tops: flying pixels lie lower
    for i in (0, 1):
        along = np.abs(levelled[:, 1 - i]) < bin_half_width - WALL_SEARCH
        wall = high & along & (np.abs(np.abs(levelled[:, i]) - bin_half_width) < WALL_SEARCH)
        sides = [wall & (levelled[:, i] > 0), wall & (levelled[:, i] < 0)]
        if min(side.sum() for side in sides) < MIN_WALL_POINTS:
            raise ValueError(f"calibration needs both bin walls across {'xy'[i]} in view: found "
                             f"{[int(side.sum()) for side in sides]} points on them (at least {MIN_WALL_POINTS} each)")
        offset[i] = (np.median(levelled[sides[0], i]) + np.median(levelled[sides[1], i])) / 2
    return Camera(camera.K, level @ camera.rotation, level @ camera.centre - offset, camera.width, camera.height)


def random_start(key, valid) -> jax.Array:
    """A uniformly random index among the valid entries of valid [P] (0 when none is valid) -> int32 []."""
    return jnp.argmax(jnp.where(valid, jax.random.uniform(key, valid.shape), -1.0)).astype(jnp.int32)


@functools.partial(jax.jit, static_argnames="n")
def fps(points, valid, n: int, start):
    """Farthest point sampling. points [P, 3], valid [P] bool, n static, start [] int32 (a valid index) ->
    (indices [n] int32, radius [n] float32 m).

    indices[0] = start; indices[i] is the valid point farthest from indices[:i] (lowest index on ties), and
    radius[i] is that distance: the covering radius of the sample indices[:i] over the valid cloud. radius[0] = inf
    (nothing covers yet); radius is non-increasing. Prefixes: indices[:k] is the size-k FPS sample, and
    ``radius > r`` masks the smallest prefix whose covering radius (the next entry's radius) is at most r. Once every
    valid point is picked, further picks repeat valid points with radius 0. Invalid points are never read.
    """
    pts = jnp.asarray(points, jnp.float32).T  # [3, P]: one contiguous row per coordinate
    valid = jnp.asarray(valid, bool)

    def pick(i, carry):
        min_d2, indices, radius = carry
        d2 = jnp.sum(jnp.square(pts - pts[:, indices[i - 1], None]), axis=0)
        min_d2 = jnp.where(valid, jnp.minimum(min_d2, d2), -jnp.inf)
        far = jnp.argmax(min_d2).astype(jnp.int32)
        return min_d2, indices.at[i].set(far), radius.at[i].set(jnp.sqrt(jnp.maximum(min_d2[far], 0.0)))

    init = (jnp.where(valid, jnp.inf, -jnp.inf), jnp.zeros(n, jnp.int32).at[0].set(start),
            jnp.full(n, jnp.inf, jnp.float32))
    _, indices, radius = jax.lax.fori_loop(1, n, pick, init)
    return indices, radius


def recentre(particles, points, valid, r_center):
    """Move each particle to the mean of the valid cloud points within r_center (m) of it (inclusive, so a particle
    on a cloud point always has one). particles [n, 3], points [P, 3], valid [P] -> [n, 3]; a particle with no
    point in reach stays put. One particle at a time (``lax.map``), so memory stays O(P), never [n, P]."""
    pts = jnp.asarray(points, jnp.float32).T  # [3, P]
    r2 = jnp.square(r_center)

    def centre(particle):
        near = valid & (jnp.sum(jnp.square(pts - particle[:, None]), axis=0) <= r2)
        count = jnp.sum(near)
        total = jnp.sum(jnp.where(near, pts, 0.0), axis=1)
        return jnp.where(count > 0, total / jnp.maximum(count, 1), particle)

    return jax.lax.map(centre, jnp.asarray(particles, jnp.float32))


def _particles(points, valid, depth, omega, key, capacity: int, r_center) -> Particles:
    """h on a packed cloud (points [P, 3], valid [P]) of a depth image [H, W] (no reading in it at all is an error)."""
    n_points = jnp.sum(valid).astype(jnp.int32)
    omega = jnp.asarray(omega, jnp.int32)
    indices, radius = fps(points, valid, capacity + 1, random_start(key, valid))  # one extra pick: r(ω = capacity)
    r_omega = radius[jnp.clip(omega, 0, capacity)]  # covering radius of the ω-sample
    if r_center is None:
        r_center = jnp.minimum(R_CENTER_MAX, 0.5 * r_omega)
    positions = recentre(points[indices[:capacity]], points, valid, r_center)
    error = (jnp.where(~jnp.any(is_reading(depth)), NO_DEPTH, 0)
             | jnp.where(n_points == 0, EMPTY_FOREGROUND, 0)
             | jnp.where((omega < 1) | (omega > capacity), BAD_OMEGA, 0)
             | jnp.where((n_points > 0) & (n_points < omega), TOO_FEW_POINTS, 0)).astype(jnp.int32)
    mask = (jnp.arange(capacity) < omega) & (error == 0)
    return Particles(jnp.where(mask[:, None], positions, 0.0), mask, jnp.where(error == 0, r_omega, 0.0), n_points,
                     error)


@functools.partial(jax.jit, static_argnames=("camera", "capacity", "max_points", "real_depth"))
def _sample_particles(observation, camera, omega, key, capacity, max_points, r_center, foreground_kw, real_depth):
    points, valid = point_cloud(observation, camera, max_points=max_points, real_depth=real_depth, **foreground_kw)
    return _particles(points, valid, observation.depth, omega, key, capacity, r_center)


@functools.partial(jax.jit, static_argnames="capacity")
def cloud_particles(points, valid, depth, omega, key, capacity: int) -> Particles:
    """h on a cloud already made (``point_cloud``'s points [P, 3], valid [P]) of the depth image [H, W]: the
    particles of ``sample_particles`` without computing the cloud again."""
    return _particles(points, valid, depth, omega, key, capacity, None)


def _nearest_kinds(points, valid, kind_image, particles: Particles):
    """Each particle's kind: that of the nearest labelled foreground pixel (points [H*W, 3], valid [H*W], kind_image
    [H, W]) on the table plane -> [capacity] int32, -1 where masked or when no pixel has a kind."""
    kinds = jnp.asarray(kind_image, jnp.int32).reshape(-1)
    labelled = valid & (kinds >= 0)
    x, y = points[:, 0], points[:, 1]

    def nearest(particle):
        d2 = jnp.where(labelled, jnp.square(x - particle[0]) + jnp.square(y - particle[1]), jnp.inf)
        return kinds[jnp.argmin(d2)]

    found = jax.lax.map(nearest, particles.positions)
    return jnp.where(particles.mask & jnp.any(labelled), found, -1).astype(jnp.int32)


@functools.partial(jax.jit, static_argnames=("camera", "real_depth"))
def particle_kinds(observation: Observation, camera: Camera, particles: Particles, real_depth: bool = False):
    """Each particle's piece kind: the kind (``observation.kind``) of the foreground pixel nearest to it on the table
    plane -> [capacity] int32, -1 where masked or when no foreground pixel has a kind. For Sort's objective, which
    scores each kind's particles against its own goal (``objective.kind_objective``)."""
    return _nearest_kinds(*foreground(observation, camera, real_depth=real_depth), observation.kind, particles)


class Perceived(NamedTuple):
    """One frame, perceived once: the point cloud (points [P, 3] m, valid [P]; the planner's pushes start through
    it), the particles h(y, ω) and, where asked (Sort), each particle's kind [capacity] (else None)."""

    points: jax.Array
    valid: jax.Array
    particles: Particles
    kinds: jax.Array | None


def perceive(observation: Observation, camera: Camera, omega, key, capacity: int, *, max_points: int | None,
             real_depth: bool = False, kind=None, with_kinds: bool = False) -> Perceived:
    """The frame's foreground computed once and everything a decision reads from it (``Perceived``): the cloud of
    ``point_cloud``, the particles of ``sample_particles`` at ω (may be traced) in capacity slots and, with_kinds,
    ``particle_kinds``. kind: only the pieces of this kind index (may be traced; None: every piece). Traceable;
    errors are in ``particles.error``."""
    points, valid = foreground(observation, camera, real_depth=real_depth, kind=kind)
    cloud = pack(points, valid, max_points)
    particles = _particles(*cloud, observation.depth, omega, key, capacity, None)
    kinds = _nearest_kinds(points, valid, observation.kind, particles) if with_kinds else None
    return Perceived(*cloud, particles, kinds)


def describe_error(error: int, omega=None, capacity=None, n_points=None) -> str:
    """A readable list of the problems in a concrete ``Particles.error`` ('' when 0)."""
    problems = []
    if error & NO_DEPTH:
        problems.append(f"the depth image has no reading (every pixel 0, NaN, infinite, negative or beyond "
                        f"{NO_READING:g} m: a depth in millimetres reads as none; give metres)")
    if error & EMPTY_FOREGROUND:
        problems.append(f"empty foreground: no point is above the table margin and at most {PILE_CEILING:g} m above "
                        "the table (within the workspace, of the requested kind / colour)")
    if error & BAD_OMEGA:
        problems.append(f"omega={omega} is outside [1, capacity={capacity}]")
    if error & TOO_FEW_POINTS:
        problems.append(f"too few foreground points: {n_points} points for omega={omega}")
    return "; ".join(problems)


def check_particles(particles: Particles, omega, capacity, what: str) -> None:
    """Raise a ValueError naming the problem when any of concrete ``particles`` (one set, or a batch [B]: then the
    failing indices are named too) has error bits. omega: the ω asked for (an int, or [B]); capacity: the slots."""
    error = np.asarray(particles.error)
    if not error.any():
        return
    bad = np.flatnonzero(error)
    first = int(bad[0]) if error.ndim else ()
    where = f"{what} {bad.tolist()}: " if error.ndim else f"{what}: "
    raise ValueError(where + describe_error(int(error[first]), int(np.asarray(omega)[first]), capacity,
                                            int(np.asarray(particles.n_points)[first])))


def sample_particles(observation: Observation, camera: Camera, omega, key, capacity: int, *,
                     max_points: int | None = None, r_center=None, margin: float = FOREGROUND_MARGIN,
                     workspace: float = WORKSPACE_HALF_WIDTH, kind=None, colour=None,
                     colour_tol: float = COLOUR_TOL, real_depth: bool = False) -> Particles:
    """h(y, ω): one observation (depth [H, W], and kind / rgb when restricting) -> Particles with capacity slots, the
    first ω valid. omega: int, may be traced (``jax.vmap`` over ω values equals calling per ω); key: FPS start;
    max_points: see ``point_cloud`` (at 256 x 256, 8192 made h about 5 times faster on an H200); r_center:
    re-centring radius (m), default min(R_CENTER_MAX, 0.5 r(ω)) with r(ω) the covering radius of the ω-sample, 0 to
    disable; margin, workspace, kind, colour, colour_tol, real_depth: see ``foreground``. Raises ValueError naming the
    problem when the result is concrete and the input bad (no depth reading at all, empty foreground, ω outside [1,
    capacity], fewer foreground points than ω); traced, ``Particles.error`` says it.
    """
    if not isinstance(capacity, int | np.integer) or not 1 <= capacity <= MAX_CAPACITY:
        raise ValueError(f"capacity must be an int in [1, {MAX_CAPACITY}], got {capacity!r}")
    if np.ndim(omega):
        raise ValueError(f"omega must be one count of particles (jax.vmap over several), got shape {np.shape(omega)}")
    for name, value, low in (("margin", margin, 0.0), ("workspace", workspace, 0.0), ("colour_tol", colour_tol, 0.0),
                             ("r_center", r_center, 0.0)):
        if value is not None and not isinstance(value, jax.core.Tracer) and not (
                np.ndim(value) == 0 and np.isfinite(value) and value >= low):
            raise ValueError(f"{name} must be a finite number >= {low:g} (m), got {value!r}")
    if kind is not None and not isinstance(kind, int | np.integer | jax.Array):
        raise ValueError(f"kind must be a piece kind's index (an int, as observation.kind holds), got {kind!r}")
    if max_points is not None and (not isinstance(max_points, int | np.integer) or max_points < 1):
        raise ValueError(f"max_points must be None or a positive int, got {max_points!r}")
    if isinstance(omega, jax.core.Tracer):
        if not jnp.issubdtype(omega.dtype, jnp.integer):
            raise TypeError(f"a traced omega must be an integer array (a count of particles), got {omega.dtype}")
    elif not np.all(np.mod(np.asarray(omega, np.float64), 1) == 0):
        raise ValueError(f"omega must be a whole number of particles, got {omega!r}")
    if tuple(np.shape(observation.depth)) != (camera.height, camera.width):
        raise ValueError(f"depth image has shape {np.shape(observation.depth)}, the camera expects "
                         f"{(camera.height, camera.width)} (vmap sample_particles over a batch of observations)")
    observation = observation._replace(**{name: jnp.asarray(x) for name, x in observation._asdict().items()
                                          if isinstance(x, list | tuple)})  # nested lists: arrays, as jit needs
    foreground_kw = dict(margin=margin, workspace=workspace, kind=kind, colour=colour, colour_tol=colour_tol)
    out = _sample_particles(observation, camera, omega, key, int(capacity), max_points and int(max_points), r_center,
                            foreground_kw, bool(real_depth))
    if not isinstance(out.error, jax.core.Tracer):
        check_particles(out, omega, capacity, "sample_particles")
    return out
