"""Top-down pinhole camera: intrinsics, extrinsics, world <-> pixel, and a batched RGBD + segmentation renderer in JAX.

Conventions (OpenCV): camera frame x right, y down, z forward (the optical axis). Pixel (row v, column u) has its
centre at image coordinates (u + 0.5, v + 0.5); ``world_to_pixel`` returns continuous (u, v) and ``floor`` gives the
index. Depth is z-depth along the optical axis in metres, as depth cameras report it (not the distance along the ray).

The renderer casts one analytic ray per pixel centre at spheres, capsules and boxes. Each piece only touches a small
fixed window of pixels around its projection, so a piece is "splatted": its window's rays are intersected with it and
the nearest hit per pixel wins (a scatter-min). Cost and memory are N x window^2 per world, independent of the image
size, so observations batch with thousands of worlds. The table and walls are a precomputed background.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import CameraConfig

_MISS = jnp.inf


def neighbourhoods(image):
    """image [H, W] -> its 3 x 3 neighbourhoods [9, H, W] (edges replicated), row by row: index 4 is the pixel itself,
    1, 3, 5 and 7 its 4-neighbours (up, left, right, down)."""
    h, w = image.shape
    padded = jnp.pad(image, 1, mode="edge")
    return jnp.stack([padded[i:i + h, j:j + w] for i in range(3) for j in range(3)])


def _xp(*arrays):
    """jax.numpy where any of ``arrays`` is a JAX array (or a tracer), else NumPy."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


MIN_IMAGE, MAX_IMAGE = 8, 4096  # pixels per side: the renderer's and perception's range (a 4K depth frame fits)


def rotation_about(axis, angle: float) -> np.ndarray:
    """The rotation [3, 3] by ``angle`` (radians) about ``axis`` [3] (any length; a zero axis needs angle 0), by
    Rodrigues' formula."""
    axis = np.asarray(axis, np.float64)
    norm = np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]) / max(norm, 1e-12)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def check_image_size(width: int, height: int) -> None:
    """ValueError naming the limits for an image side outside [MIN_IMAGE, MAX_IMAGE] pixels."""
    if not (MIN_IMAGE <= width <= MAX_IMAGE and MIN_IMAGE <= height <= MAX_IMAGE):
        raise ValueError(f"image size {width} x {height} pixels is outside [{MIN_IMAGE}, {MAX_IMAGE}] per side")


MAX_CENTRE = 100.0  # m: a camera's centre lies this close to the table's origin along each axis (a table-top camera:
#   about 1 m above it)
DISTORTION_FIELDS = {"distortion", "dist", "D", "coeffs", "dist_coeffs", "distortion_coeffs",
                     "distortion_coefficients"}  # a camera JSON's lens distortion, under the names tools write it


