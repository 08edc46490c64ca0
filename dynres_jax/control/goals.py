"""Goals: the goal masks of the tasks, built on the host (NumPy / OpenCV) from shapes in metres on the table plane
(discs, polygons, text, Sort's two discs), and the ``Goal`` record the objective reads (``make_goal``: the mask's
signed distance field and farthest-point samples, in pixels of the camera's image); ``KindGoals`` holds one goal per
piece kind (Sort). Outputs of the mask builders are [H, W] bool; a goal outside the bin or empty is a ValueError.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import SceneConfig
from dynres_jax.control.objective import kind_costs, kind_objective, objective, planner_cost, squared_distance_to
from dynres_jax.perception import fps
from dynres_jax.sim.camera import Camera

BIN_HALF_WIDTH = SceneConfig().bin_half_width  # m: goals must lie inside the bin [-b, b]^2
TEXT_OVERSAMPLE = 8  # text is drawn on a canvas this many times finer than the image, then sampled per pixel


class Goal(NamedTuple):
    """A goal region in the camera's pixel grid (a pytree: pass it through jit / vmap).

    mask [H, W] bool: goal pixels; distance [H, W] float32: signed distance field in pixels (negative inside, positive
    outside; a pixel's distance to the nearest pixel centre of the other set); samples [Q, 2] float32: pixel
    coordinates (u, v) of an FPS subsample of the goal pixels' centres, in FPS order; sample_mask [Q] bool: valid
    samples (all but the tail when the goal has fewer than Q pixels)."""

    mask: jax.Array
    distance: jax.Array
    samples: jax.Array
    sample_mask: jax.Array

    labels_kinds = False  # whether c needs each particle's piece kind (perception labels them: KindGoals)

    def cut(self, n: int) -> Goal:
        """The goal with its first ``n`` samples (FPS order: still an FPS sample; c on fewer samples)."""
        return self._replace(samples=self.samples[..., :n, :], sample_mask=self.sample_mask[..., :n])

    def cost_now(self, positions, mask, kinds, camera: Camera):
        """(c of particles positions [N, 3] m with mask [N], the planner's baseline: None); kinds: unused (None)."""
        return objective(positions, mask, self, camera), None

    def planner_cost(self, camera: Camera, kinds, baseline):
        """c against this goal as the planner's cost (``objective.planner_cost``); kinds and baseline: None."""
        if kinds is not None or baseline is not None:
            raise ValueError("particle kinds and a baseline go with KindGoals (Sort's per-kind goals), not a Goal")
        return planner_cost(camera, self)


class KindGoals(NamedTuple):
    """One goal per piece kind (Sort), a pytree like ``Goal``: goals, a Goal whose every leaf has a leading axis [K]
    (goal k for kind k); hold [K] bool: kinds only kept from getting worse, not pursued (``kind_objective``);
    avoid [K, H, W] float32: signed distance (pixels) to the region kind k's pieces must keep out of (the other kinds'
    own goals; ``NOWHERE`` where there is none); mixing [] float32: the weight of that intrusion in c_k (0: the
    objective without it)."""

    goals: Goal
    hold: jax.Array
    avoid: jax.Array
    mixing: jax.Array

    labels_kinds = True  # c_k reads each particle's kind

    def cut(self, n: int) -> KindGoals:
        """Every kind's goal with its first ``n`` samples (``Goal.cut``)."""
        return self._replace(goals=self.goals.cut(n))

    def cost_now(self, positions, mask, kinds, camera: Camera):
        """(Sort's c of the particles now, the planner's baseline: each kind's c_k now, [K]); kinds [N] int."""
        baseline = kind_costs(positions, mask, kinds, self, camera)
        return kind_objective(positions, mask, kinds, self, camera, baseline), baseline

    def planner_cost(self, camera: Camera, kinds, baseline):
        """Sort's c (``kind_objective``) as the planner's cost, with the particles' kinds [N] and baseline [K]."""
        if kinds is None or baseline is None:
            raise ValueError("KindGoals score particles by kind against a baseline: give both")
        return planner_cost(camera, self, kinds, baseline)


NOWHERE = 1e4  # pixels: the signed distance of a region no pixel is in (KindGoals.avoid when no kind is avoided)


def stack(goals) -> Goal:
    """A sequence of Goals of one camera -> one Goal with a leading axis (a batch of episodes' goals, or kinds')."""
    return jax.tree.map(lambda *x: jnp.stack(x), *goals)


def stack_goals(goals, hold=None, avoid=None, mixing: float = 0.0) -> KindGoals:
    """A sequence of K Goals of one camera (goal k for kind k), hold [K] bool (default: pursue every kind), avoid: K
    Goals, kind k's own region (Sort: its true goal), of which kind k must keep out of every other kind's (None: no
    region is avoided), and mixing >= 0, the weight of an intrusion (``objective.kind_costs``) -> KindGoals."""
    hold = np.zeros(len(goals), bool) if hold is None else np.asarray(hold, bool)
    if hold.shape != (len(goals),):
        raise ValueError(f"hold must have one flag per goal ({len(goals)}), got shape {hold.shape}")
    if not (np.isfinite(mixing) and mixing >= 0):
        raise ValueError(f"mixing must be a finite weight >= 0, got {mixing}")
    shape = goals[0].distance.shape
    if avoid is None:
        fields = jnp.full((len(goals), *shape), NOWHERE, jnp.float32)
    else:
        if len(avoid) != len(goals):
            raise ValueError(f"avoid must have one region per goal ({len(goals)}), got {len(avoid)}")
        others = [[a.distance for j, a in enumerate(avoid) if j != k] for k in range(len(avoid))]
        fields = jnp.stack([functools.reduce(jnp.minimum, o) if o else jnp.full(shape, NOWHERE, jnp.float32)
                            for o in others])  # the union of the other kinds' regions: the nearest one's distance
    return KindGoals(stack(goals), jnp.asarray(hold), fields, jnp.float32(mixing))


# ---------------------------------------------------------------------------------------------------------------
# Goal masks (host, NumPy / OpenCV). Inputs in metres on the table plane; outputs [H, W] bool.
# ---------------------------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=4)
def table_xy(camera: Camera) -> np.ndarray:
    """[H, W, 2] world (x, y) in metres where each pixel centre's ray meets the table (NaN where it never does);
    computed once per camera, read-only."""
    d = np.asarray(camera.ray_directions(camera.pixel_centres()), np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] < 0, -camera.centre[2] / d[..., 2], np.nan)
    xy = camera.centre[:2] + t[..., None] * d[..., :2]
    xy.flags.writeable = False
    return xy


def check_within(mask, camera: Camera, half_width: float) -> None:
    """ValueError when a goal pixel of mask [H, W] lies outside the table square ±half_width (m) or off the table."""
    xy = table_xy(camera)[np.asarray(mask, bool)]
    if (outside := ~np.all(np.abs(xy) <= half_width, axis=-1)).any():  # NaN (off the table) is outside too
        hint = "; if the mask is right, the camera's pose is not the one that frames it" if outside.all() else ""
        raise ValueError(f"{int(outside.sum())} of the goal's {len(xy)} pixels lie outside the workspace (table "
                         f"square ±{half_width:g} m); pieces cannot be pushed there{hint}")


def _project(camera: Camera, xy) -> np.ndarray:
    """Table points xy [..., 2] (m) -> pixel coordinates [..., 2]."""
    xy = np.asarray(xy, np.float64)
    uv, _ = camera.world_to_pixel(np.concatenate([xy, np.zeros_like(xy[..., :1])], axis=-1))
    return np.asarray(uv, np.float64)


def _check_positive(name: str, value) -> None:
    """ValueError naming ``name`` unless value is one finite positive number (not a string, bool or several)."""
    try:
        number = None if isinstance(value, (bool, np.bool_, str, bytes)) or np.ndim(value) else float(value)
    except (TypeError, ValueError):
        number = None
    if number is None or not np.isfinite(number) or number <= 0:
        raise ValueError(f"{name} must be positive: one finite number, got {value!r}")


def _point(name: str, xy) -> np.ndarray:
    """xy as a finite table point [2] (m); ValueError naming ``name`` for another shape or a non-number."""
    try:
        point = np.asarray(xy, np.float64)
    except (TypeError, ValueError):
        point = np.full(0, np.nan)
    if point.shape != (2,) or not np.all(np.isfinite(point)):
        raise ValueError(f"{name} must be a finite (x, y) in metres, got {xy!r}")
    return point


def _check_in_view(what: str, camera: Camera, outline_xy, bin_half_width: float) -> None:
    """outline_xy [K, 2] (m): points whose hull holds the goal. Every one must be inside the bin and the image."""
    outline_xy = np.asarray(outline_xy, np.float64)
    if not np.all(np.isfinite(outline_xy)):
        raise ValueError(f"{what}: coordinates must be finite")
    _check_positive(f"{what}: bin_half_width", bin_half_width)
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
    centre = _point("disc centre", centre_xy)
    angle = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    outline = centre + radius * np.stack([np.cos(angle), np.sin(angle)], -1)
    _check_in_view("disc goal", camera, outline, bin_half_width)  # the outline holds the 4 axis extremes
    inside = np.linalg.norm(table_xy(camera) - centre, axis=-1) <= radius
    return _check_nonempty("disc goal", inside)


def polygon_goal(camera: Camera, vertices_xy, *, bin_half_width: float = BIN_HALF_WIDTH) -> np.ndarray:
    """Pixels whose centre's table point is inside the simple polygon vertices_xy [K, 2] (m, K >= 3, either
    orientation; even-odd crossing rule). -> [H, W] bool. ValueError for fewer than 3 vertices, a polygon reaching
    outside the bin or image, or one with no pixels."""
    v = np.asarray(vertices_xy, np.float64)
    if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3:
        raise ValueError(f"polygon vertices must be [K >= 3, 2], got shape {v.shape}")
    _check_in_view("polygon goal", camera, v, bin_half_width)
    xy = table_xy(camera)
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
    centre = _point("text centre", centre_xy)
    # the ink is height_m tall: text that cannot fit fails before it is drawn (the drawing costs most for large text)
    _check_in_view(f"text goal {text!r}", camera, centre + [[0, -0.45 * height_m], [0, 0.45 * height_m]],
                   bin_half_width)
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
    xy = table_xy(camera)
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

def signed_distance(mask) -> jax.Array:
    """mask [H, W] bool -> its signed distance field [H, W] float32 (px): outside a pixel's distance to the nearest
    goal pixel, inside minus its distance to the nearest non-goal pixel (centre to centre; what cv2.distanceTransform
    with DIST_MASK_PRECISE gives for the mask and its complement)."""
    mask = jnp.asarray(mask, bool)
    return jnp.sqrt(squared_distance_to(mask)) - jnp.sqrt(squared_distance_to(~mask))


@functools.partial(jax.jit, static_argnames=("camera", "n_samples"))
def goal_fields(mask, camera: Camera, n_samples: int) -> Goal:
    """The Goal of mask [H, W] bool, traceable (no checks: an empty mask gives no valid sample, a full one a
    meaningless distance field; ``make_goal`` checks): its ``signed_distance`` and ``n_samples`` FPS samples of the
    goal pixel centres, starting from the first goal pixel in raster order."""
    mask = jnp.asarray(mask, bool)
    uv = jnp.asarray(camera.pixel_centres().reshape(-1, 2), jnp.float32)
    flat = mask.reshape(-1)
    idx, _ = fps(jnp.concatenate([uv, jnp.zeros_like(uv[:, :1])], -1), flat, n_samples,
                 jnp.argmax(flat).astype(jnp.int32))
    return Goal(mask, signed_distance(mask), uv[idx], jnp.arange(n_samples) < jnp.sum(flat))


def _checked_mask(mask, camera: Camera, what: str = "goal mask") -> np.ndarray:
    """mask as [H, W] bool; ValueError for the wrong shape, no pixels, or every pixel."""
    mask = np.asarray(mask)
    if mask.shape != (camera.height, camera.width):
        raise ValueError(f"{what} has shape {mask.shape}, the camera's image is {(camera.height, camera.width)}")
    mask = mask.astype(bool)
    _check_nonempty(what, mask)
    if mask.all():
        raise ValueError(f"{what} covers the whole image: its signed distance field is undefined")
    return mask


MAX_GOAL_SAMPLES = 100_000  # Q at most: FPS over the goal is O(Q x pixels); 10^7 ran for minutes without a word


def _check_samples(n_samples) -> int:
    if not isinstance(n_samples, int | np.integer) or not 1 <= n_samples <= MAX_GOAL_SAMPLES:
        raise ValueError(f"n_samples must be an int in [1, {MAX_GOAL_SAMPLES}], got {n_samples!r}")
    return int(n_samples)


def make_goal(mask, camera: Camera, n_samples: int = 500) -> Goal:
    """Goal mask [H, W] bool (the camera's pixel grid) -> Goal with its signed distance field (pixels, exact
    Euclidean, ``signed_distance``) and ``n_samples`` FPS samples of the goal pixel centres (``goal_fields``).
    ValueError for a mask of the wrong shape, an empty mask (no pixels) or one covering the whole image."""
    mask = _checked_mask(mask, camera)
    return goal_fields(mask, camera, _check_samples(n_samples))


OBJECTIVES = {  # the forms of c's first term a goal can carry (``with_objective``), each in words for --help
    "paper": "Σ SDF: rewards depth inside the goal",
    "hinge": "Σ max(0, SDF): only particles outside cost",
}


def check_objective(objective: str) -> str:
    """``objective`` when it names one of ``OBJECTIVES``, else ValueError naming them."""
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
    return objective


def with_objective(goal: Goal, objective: str) -> Goal:
    """The goal whose SDF term in c takes the form ``objective``: "paper" (unchanged: Σ SDF(p), negative inside, so
    c rewards particles deep in the goal) or "hinge" (Σ max(0, SDF(p)): the distance field clipped at 0, so only
    particles outside cost and the coverage term alone places those inside). Only c changes: the mask, and with it d,
    the inside share and the seen share, are the same. Works on a Goal or a stacked batch of them."""
    return goal if check_objective(objective) == "paper" else goal._replace(distance=jnp.maximum(goal.distance, 0.0))


GOAL_BATCH = 64  # masks a batched goal computation vectorises at once (its memory grows with it: about 2 MB a mask)


def make_goals(masks, camera: Camera, n_samples: int = 500) -> Goal:
    """``make_goal`` of each of masks [B, H, W] in one compiled call (``GOAL_BATCH`` masks vectorised at a time):
    the Goals stacked [B, ...], equal to ``stack`` of the one-by-one Goals. ValueError naming the first bad mask."""
    masks = np.asarray(masks)
    if masks.ndim != 3 or len(masks) == 0:
        raise ValueError(f"goal masks must be [B >= 1, H, W], got shape {masks.shape}")
    n_samples = _check_samples(n_samples)
    masks = np.stack([_checked_mask(m, camera, f"goal mask {i}") for i, m in enumerate(masks)])
    return _goal_fields_batch(masks, camera, n_samples, min(GOAL_BATCH, len(masks)))


@functools.partial(jax.jit, static_argnames=("camera", "n_samples", "batch"))
def _goal_fields_batch(masks, camera: Camera, n_samples: int, batch: int) -> Goal:
    return jax.lax.map(lambda m: goal_fields(m, camera, n_samples), masks, batch_size=batch)
