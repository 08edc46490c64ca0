"""Task objective c(z, y_g), the evaluation metric d, goal masks and the Gather success share.

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
from typing import NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import SceneConfig
from dynres_jax.perception import foreground, fps
from dynres_jax.sim.camera import Camera, Observation

BIN_HALF_WIDTH = SceneConfig().bin_half_width  # m: goals must lie inside the bin [-b, b]^2
SAMPLES_PER_PARTICLE = 5  # |Q'| = min(5 ω, |Q|) (reference code)
MAX_PAIRS = 20_000_000  # c's coverage term evaluates at most this many (goal sample, particle) distances at once
TEXT_OVERSAMPLE = 8  # text is drawn on a canvas this many times finer than the image, then sampled per pixel


class Goal(NamedTuple):
    """A goal region in the camera's pixel grid (a pytree: pass it through jit / vmap).

    mask [H, W] bool: goal pixels; distance [H, W] float32: signed distance field in pixels (negative inside, positive
    outside; a pixel's distance to the nearest pixel centre of the other set); samples [Q, 2] float32: pixel
    coordinates (u, v) of an FPS subsample of the goal pixels' centres, in FPS order; sample_mask [Q] bool: valid
    samples (all but the tail when the goal has fewer than Q pixels).
    """

    mask: jax.Array
    distance: jax.Array
    samples: jax.Array
    sample_mask: jax.Array


class KindGoals(NamedTuple):
    """One goal per piece kind (Sort), a pytree like ``Goal``: goals, a Goal whose every leaf has a leading axis [K]
    (goal k for kind k); hold [K] bool: kinds only kept from getting worse, not pursued (``kind_objective``)."""

    goals: Goal
    hold: jax.Array


def stack(goals) -> Goal:
    """A sequence of Goals of one camera -> one Goal with a leading axis (a batch of episodes' goals, or kinds')."""
    return jax.tree.map(lambda *x: jnp.stack(x), *goals)


def stack_goals(goals, hold=None) -> KindGoals:
    """A sequence of K Goals of one camera (goal k for kind k) and hold [K] bool (default: pursue every kind) ->
    KindGoals."""
    hold = np.zeros(len(goals), bool) if hold is None else np.asarray(hold, bool)
    if hold.shape != (len(goals),):
        raise ValueError(f"hold must have one flag per goal ({len(goals)}), got shape {hold.shape}")
    return KindGoals(stack(goals), jnp.asarray(hold))


# ---------------------------------------------------------------------------------------------------------------
# Goal masks (host, NumPy / OpenCV). Inputs in metres on the table plane; outputs [H, W] bool.
# ---------------------------------------------------------------------------------------------------------------

def _table_xy(camera: Camera) -> np.ndarray:
    """[H, W, 2] world (x, y) in metres where each pixel centre's ray meets the table (NaN where it never does)."""
    d = np.asarray(camera.ray_directions(camera.pixel_centres()), np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] < 0, -camera.centre[2] / d[..., 2], np.nan)
    return camera.centre[:2] + t[..., None] * d[..., :2]


def _project(camera: Camera, xy) -> np.ndarray:
    """Table points xy [..., 2] (m) -> pixel coordinates [..., 2]."""
    xy = np.asarray(xy, np.float64)
    uv, _ = camera.world_to_pixel(np.concatenate([xy, np.zeros_like(xy[..., :1])], axis=-1))
    return np.asarray(uv, np.float64)


def _check_positive(name: str, value) -> None:
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be positive, got {value}")


def _check_in_view(what: str, camera: Camera, outline_xy, bin_half_width: float) -> None:
    """outline_xy [K, 2] (m): points whose hull holds the goal. Every one must be inside the bin and the image."""
    outline_xy = np.asarray(outline_xy, np.float64)
    if not np.all(np.isfinite(outline_xy)):
        raise ValueError(f"{what}: coordinates must be finite")
    reach = float(np.max(np.abs(outline_xy)))
    if reach > bin_half_width + 1e-9:
        raise ValueError(f"{what} reaches outside the bin: |x| or |y| up to {reach:.4f} m > {bin_half_width} m")
    uv = _project(camera, outline_xy)
    if np.any(uv < 0) or np.any(uv[:, 0] > camera.width) or np.any(uv[:, 1] > camera.height):
        raise ValueError(f"{what} reaches outside the camera image ({camera.width} x {camera.height} pixels)")


def _check_nonempty(what: str, mask: np.ndarray) -> np.ndarray:
    if not mask.any():
        raise ValueError(f"{what} covers no pixel centre (goal has no pixels): make it larger")
    return mask