def _short(value, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters, for a message of one line."""
    try:
        text = repr(value)
    except ValueError:  # an integer of more digits than Python prints
        text = "a number too large to print"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _numbers(value, depth: int) -> np.ndarray | None:
    """A JSON value as float64, or None unless it is a number (not a boolean) or, ``depth`` deep, lists of them
    (a larger integer than a float holds is None too)."""
    if depth and isinstance(value, list):
        rows = [_numbers(v, depth - 1) for v in value]
        if any(r is None for r in rows) or len({r.shape for r in rows}) > 1:
            return None
        return np.array(rows, np.float64).reshape(len(rows), *(rows[0].shape if rows else ()))
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        return np.asarray(float(value))
    except OverflowError:
        return None


MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0  # fields of view (each axis) that real cameras have


def check_geometry(K: np.ndarray, rotation: np.ndarray, centre: np.ndarray, width: int, height: int) -> None:
    """ValueError naming what no real camera over the table has: a rotation that is not a rotation (orthonormal
    within 1e-3, determinant +1), non-positive focal lengths or ones that give a field of view outside
    [MIN_FOV_DEG, MAX_FOV_DEG], a K with skew or whose last row is not (0, 0, 1) or whose principal point lies outside
    the image, a camera below the table (centre z <= 0) or one that does not look down at it."""
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0:
        raise ValueError(f"camera: rotation must be a rotation matrix (orthonormal, determinant +1), got "
                         f"{np.round(rotation, 4).tolist()}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"camera: K's focal lengths must be positive pixels, got fx = {K[0, 0]:g}, fy = {K[1, 1]:g}")
    if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0 or K[0, 1] != 0:
        raise ValueError(f"camera: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (a pinhole without skew: the "
                         f"projection uses fx, fy, cx and cy only), got {K.tolist()}")
    fov = np.degrees(2 * np.arctan2([width / 2, height / 2], [K[0, 0], K[1, 1]]))
    if not np.all((MIN_FOV_DEG <= fov) & (fov <= MAX_FOV_DEG)):
        raise ValueError(f"camera: K's focal lengths fx = {K[0, 0]:g}, fy = {K[1, 1]:g} px give a {fov[0]:.3g} x "
                         f"{fov[1]:.3g} degree field of view on a {width} x {height} image; a real camera's lies in "
                         f"[{MIN_FOV_DEG:g}, {MAX_FOV_DEG:g}] (are they in pixels?)")
    if not (0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height):
        raise ValueError(f"camera: K's principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {width} x {height} "
                         "image")
    if not centre[2] > 0 or not rotation[2, 2] < 0:
        raise ValueError(f"camera: it must be above the table (centre z > 0, got {centre[2]:g} m) and look down at it "
                         f"(its optical axis's world z < 0, got {rotation[2, 2]:g})")


@dataclass(frozen=True, eq=False)
class Camera:
    """Pinhole camera. K: [3, 3] intrinsics (pixels); rotation: [3, 3] camera-to-world (columns are the camera's
    axes in the world frame); centre: [3] camera position in the world (metres); width, height in pixels."""

    K: np.ndarray
    rotation: np.ndarray
    centre: np.ndarray
    width: int
    height: int

    @classmethod
    def top_down(cls, cfg: CameraConfig) -> Camera:
        check_image_size(cfg.width, cfg.height)
        if cfg.distance <= 0 or cfg.view_half_width <= 0:
            raise ValueError(f"camera config out of range: {cfg}")
        f = (cfg.width / 2) * cfg.distance / cfg.view_half_width
        K = np.array([[f, 0, cfg.width / 2], [0, f, cfg.height / 2], [0, 0, 1.0]])
        rotation = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
        return cls(K, rotation, np.array([0.0, 0.0, cfg.distance]), cfg.width, cfg.height)

    # Equal cameras compare and hash equal, so a camera loaded twice reuses compiled functions (jit static args).
    def _key(self):
        return (self.K.tobytes(), self.rotation.tobytes(), self.centre.tobytes(), self.width, self.height)

    def __eq__(self, other):
        return isinstance(other, Camera) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())

    # --- serialisation for real cameras: {"K": 3x3, "rotation": 3x3, "centre": 3, "width", "height"} ---
    def to_json(self) -> str:
        return json.dumps({"K": self.K.tolist(), "rotation": self.rotation.tolist(), "centre": self.centre.tolist(),
                           "width": self.width, "height": self.height}, indent=1)

    @classmethod
    def from_json(cls, text: str) -> Camera:
        """A camera from its JSON; ValueError naming a missing field, one of the wrong shape or with a value that is
        not a finite number, distortion coefficients other than zeros (``DISTORTION_FIELDS``: not modelled), an image
        size outside [MIN_IMAGE, MAX_IMAGE], or geometry no camera has (``check_geometry``)."""
        try:
            d = json.loads(text)
        except RecursionError:
            raise ValueError("camera JSON is nested too deeply to be a camera") from None
        fields = ("K", "rotation", "centre", "width", "height")
        if not isinstance(d, dict):
            raise ValueError(f"camera JSON must be an object with {', '.join(fields)}, got {type(d).__name__} "
                             f"{_short(d)}")
        missing = set(fields) - set(d)
        if missing:
            raise ValueError(f"camera JSON lacks {sorted(missing)}")
        arrays = {}
        for name, shape in (("K", (3, 3)), ("rotation", (3, 3)), ("centre", (3,)), ("width", ()), ("height", ())):
            a = _numbers(d[name], len(shape))
            if a is None or a.shape != shape or not np.all(np.isfinite(a)):
                wanted = f"finite numbers of shape {shape}" if shape else "a finite number"
                raise ValueError(f"camera JSON: {name} must be {wanted}, got {_short(d[name])}")
            arrays[name] = a
        for name in DISTORTION_FIELDS & set(d):
            coeffs = _numbers(d[name], 1)
            if coeffs is None or np.any(coeffs != 0):
                raise ValueError(f"camera JSON: {name} {_short(d[name])}: lens distortion is not modelled (a pinhole "
                                 "camera); give undistorted frames (a RealSense's rectified streams) and zeros or no "
                                 f"{name}")
        if not np.all(np.abs(arrays["centre"]) <= MAX_CENTRE):
            raise ValueError(f"camera JSON: centre {_short(d['centre'])} lies more than {MAX_CENTRE:g} m from the "
                             "table's origin along an axis (metres expected)")
        if arrays["width"] != int(arrays["width"]) or arrays["height"] != int(arrays["height"]):
            raise ValueError(f"camera JSON: width and height must be whole pixels, got {d['width']}, {d['height']}")
        check_image_size(int(arrays["width"]), int(arrays["height"]))
        check_geometry(arrays["K"], arrays["rotation"], arrays["centre"], int(arrays["width"]), int(arrays["height"]))
        return cls(arrays["K"], arrays["rotation"], arrays["centre"], int(arrays["width"]), int(arrays["height"]))

    # --- geometry (NumPy in, NumPy out, so host callers such as goal masks stay off the device; JAX otherwise) ---
    def world_to_pixel(self, points):
        """points [..., 3] world -> (uv [..., 2] continuous pixel coordinates, depth [...] z-depth in metres)."""
        p_cam = (points - self.centre) @ self.rotation  # R^T (p - c), row-vector form
        z = p_cam[..., 2]
        uv = p_cam[..., :2] / z[..., None] * np.diag(self.K)[:2] + self.K[:2, 2]
        return uv, z

    def pixel_to_world(self, uv, depth):
        """uv [..., 2] pixel coordinates and z-depth [...] (metres) -> world points [..., 3]."""
        xy = (uv - self.K[:2, 2]) / np.diag(self.K)[:2]
        p_cam = _xp(uv, depth).concatenate([xy * depth[..., None], depth[..., None]], axis=-1)
        return p_cam @ self.rotation.T + self.centre

    def ray_directions(self, uv):
        """uv [..., 2] -> world ray directions [..., 3] whose camera-z component is 1, so distance along them is
        z-depth."""
        xy = (uv - self.K[:2, 2]) / np.diag(self.K)[:2]
        xp = _xp(uv)
        return xp.concatenate([xy, xp.ones_like(xy[..., :1])], axis=-1) @ self.rotation.T

    def pixel_centres(self) -> np.ndarray:
        """[H, W, 2] (u, v) of every pixel centre."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        return np.stack([u, v], axis=-1)


class Observation(NamedTuple):
    """A top-down RGBD frame. depth [H, W] float32 z-depth (m); piece [H, W] int32 piece index or -1;
    kind [H, W] int32 index into the scene's kinds or -1; rgb [H, W, 3] uint8."""

    depth: jax.Array
    piece: jax.Array
    kind: jax.Array
    rgb: jax.Array


# ---------------------------------------------------------------------------------------------------------------
# Ray-primitive intersection. o [3] ray origin, d [..., 3] directions, geometry per ray. Returns (t [...], normal
# [..., 3]) with t in units of |d| and t = inf on a miss. Shapes broadcast.
# ---------------------------------------------------------------------------------------------------------------

def _safe_sqrt(x):
    return jnp.sqrt(jnp.maximum(x, 0.0))


def ray_sphere(o, d, c, r):
    oc = o - c
    a = jnp.sum(d * d, -1)
    b = jnp.sum(d * oc, -1)
    h = b * b - a * (jnp.sum(oc * oc, -1) - r * r)
    t = (-b - _safe_sqrt(h)) / a
    t = jnp.where((h >= 0) & (t > 0), t, _MISS)
    n = (o + t[..., None] * d - c) / r[..., None]
    return t, n


def ray_capsule(o, d, c, axis, r, half):
    """Capsule of radius r around the segment c +- half * axis (axis a unit vector)."""
    pa = c - half[..., None] * axis
    ba = 2 * half[..., None] * axis
    oa = o - pa
    baba = jnp.sum(ba * ba, -1)
    bard = jnp.sum(ba * d, -1)
    baoa = jnp.sum(ba * oa, -1)
    rdoa = jnp.sum(d * oa, -1)
    oaoa = jnp.sum(oa * oa, -1)
    dd = jnp.sum(d * d, -1)
    a = baba * dd - bard * bard
    b = baba * rdoa - baoa * bard
    cc = baba * oaoa - baoa * baoa - r * r * baba
    h = b * b - a * cc
    t_body = (-b - _safe_sqrt(h)) / jnp.where(jnp.abs(a) > 1e-20, a, 1e-20)
    y = baoa + t_body * bard
    body_ok = (h >= 0) & (y > 0) & (y < baba) & (t_body > 0)
    # end caps: the spheres at either end of the segment
    t0, _ = ray_sphere(o, d, pa, r)
    t1, _ = ray_sphere(o, d, pa + ba, r)
    t = jnp.where(body_ok, t_body, jnp.minimum(t0, t1))
    p = o + jnp.where(jnp.isfinite(t), t, 0.0)[..., None] * d
    s = jnp.clip(jnp.sum((p - pa) * ba, -1) / baba, 0.0, 1.0)
    n = (p - pa - s[..., None] * ba) / r[..., None]
    return t, n


def ray_box(o, d, c, rot, half):
    """Box centred at c with rotation rot [..., 3, 3] (columns: box axes) and half-sizes half [..., 3]."""
    ol = jnp.einsum("...ji,...j->...i", rot, o - c)
    dl = jnp.einsum("...ji,...j->...i", rot, d)
    dl = jnp.where(jnp.abs(dl) < 1e-12, 1e-12, dl)
    t1 = (-half - ol) / dl
    t2 = (half - ol) / dl
    tnear = jnp.minimum(t1, t2)
    t_in = jnp.max(tnear, -1)
    t_out = jnp.min(jnp.maximum(t1, t2), -1)
    t = jnp.where((t_out >= t_in) & (t_in > 0), t_in, _MISS)
    axis = jnp.argmax(tnear, -1)
    n_local = -jnp.sign(jnp.take_along_axis(dl, axis[..., None], -1)) * jax.nn.one_hot(axis, 3)
    return t, jnp.einsum("...ij,...j->...i", rot, n_local)


def _shade(rgb, n, d):
    """Lambert shading lit from the camera: rgb [..., 3] in [0, 1] -> [..., 3]."""
    cos = jnp.abs(jnp.sum(n * d, -1)) / jnp.linalg.norm(d, axis=-1)
    return rgb * (0.35 + 0.65 * cos[..., None])


class Renderer:
    """Renders a scene's pieces (plus the static table and walls) through a camera.

    ``renderer(pos [N, 3], mat [N, 3, 3]) -> Observation`` is a pure JAX function of the piece geoms' world poses;
    ``jax.vmap`` it over worlds. Build once per (scene, camera).
    """

    def __init__(self, scene, camera: Camera):
        self.camera = camera
        self.n = scene.n_pieces
        self.geom_type = jnp.asarray(scene.geom_type)
        self.size = jnp.asarray(scene.size, jnp.float32)
        self.kind = jnp.asarray(scene.kind, jnp.int32)
        self.rgb = jnp.asarray(scene.rgb, jnp.float32)
        f = float(camera.K[0, 0])
        # A window that holds any piece's projection: footprint at the piece's top, seen from the camera.
        top = float(np.max(scene.rest_height * 2))
        reach = float(np.max(scene.footprint)) * f / (camera.centre[2] - top)
        self.window = int(2 * np.ceil(reach) + 3)
        off = np.arange(self.window) - self.window // 2
        self.offsets = jnp.asarray(np.stack(np.meshgrid(off, off), -1).reshape(-1, 2))  # [W*W, 2] (du, dv)
        self.background = self._background(scene)

    def _background(self, scene) -> Observation:
        """Table plane (z = 0) and the bin walls, rendered once."""
        cam, cfg = self.camera, scene.config
        d = cam.ray_directions(jnp.asarray(cam.pixel_centres(), jnp.float32))
        o = jnp.asarray(cam.centre, jnp.float32)
        t_table = -o[2] / d[..., 2]
        b, th, hgt = cfg.bin_half_width, cfg.wall_thickness, cfg.wall_height
        depth, rgb = t_table, jnp.broadcast_to(jnp.array([0.9, 0.9, 0.88]), d.shape) * 1.0
        for x, y, sx, sy in [(b + th / 2, 0, th / 2, b + th), (-b - th / 2, 0, th / 2, b + th),
                             (0, b + th / 2, b + th, th / 2), (0, -b - th / 2, b + th, th / 2)]:
            t, n = ray_box(o, d, jnp.array([x, y, hgt / 2]), jnp.eye(3), jnp.array([sx, sy, hgt / 2]))
            hit = t < depth
            depth = jnp.where(hit, t, depth)
            rgb = jnp.where(hit[..., None], _shade(jnp.array([0.6, 0.6, 0.6]), n, d), rgb)
        shape = depth.shape
        return Observation(depth.astype(jnp.float32), jnp.full(shape, -1, jnp.int32), jnp.full(shape, -1, jnp.int32),
                           rgb.astype(jnp.float32))

    def __call__(self, pos, mat, plate=None) -> Observation:
        """pos [N, 3], mat [N, 3, 3] piece geom poses; plate optional (centre [3], rotation [3, 3], half-sizes [3])
        drawn as a dark box (for GIFs; the plate is lifted out of view when observations are taken)."""
        cam, H, W = self.camera, self.camera.height, self.camera.width
        uv_c, _ = cam.world_to_pixel(pos)
        pix = jnp.floor(uv_c).astype(jnp.int32)[:, None, :] + self.offsets[None]  # [N, W*W, 2] (u, v)
        inside = (pix[..., 0] >= 0) & (pix[..., 0] < W) & (pix[..., 1] >= 0) & (pix[..., 1] < H)
        flat = jnp.where(inside, pix[..., 1] * W + pix[..., 0], H * W)  # H*W: dropped by the scatter
        d = cam.ray_directions(pix.astype(jnp.float32) + 0.5)
        o = jnp.asarray(cam.centre, jnp.float32)
        shape = d.shape[:2]
        pos_r = jnp.broadcast_to(pos[:, None], shape + (3,))
        mat_r = jnp.broadcast_to(mat[:, None], shape + (3, 3))
        radius = jnp.broadcast_to(self.size[:, None, 0], shape)
        t_s, n_s = ray_sphere(o, d, pos_r, radius)
        t_c, n_c = ray_capsule(o, d, pos_r, mat_r[..., :, 2], radius, jnp.broadcast_to(self.size[:, None, 1], shape))
        t_b, n_b = ray_box(o, d, pos_r, mat_r, jnp.broadcast_to(self.size[:, None], shape + (3,)))
        gt = self.geom_type[:, None]
        t = jnp.where(gt == 0, t_s, jnp.where(gt == 1, t_c, t_b))
        n = jnp.where((gt == 0)[..., None], n_s, jnp.where((gt == 1)[..., None], n_c, n_b))
        t = jnp.where(inside, t, _MISS)

        bg = self.background
        depth = bg.depth.reshape(-1).at[flat].min(t, mode="drop")
        win = jnp.isfinite(t) & (t <= depth.at[flat].get(mode="fill", fill_value=-1.0))
        idx = jnp.broadcast_to(jnp.arange(self.n, dtype=jnp.int32)[:, None], t.shape)
        piece = bg.piece.reshape(-1).at[flat].max(jnp.where(win, idx, -1), mode="drop")
        colour = _shade(self.rgb[:, None], n, d)
        rgb = jnp.zeros((H * W, 3)).at[flat].max(jnp.where(win[..., None], colour, 0.0), mode="drop")
        rgb = jnp.where((piece >= 0)[:, None], rgb, bg.rgb.reshape(-1, 3))
        kind = jnp.where(piece >= 0, self.kind[jnp.maximum(piece, 0)], -1)
        depth, piece, kind, rgb = (depth.reshape(H, W), piece.reshape(H, W), kind.reshape(H, W),
                                   rgb.reshape(H, W, 3))
        if plate is not None:
            centre, rot, half = plate
            dp = cam.ray_directions(jnp.asarray(cam.pixel_centres(), jnp.float32))
            tp, npl = ray_box(o, dp, centre, rot, half)
            hit = tp < depth
            depth = jnp.where(hit, tp, depth)
            piece, kind = jnp.where(hit, -2, piece), jnp.where(hit, -2, kind)
            rgb = jnp.where(hit[..., None], _shade(jnp.array([0.15, 0.15, 0.15]), npl, dp), rgb)
        return Observation(depth, piece, kind, jnp.round(jnp.clip(rgb, 0, 1) * 255).astype(jnp.uint8))
