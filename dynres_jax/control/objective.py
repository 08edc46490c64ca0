"""Task objective c(z, y_g), the evaluation metric d and the share of pieces inside the goal (goals: ``goals``).

Paper mapping (PAPER.md "Task objective c(z, y_g)" and "Tasks"): with P the particles projected to the image and
Q the goal-mask pixels,

    c = ( Σ_{p∈P} SDF(p) + Σ_{q∈Q'} min_{p∈P} |p − q| ) / ω

- SDF is the goal's signed distance field (reference code): negative inside the goal, positive outside, looked up
  with bilinear interpolation so c is differentiable w.r.t. the particle positions.
- Q' is the first ``min(5 ω, |Q|)`` points of a fixed farthest-point subsample of Q (``Goal.samples``, FPS order, so
  every prefix is itself an FPS sample); ω is the number of valid particles. Dividing by ω follows the reference.
- ``distribution_distance`` (the paper's metric d, as the supplement defines it) is unsigned: every foreground pixel's
  distance to the goal plus every goal pixel's distance to the foreground, over the foreground pixel count;
  ``inside_share`` the share of pieces whose centre projects inside the goal
  (Gather's success measure).

Units: goal builders take metres on the table plane (z = 0, world frame); everything inside a ``Goal`` and every
term of c and d is in pixels of the camera's image (a pixel (row v, column u) has its centre at (u + 0.5, v + 0.5),
``sim/camera.py``). Goal masks are built on the host in NumPy / OpenCV; c, d and ``inside_share`` are pure JAX over
padded particle sets with masks (masked particles are inert), so they ``jax.vmap`` over particle sets and goals.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import Partial

from dynres_jax.errors import InputError
from dynres_jax.models.propagation import gather_rows
from dynres_jax.perception import foreground
from dynres_jax.sim.camera import Camera, Observation

if TYPE_CHECKING:  # the goals import c (each goal carries its cost: ``Goal.planner_cost``), not the other way round
    from dynres_jax.control.goals import Goal, KindGoals

SAMPLES_PER_PARTICLE = 5  # |Q'| = min(5 ω, |Q|) (reference code)
MAX_PAIRS = 20_000_000  # c's coverage term evaluates at most this many (goal sample, particle) distances at once


# ---------------------------------------------------------------------------------------------------------------
# c, d and the success share (JAX)
# ---------------------------------------------------------------------------------------------------------------

def bilinear(image, uv):
    """Bilinear interpolation of image [H, W] at pixel coordinates uv [..., 2] (u, v; pixel centres at +0.5)
    -> [...]. Coordinates are clamped to the outermost pixel centres (constant outside, zero gradient there)."""
    H, W = image.shape
    x = jnp.clip(uv[..., 0] - 0.5, 0.0, W - 1.0)
    y = jnp.clip(uv[..., 1] - 0.5, 0.0, H - 1.0)
    x0 = jnp.clip(jnp.floor(x), 0, W - 2)
    y0 = jnp.clip(jnp.floor(y), 0, H - 2)
    fx, fy = x - x0, y - y0
    i, j = y0.astype(jnp.int32), x0.astype(jnp.int32)
    top = (1 - fx) * image[i, j] + fx * image[i, j + 1]
    bottom = (1 - fx) * image[i + 1, j] + fx * image[i + 1, j + 1]
    return (1 - fy) * top + fy * bottom


def _root(d2):
    """sqrt(d2) for squared distances d2 >= 0, with a zero (not NaN) gradient at d2 = 0."""
    positive = d2 > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, d2, 1.0)), 0.0)


def _argmin_nonnegative(values):
    """The index of the smallest of values [P] (each >= 0 or +inf) by one plain integer min: a non-negative float's
    bits order as an int32 does, so each value's bits with the lowest ceil(log2 P) replaced by its index reduce to
    the index of the smallest (on a GPU several times faster than ``argmin``'s two-operand reduction). Values within
    2^ceil(log2 P) units in the last place of the smallest (a relative 1.5e-5 for P = 100) count as ties, which go
    to the lower index."""
    p = values.shape[-1]
    low = (1 << max(1, (p - 1).bit_length())) - 1
    packed = (jax.lax.bitcast_convert_type(values.astype(jnp.float32), jnp.int32) & ~low) | jnp.arange(p)
    return jnp.min(packed, axis=-1) & low


def _cost(pixels, valid, goal: Goal):
    """The formula of c on points at pixel coordinates pixels [P, 2] with valid [P] -> scalar (pixels)."""
    omega = jnp.sum(valid)
    pixels = jnp.where(valid[:, None], pixels, 0.0)
    sdf_term = jnp.sum(jnp.where(valid, bilinear(goal.distance, pixels), 0.0))
    Q, P = goal.samples.shape[0], pixels.shape[0]
    active = goal.sample_mask & (jnp.arange(Q) < SAMPLES_PER_PARTICLE * omega)

    def nearest(q):
        """The index of the valid p nearest to q, found without gradients (a tie goes to the lower index)."""
        u, v = jax.lax.stop_gradient(pixels).T  # [P] each: a sum of two squares, not a reduction over an axis of 2
        return _argmin_nonnegative(jnp.where(valid, jnp.square(u - q[0]) + jnp.square(v - q[1]), jnp.inf))

    index = jax.lax.map(nearest, goal.samples, batch_size=max(1, min(Q, MAX_PAIRS // P)))  # [Q]
    # differentiated through the one nearest p of each goal sample (the backward pass touches Q points, not Q x P),
    # its gradients summed repeatably (``gather_rows``)
    nearest_distance = _root(jnp.sum(jnp.square(gather_rows(pixels, index) - goal.samples), axis=-1))
    coverage_term = jnp.sum(jnp.where(active, nearest_distance, 0.0))
    return (sdf_term + coverage_term) / jnp.maximum(omega, 1)


def objective(positions, mask, goal: Goal, camera: Camera):
    """Task objective c: particles positions [N, 3] (world, m) with mask [N] bool -> scalar (pixels).

    c = (Σ_p SDF(p) + Σ_{q∈Q'} min_p |p − q|) / ω over the ω valid particles projected by ``camera``, Q' the first
    min(5 ω, Q) valid goal samples. Masked particles are inert (any value, NaN included). Differentiable w.r.t.
    positions; ``jax.vmap`` over particle sets and goals. ValueError (at trace time) for positions not [N >= 1, 3]
    or a mask not [N]; InputError for a concrete mask with no valid particle (traced, ω = 0 gives 0: a jitted
    caller masks such sets itself, as the planner's error bits do)."""
    if jnp.ndim(positions) != 2 or jnp.shape(positions)[-1] != 3 or jnp.shape(positions)[0] < 1 or jnp.shape(
            mask) != jnp.shape(positions)[:1]:
        raise ValueError(f"objective: positions must be [N >= 1, 3] (m) and mask [N], got {jnp.shape(positions)} "
                         f"and {jnp.shape(mask)}")
    if not isinstance(mask, jax.core.Tracer) and not np.asarray(mask, bool).any():
        raise InputError("objective: no valid particle (the mask is all False); c of an empty set is undefined")
    return _objective(positions, mask, goal, camera)


@functools.partial(jax.jit, static_argnames="camera")
def _objective(positions, mask, goal: Goal, camera: Camera):
    mask = jnp.asarray(mask, bool)
    positions = jnp.where(mask[:, None], jnp.asarray(positions, jnp.float32), 0.0)
    uv, _ = camera.world_to_pixel(positions)
    return _cost(uv, mask, goal)


def _intrusion(pixels, valid, avoid):
    """How deep points at pixels [P, 2] (finite) with valid [P] lie inside a region of signed distance field avoid
    [H, W]: Σ_p max(0, -SDF(p)) / ω (pixels; 0 outside the region, and when ω = 0)."""
    depth = jax.nn.relu(-bilinear(avoid, pixels))
    return jnp.sum(jnp.where(valid, depth, 0.0)) / jnp.maximum(jnp.sum(valid), 1)


@functools.partial(jax.jit, static_argnames="camera")
def kind_costs(positions, mask, kinds, goals: KindGoals, camera: Camera):
    """c_k of each kind's particles: c against its own goal plus goals.mixing × its intrusion into the region it must
    keep out of (``KindGoals.avoid``: the other kinds' goals; ``_intrusion``): positions [N, 3] (m), mask [N] bool,
    kinds [N] int (each particle's kind index) -> [K] (pixels; 0 for a kind with no particle). Each is a mean over
    that kind's particles, so kinds weigh alike whatever their particle counts."""
    mask = jnp.asarray(mask, bool)
    uv, _ = camera.world_to_pixel(jnp.where(mask[:, None], jnp.asarray(positions, jnp.float32), 0.0))

    def one(goal, avoid, k):  # c (``objective``) and the intrusion of one kind, on the particles projected once
        mine = mask & (kinds == k)
        return _cost(uv, mine, goal) + goals.mixing * _intrusion(uv, mine, avoid)

    return jax.vmap(one)(goals.goals, goals.avoid, jnp.arange(goals.hold.shape[0]))


@functools.partial(jax.jit, static_argnames="camera")
def kind_objective(positions, mask, kinds, goals: KindGoals, camera: Camera, baseline):
    """Sort's objective -> scalar (pixels): c_k (``kind_costs``) summed over the pursued kinds, plus, for each held
    kind, max(0, c_k - baseline_k): what the particles lost against their goal since the baseline [K] (c_k of the
    particles now), so a push that scatters a resting pile costs what it scatters and a resting pile never draws the
    push to itself."""
    costs = kind_costs(positions, mask, kinds, goals, camera)
    return jnp.sum(jnp.where(goals.hold, jax.nn.relu(costs - baseline), costs))


def squared_distance_to(mask):
    """Exact squared Euclidean distance (pixels²) from every pixel centre of mask [H, W] bool's grid to the nearest
    True pixel centre -> [H, W] float32 (0 on True pixels, +inf everywhere when none is True). Separable: the
    nearest True pixel of each column, then the best column for each pixel (O(H²W + HW²), memory O(HW))."""
    mask = jnp.asarray(mask, bool)
    H, W = mask.shape
    rows, cols = jnp.arange(H, dtype=jnp.float32), jnp.arange(W, dtype=jnp.float32)
    column = jax.lax.map(lambda i: jnp.min(jnp.where(mask, jnp.square(rows - i)[:, None], jnp.inf), axis=0), rows)
    return jax.lax.map(lambda g: jnp.min(g[None, :] + jnp.square(cols[:, None] - cols[None, :]), axis=1), column)


@jax.jit
def _mask_distance(current, goal_mask):
    """d of two pixel masks [H, W] -> scalar (pixels): unsigned, each summed over its pixels, over |current|."""
    to_goal = jnp.sqrt(squared_distance_to(goal_mask))
    to_current = jnp.sqrt(squared_distance_to(current))
    total = jnp.sum(jnp.where(current, to_goal, 0.0)) + jnp.sum(jnp.where(goal_mask, to_current, 0.0))
    return jnp.where(jnp.any(current), total / jnp.maximum(jnp.sum(current), 1), jnp.inf)


def distribution_distance(observation_or_mask, goal: Goal, camera: Camera, **foreground_kw):
    """The paper's metric d (supplement, "Distribution Distance"), unsigned -> scalar (pixels).

    d = (Σ_{f∈F} min_{q∈Q} |f − q| + Σ_{q∈Q} min_{f∈F} |f − q|) / |F|, with F the foreground pixels, Q every goal
    pixel (not a subsample) and distances between pixel centres, exact (``squared_distance_to``). A
    foreground pixel inside the goal adds 0 (no signed distance). The sum is divided by the foreground pixel count, as
    the reference divides c by ω: a mean per foreground pixel. observation_or_mask: an Observation (its foreground by
    ``perception.foreground``, ``foreground_kw`` passed on: kind= for one kind of a Sort scene) or a foreground
    mask [H, W] bool. +inf when there is no foreground pixel. ``jax.vmap`` over observations and goals."""
    _check_goal_size(goal, camera)
    return _mask_distance(_foreground_mask(observation_or_mask, camera, foreground_kw), goal.mask)


def _check_goal_size(goal: Goal, camera: Camera) -> None:
    """ValueError when the goal's mask is not the camera's image size (a goal made for another camera)."""
    if jnp.shape(goal.mask)[-2:] != (camera.height, camera.width):
        raise ValueError(f"the goal was made for {jnp.shape(goal.mask)[-1]} x {jnp.shape(goal.mask)[-2]} images, the "
                         f"camera's are {camera.width} x {camera.height}: make the goal with this camera")


def _foreground_mask(observation_or_mask, camera: Camera, foreground_kw: dict):
    """An Observation's foreground (``perception.foreground``) or a given mask, checked, as [H, W] bool."""
    if isinstance(observation_or_mask, Observation):
        _, valid = foreground(observation_or_mask, camera, **foreground_kw)
        return valid.reshape(camera.height, camera.width)
    current = jnp.asarray(observation_or_mask, bool)
    if current.shape != (camera.height, camera.width):
        raise ValueError(f"foreground mask has shape {current.shape}, the camera's image is "
                         f"{(camera.height, camera.width)}")
    return current


def seen_inside(observation_or_mask, goal: Goal, camera: Camera, **foreground_kw):
    """What a camera can tell of success: the share of the frame's foreground pixels that lie on goal pixels -> scalar
    in [0, 1] (0 without foreground). observation_or_mask: as ``distribution_distance`` takes it (``foreground_kw``:
    real_depth= for a real camera's frame). ``jax.vmap`` over observations and goals."""
    _check_goal_size(goal, camera)
    current = _foreground_mask(observation_or_mask, camera, foreground_kw)
    return jnp.sum(current & goal.mask) / jnp.maximum(jnp.sum(current), 1)


@functools.partial(jax.jit, static_argnames="camera")
def inside_share(piece_pos, piece_mask, goal: Goal, camera: Camera):
    """Success share: pieces piece_pos [N, 3] (world centres, m) with piece_mask [N] bool -> scalar in [0, 1], the
    share of valid pieces whose centre projects to a goal pixel (0 when no piece is valid; NaN when a valid piece's
    position is NaN or infinite: no share to read). ValueError (at trace time) for positions not [N, 3], a mask not
    [N] or a goal of another camera's size."""
    if jnp.ndim(piece_pos) != 2 or jnp.shape(piece_pos)[-1] != 3 or jnp.shape(piece_mask) != jnp.shape(piece_pos)[:1]:
        raise ValueError(f"inside_share: piece_pos must be [N, 3] (m) and piece_mask [N], got {jnp.shape(piece_pos)} "
                         f"and {jnp.shape(piece_mask)}")
    _check_goal_size(goal, camera)
    piece_mask = jnp.asarray(piece_mask, bool)
    finite = jnp.all(jnp.isfinite(jnp.asarray(piece_pos)) | ~piece_mask[:, None])
    uv, _ = camera.world_to_pixel(jnp.where(piece_mask[:, None], jnp.asarray(piece_pos, jnp.float32), 0.0))
    u, v = jnp.floor(uv[:, 0]).astype(jnp.int32), jnp.floor(uv[:, 1]).astype(jnp.int32)
    in_image = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    hit = piece_mask & in_image & goal.mask[jnp.clip(v, 0, camera.height - 1), jnp.clip(u, 0, camera.width - 1)]
    return jnp.where(finite, jnp.sum(hit) / jnp.maximum(jnp.sum(piece_mask), 1), jnp.nan)


def _cost_of(camera, goal, positions, mask):
    return objective(positions, mask, goal, camera)


def _kind_cost_of(camera, goals, kinds, baseline, positions, mask):
    return kind_objective(positions, mask, kinds, goals, camera, baseline)


@functools.cache
def _camera_cost(camera, per_kind: bool):
    """One function object per camera: the planner's compile cache keys a cost by its function's identity."""
    return functools.partial(_kind_cost_of if per_kind else _cost_of, camera)


def planner_cost(camera, goal: Goal, *per_kind) -> Partial:
    """c as the planner's cost ``(positions, mask) -> []`` against ``goal`` (a pytree argument, so a new goal for the
    same camera reuses the compiled plan); with ``per_kind`` = (kinds [N], baseline [K]), ``kind_objective`` against
    KindGoals."""
    return Partial(_camera_cost(camera, bool(per_kind)), goal, *per_kind)