def _metres_per_pixel(camera: Camera, xy) -> float:
    """Side of one pixel on the table near xy (m), from the projection of a small cross."""
    step = 1e-3
    uv = _project(camera, np.asarray(xy, np.float64) + [[0, 0], [step, 0], [0, step]])
    return step / float(np.mean(np.linalg.norm(uv[1:] - uv[0], axis=-1)))


def disc_goal(camera: Camera, centre_xy, radius: float, *, bin_half_width: float = BIN_HALF_WIDTH) -> np.ndarray:
    """Gather goal: pixels whose centre's table point lies within ``radius`` (m) of ``centre_xy`` [2] (m).
    -> [H, W] bool. ValueError for radius <= 0, a disc reaching outside the bin or image, or one with no pixels."""
    _check_positive("disc radius", radius)
    centre = np.asarray(centre_xy, np.float64).reshape(2)
    angle = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    outline = centre + radius * np.stack([np.cos(angle), np.sin(angle)], -1)
    _check_in_view("disc goal", camera, outline, bin_half_width)  # the outline holds the 4 axis extremes
    inside = np.linalg.norm(_table_xy(camera) - centre, axis=-1) <= radius
    return _check_nonempty("disc goal", inside)


def polygon_goal(camera: Camera, vertices_xy, *, bin_half_width: float = BIN_HALF_WIDTH) -> np.ndarray:
    """Pixels whose centre's table point is inside the simple polygon vertices_xy [K, 2] (m, K >= 3, either
    orientation; even-odd crossing rule). -> [H, W] bool. ValueError for fewer than 3 vertices, a polygon reaching
    outside the bin or image, or one with no pixels."""
    v = np.asarray(vertices_xy, np.float64)
    if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3:
        raise ValueError(f"polygon vertices must be [K >= 3, 2], got shape {v.shape}")
    _check_in_view("polygon goal", camera, v, bin_half_width)
    xy = _table_xy(camera)
    x, y = xy[..., 0], xy[..., 1]
    inside = np.zeros(x.shape, bool)
    for (x0, y0), (x1, y1) in zip(v, np.roll(v, -1, axis=0), strict=True):
        straddles = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= straddles & (x < x_cross)
    return _check_nonempty("polygon goal", inside)


def random_polygon_goal(rng: np.random.Generator, camera: Camera, *, n_vertices=(3, 8), radius=(0.04, 0.1),
                        bin_half_width: float = BIN_HALF_WIDTH) -> np.ndarray:
    """A random star-shaped polygon goal: n vertices (n uniform in the inclusive range ``n_vertices``) at jittered,
    increasing angles around a centre, each at a distance uniform in ``radius`` (m); the centre is uniform over the
    positions that keep the polygon in the bin. -> [H, W] bool."""
    lo, hi = int(n_vertices[0]), int(n_vertices[1])
    if lo < 3 or hi < lo:
        raise ValueError(f"n_vertices must be a range (lo, hi) with 3 <= lo <= hi, got {n_vertices}")
    r_lo, r_hi = float(radius[0]), float(radius[1])
    _check_positive("random polygon radius", r_lo)
    if r_hi < r_lo or r_hi >= bin_half_width:
        raise ValueError(f"random polygon radius range {radius} must satisfy lo <= hi < bin_half_width")
    n = int(rng.integers(lo, hi + 1))
    angle = rng.uniform(0, 2 * np.pi) + 2 * np.pi * (np.arange(n) + 0.8 * rng.uniform(size=n)) / n
    r = rng.uniform(r_lo, r_hi, n)
    offsets = r[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    centre = rng.uniform(-bin_half_width + np.abs(offsets).max(0), bin_half_width - np.abs(offsets).max(0))
    return polygon_goal(camera, centre + offsets, bin_half_width=bin_half_width)


def _draw_text(text: str, font: int, scale: float, thickness: int) -> np.ndarray:
    """The text drawn by cv2.putText on a canvas with a margin -> [h, w] bool (canvas rows down, columns right)."""
    (w, h), base = cv2.getTextSize(text, font, scale, thickness)
    pad = 2 * thickness + 4
    canvas = np.zeros((h + base + 2 * pad, w + 2 * pad), np.uint8)
    cv2.putText(canvas, text, (pad, pad + h), font, scale, 255, thickness, cv2.LINE_8)
    return canvas > 0


def text_goal(camera: Camera, text: str, centre_xy, height_m: float, font: int = cv2.FONT_HERSHEY_SIMPLEX,
              thickness_m: float | None = None, *, bin_half_width: float = BIN_HALF_WIDTH) -> np.ndarray:
    """Redistribute goal: ``text`` (letters, digits, any characters OpenCV's Hershey fonts draw) as a mask.

    The text is drawn with cv2.putText (``font``, stroke ``thickness_m`` metres, default height_m / 5) on a canvas
    ``TEXT_OVERSAMPLE`` times finer than the image, scaled so its ink is ``height_m`` metres tall (to within a canvas
    pixel) and its ink bounding box is centred on ``centre_xy`` [2] (m); the image's x axis is the text's left to
    right, +y its up. A pixel is in the goal when its centre's table point falls on ink. -> [H, W] bool.
    ValueError for empty text, non-positive height or thickness, text reaching outside the bin or image, no pixels.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"text goal: text must be a non-empty string, got {text!r}")
    undrawable = sorted({c for c in text if not " " <= c <= "~"})
    if undrawable:  # OpenCV's Hershey fonts draw printable ASCII and turn anything else into "?"
        raise ValueError(f"text goal: OpenCV's fonts cannot draw {undrawable} (printable ASCII only)")
    _check_positive("text height_m", height_m)
    thickness_m = height_m / 5 if thickness_m is None else thickness_m
    _check_positive("text thickness_m", thickness_m)
    centre = np.asarray(centre_xy, np.float64).reshape(2)
    res = _metres_per_pixel(camera, centre) / TEXT_OVERSAMPLE  # metres per canvas pixel
    thickness = max(1, round(thickness_m / res))
    scale = 1.0
    for _ in range(2):  # ink height is nearly proportional to the scale: two rescalings land within a pixel
        rows = np.flatnonzero(_draw_text(text, font, scale, thickness).any(axis=1))
        scale *= height_m / res / (rows[-1] - rows[0] + 1)
    ink = _draw_text(text, font, scale, thickness)
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    half = np.array([cols[-1] - cols[0] + 1, rows[-1] - rows[0] + 1]) * res / 2  # ink half-extent (x, y), m
    corners = centre + half * np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]])
    _check_in_view(f"text goal {text!r}", camera, corners, bin_half_width)
    xy = _table_xy(camera)
    col = np.round((cols[0] + cols[-1]) / 2 + (xy[..., 0] - centre[0]) / res)
    row = np.round((rows[0] + rows[-1]) / 2 - (xy[..., 1] - centre[1]) / res)
    on_canvas = (col >= 0) & (col < ink.shape[1]) & (row >= 0) & (row < ink.shape[0])
    inside = on_canvas & ink[np.where(on_canvas, row, 0).astype(int), np.where(on_canvas, col, 0).astype(int)]
    return _check_nonempty(f"text goal {text!r}", inside)


def sort_goals(camera: Camera, centres, radius: float, *, bin_half_width: float = BIN_HALF_WIDTH) -> np.ndarray:
    """Sort goals: two disjoint discs of ``radius`` (m) at centres [2, 2] (m), one per object kind.
    -> [2, H, W] bool (goal k for kind k). ValueError when the discs overlap or either disc is bad (``disc_goal``)."""
    centres = np.asarray(centres, np.float64)
    if centres.shape != (2, 2):
        raise ValueError(f"sort goal centres must be [2, 2] (one (x, y) per kind), got shape {centres.shape}")
    _check_positive("sort goal radius", radius)
    gap = float(np.linalg.norm(centres[0] - centres[1]))
    if gap <= 2 * radius:
        raise ValueError(f"sort goals overlap: centres {gap:.4f} m apart, need more than 2 * radius = {2 * radius} m")
    return np.stack([disc_goal(camera, c, radius, bin_half_width=bin_half_width) for c in centres])


# ---------------------------------------------------------------------------------------------------------------
# Goal: signed distance field and FPS samples (pixels)
# ---------------------------------------------------------------------------------------------------------------

def make_goal(mask, camera: Camera, n_samples: int = 500) -> Goal:
    """Goal mask [H, W] bool (the camera's pixel grid) -> Goal with its signed distance field (pixels, exact
    Euclidean: cv2.distanceTransform with DIST_MASK_PRECISE of the mask and its complement, outside − inside) and
    ``n_samples`` FPS samples of the goal pixel centres, starting from the first goal pixel in raster order.
    ValueError for a mask of the wrong shape, an empty mask (no pixels) or one covering the whole image."""
    mask = np.asarray(mask)
    if mask.shape != (camera.height, camera.width):
        raise ValueError(f"goal mask has shape {mask.shape}, the camera's image is {(camera.height, camera.width)}")
    if not isinstance(n_samples, int | np.integer) or n_samples < 1:
        raise ValueError(f"n_samples must be a positive int, got {n_samples!r}")
    mask = mask.astype(bool)
    _check_nonempty("goal mask", mask)
    if mask.all():
        raise ValueError("goal mask covers the whole image: its signed distance field is undefined")
    inside = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    uv = camera.pixel_centres().reshape(-1, 2).astype(np.float32)
    flat = mask.reshape(-1)
    idx, _ = fps(np.concatenate([uv, np.zeros_like(uv[:, :1])], -1), flat, int(n_samples), int(np.argmax(flat)))
    return Goal(jnp.asarray(mask), jnp.asarray(outside - inside, jnp.float32), jnp.asarray(uv[np.asarray(idx)]),
                jnp.arange(n_samples) < int(flat.sum()))


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
        """|p - q| to the nearest valid p: found without gradients, then differentiated through that one p (so the
        backward pass touches one point per goal sample, not all P; a tie sends the gradient to the lower index)."""
        u, v = jax.lax.stop_gradient(pixels).T  # [P] each: a sum of two squares, not a reduction over an axis of 2
        d2 = jnp.where(valid, jnp.square(u - q[0]) + jnp.square(v - q[1]), jnp.inf)
        return _root(jnp.sum(jnp.square(pixels[_argmin_nonnegative(d2)] - q)))

    nearest_distance = jax.lax.map(nearest, goal.samples, batch_size=max(1, min(Q, MAX_PAIRS // P)))
    coverage_term = jnp.sum(jnp.where(active, nearest_distance, 0.0))
    return (sdf_term + coverage_term) / jnp.maximum(omega, 1)


@functools.partial(jax.jit, static_argnames="camera")
def objective(positions, mask, goal: Goal, camera: Camera):
    """Task objective c: particles positions [N, 3] (world, m) with mask [N] bool -> scalar (pixels).

    c = (Σ_p SDF(p) + Σ_{q∈Q'} min_p |p − q|) / ω over the ω valid particles projected by ``camera``, Q' the first
    min(5 ω, Q) valid goal samples. Masked particles are inert (any value, NaN included); 0 when ω = 0.
    Differentiable w.r.t. positions; ``jax.vmap`` over particle sets and goals."""
    mask = jnp.asarray(mask, bool)
    positions = jnp.where(mask[:, None], jnp.asarray(positions, jnp.float32), 0.0)
    uv, _ = camera.world_to_pixel(positions)
    return _cost(uv, mask, goal)


@functools.partial(jax.jit, static_argnames="camera")
def kind_costs(positions, mask, kinds, goals: KindGoals, camera: Camera):
    """c of each kind's particles against its own goal: positions [N, 3] (m), mask [N] bool, kinds [N] int (each
    particle's kind index) -> [K] (pixels; 0 for a kind with no particle). Each is a mean over that kind's particles,
    so kinds weigh alike whatever their particle counts."""
    def one(goal, k):
        return objective(positions, jnp.asarray(mask, bool) & (kinds == k), goal, camera)

    return jax.vmap(one)(goals.goals, jnp.arange(goals.hold.shape[0]))


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
    pixel (not a subsample) and distances between pixel centres, exact (``squared_distance_to``). A foreground pixel
    inside the goal adds 0 (no signed distance). The sum is divided by the foreground pixel count, as the reference
    divides c by ω: a mean per foreground pixel. observation_or_mask: an Observation (its foreground by
    ``perception.foreground``, ``foreground_kw`` passed on: kind= for one kind of a Sort scene) or a foreground
    mask [H, W] bool. +inf when there is no foreground pixel. ``jax.vmap`` over observations and goals."""
    if isinstance(observation_or_mask, Observation):
        _, valid = foreground(observation_or_mask, camera, **foreground_kw)
        current = valid.reshape(camera.height, camera.width)
    else:
        current = jnp.asarray(observation_or_mask, bool)
        if current.shape != (camera.height, camera.width):
            raise ValueError(f"foreground mask has shape {current.shape}, the camera's image is "
                             f"{(camera.height, camera.width)}")
    return _mask_distance(current, goal.mask)


@functools.partial(jax.jit, static_argnames="camera")
def inside_share(piece_pos, piece_mask, goal: Goal, camera: Camera):
    """Success share: pieces piece_pos [N, 3] (world centres, m) with piece_mask [N] bool -> scalar in [0, 1], the
    share of valid pieces whose centre projects to a goal pixel (0 when no piece is valid)."""
    piece_mask = jnp.asarray(piece_mask, bool)
    uv, _ = camera.world_to_pixel(jnp.where(piece_mask[:, None], jnp.asarray(piece_pos, jnp.float32), 0.0))
    u, v = jnp.floor(uv[:, 0]).astype(jnp.int32), jnp.floor(uv[:, 1]).astype(jnp.int32)
    in_image = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    hit = piece_mask & in_image & goal.mask[jnp.clip(v, 0, camera.height - 1), jnp.clip(u, 0, camera.width - 1)]
    return jnp.sum(hit) / jnp.maximum(jnp.sum(piece_mask), 1)
