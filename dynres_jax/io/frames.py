"""Recorded RGBD frames as depth cameras save them: depth in millimetres as a 16-bit PNG (0 = no reading), colour
as an 8-bit PNG, the camera as JSON (``Camera.to_json``), a goal as a black-and-white PNG. The simulator writes the
same format (``save_frame``), so real and simulated frames go through one loader."""

from __future__ import annotations

import os

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.errors import InputError
from dynres_jax.io import files
from dynres_jax.sim.camera import Camera, Observation
from dynres_jax.sim.sensor import is_reading, readings

MIN_DEPTH, MAX_DEPTH = 0.1, 5.0  # m: a depth camera's median reading over a table top
TABLE_OFFSET = 0.03  # m: the frame's median point may lie this far from the table plane (z = 0) the camera implies
TABLE_BAND, TABLE_SHARE = 0.02, 0.25  # that share of the readings lies within this band of the median: a table


def save_frame(folder: str, obs: Observation, camera: Camera) -> dict[str, str]:
    """Write depth.png (uint16 mm; no reading, ``sim.sensor.is_reading``, or one beyond 65.535 m, as 0, the way
    cameras save it), rgb.png and camera.json into ``folder``; returns their paths."""
    os.makedirs(folder, exist_ok=True)
    paths = {name: os.path.join(folder, name) for name in ("depth.png", "rgb.png", "camera.json")}
    depth_mm = np.round(np.asarray(obs.depth, np.float64) * 1000)
    missing = ~is_reading(np.asarray(obs.depth)) | ~(depth_mm <= 65535)
    depth_mm = np.where(missing, 0, np.clip(depth_mm, 0, 65535)).astype(np.uint16)
    files.write_image(paths["depth.png"], depth_mm)
    files.write_image(paths["rgb.png"], cv2.cvtColor(np.asarray(obs.rgb, np.uint8), cv2.COLOR_RGB2BGR))
    files.write_text(paths["camera.json"], camera.to_json())
    return paths


class FrameError(InputError):
    """A recorded frame, camera or goal file that cannot be used; the message names the file."""


class MissingFrame(FrameError, FileNotFoundError):
    """A frame, camera or goal file that does not exist."""


def check_file(path: str, what: str) -> None:
    """MissingFrame when nothing is at ``path``, FrameError naming what is there (a folder, a FIFO, a device: reading
    one would block or read nothing) when it is not a regular file; ``what`` names it ("depth file")."""
    try:
        files.check_input(path, what)
    except files.MissingInput as e:
        raise MissingFrame(str(e)) from None
    except InputError as e:
        raise FrameError(str(e)) from None


def read_image(path: str, what: str, flags: int) -> np.ndarray:
    """``cv2.imread(path, flags)`` of a regular file (``check_file``), its pixels as the camera stored them. FrameError
    naming ``what`` ("goal file") when it is not a readable image, or when it carries an EXIF orientation other than
    "as stored": OpenCV would rotate it, its stored pixels would lie turned against the depth frame (which has no such
    tag), and neither is what a viewer that honours the tag showed the user."""
    check_file(path, what)
    image = cv2.imread(path, flags if flags == cv2.IMREAD_UNCHANGED else flags | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise FrameError(f"{what} {path!r} is not a readable image")
    turned = _exif_orientation(path)
    if turned in range(2, 9):  # 1: as stored; 0 or none: undefined
        raise FrameError(f"{what} {path!r} carries an EXIF orientation tag ({turned}: shown rotated or mirrored); "
                         "save its pixels the way they should lie, without the tag")
    return image


def read_mask(path: str, what: str) -> np.ndarray:
    """A goal mask image as gray levels [H, W] uint8 (``read_image``'s checks): 8-bit gray, colour (its luminance) or
    opaque colour with alpha; 16-bit white on black (0 / 65535) as its 8 high bits, as OpenCV reads it. FrameError
    naming ``what`` for a 16-bit image whose levels all lie below 256 (0 / 1, 0 / 255: OpenCV scales them to 0, and
    its white would read as no goal), one of another depth, and an alpha channel that is not fully opaque (a shape
    drawn in transparency; the goal is read from white on black, not from alpha)."""
    image = read_image(path, what, cv2.IMREAD_UNCHANGED)
    if image.dtype == np.uint16:
        if image.max() < 256:
            raise FrameError(f"{what} {path!r} is a 16-bit image with levels 0-{int(image.max())}: read as 16 bits "
                             "they are all black; save the mask 8-bit, white (> 127) on black")
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise FrameError(f"{what} {path!r} is a {image.dtype.itemsize * 8}-bit image; a goal mask is 8-bit, white "
                         "(> 127) on black")
    channels = 1 if image.ndim == 2 else image.shape[2]
    if channels in (2, 4) and (image[..., -1] < 255).any():
        raise FrameError(f"{what} {path!r} has transparent pixels (alpha); a goal mask is read from its gray levels, "
                         "white (> 127) on black: save the shape opaque, without transparency")
    if channels == 1:
        return image.reshape(image.shape[:2])
    return cv2.cvtColor(image[..., :3] if channels == 4 else image[..., :1].repeat(3, axis=2) if channels == 2
                        else image, cv2.COLOR_BGR2GRAY)


def _exif_orientation(path: str) -> int | None:
    """The EXIF orientation tag (0x0112) of an image file, or None where it has none or Pillow cannot read it (OpenCV
    has read the pixels; a malformed EXIF block raises anything from Pillow, SyntaxError included)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.getexif().get(0x0112)
    except Exception:
        return None


MAX_CAMERA_BYTES = 1 << 20  # a camera's JSON is a few hundred bytes


def load_camera(path: str) -> Camera:
    """``Camera.from_json`` of a file; FrameError naming the file and what is wrong with it, in one line (not a
    regular file, too large, not UTF-8, not JSON, or a camera ``from_json`` refuses)."""
    check_file(path, "camera file")
    try:
        size = os.path.getsize(path)
        if size > MAX_CAMERA_BYTES:
            raise ValueError(f"{size} bytes; a camera's JSON is a few hundred (at most {MAX_CAMERA_BYTES})")
        with open(path, encoding="utf-8") as f:
            return Camera.from_json(f.read())
    except (OSError, UnicodeDecodeError, ValueError) as e:  # json.JSONDecodeError is a ValueError
        raise FrameError(f"camera file {path!r}: {e}") from None


def load_frame(depth_path: str, rgb_path: str, camera_path: str) -> tuple[Observation, Camera]:
    """Read a recorded frame. Depth must be a single-channel 16-bit PNG in millimetres (0, no reading, becomes
    ``sim.sensor.NO_READING`` metres, never foreground: ``sim.sensor.is_reading``); colour an 8-bit image of the
    same size (neither with an EXIF orientation tag: ``read_image``); the camera's width and height must match.
    Segmentation is unknown (-1). Raises FrameError (MissingFrame, a FileNotFoundError, for a missing file) naming
    the file and the problem, also for depths no table-top camera sees (a median reading outside [MIN_DEPTH,
    MAX_DEPTH] m: metres saved as millimetres, or the reverse)."""
    camera = load_camera(camera_path)
    depth = read_image(depth_path, "depth file", cv2.IMREAD_UNCHANGED)
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise FrameError(f"depth file {depth_path!r} must be a single-channel 16-bit PNG in millimetres, got "
                         f"{depth.dtype} with shape {depth.shape}")
    stored = read_image(rgb_path, "colour file", cv2.IMREAD_UNCHANGED)
    if stored.dtype != np.uint8:  # IMREAD_COLOR would scale a 16-bit image (a depth frame given twice) to 8 bits
        raise FrameError(f"colour file {rgb_path!r} must be an 8-bit image, got {stored.dtype}"
                         f"{' (a depth frame?)' if stored.dtype == np.uint16 else ''}")
    rgb = cv2.cvtColor(read_image(rgb_path, "colour file", cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    if depth.shape != (camera.height, camera.width) or rgb.shape[:2] != depth.shape:
        raise FrameError(f"image sizes differ: depth {depth_path!r} {depth.shape}, colour {rgb_path!r} "
                         f"{rgb.shape[:2]}, camera {camera_path!r} {(camera.height, camera.width)}")
    metres = readings(depth.astype(np.float32) / 1000)  # 0: no reading (sim.sensor.is_reading)
    seen = is_reading(metres)
    if not seen.any():
        raise FrameError(f"depth file {depth_path!r} has no reading (every pixel 0)")
    check_table(metres, camera, f"depth file {depth_path!r} with camera {camera_path!r}")
    unknown = np.full(depth.shape, -1, np.int32)
    return Observation(metres, unknown, unknown, rgb), camera


def table_fit(depth, camera: Camera):
    """What says a depth frame [H, W] (m) shows a table where ``camera`` puts it: (the median height of its readings
    as world points, m; the share of readings within TABLE_BAND of that median; its median reading, m); NaN, 0, NaN
    for a frame with no reading. NumPy in, NumPy out (float64); JAX (traceable) otherwise, so ``check_table`` and
    the exported decision (``export``) judge a frame by the same numbers."""
    xp = jnp if isinstance(depth, jax.Array) else np
    depth = xp.asarray(depth)
    seen = is_reading(depth)
    z = camera.pixel_to_world(camera.pixel_centres(), xp.where(seen, depth, 1.0))[..., 2]
    height = xp.nanmedian(xp.where(seen, z, xp.nan))
    flat = xp.sum(seen & (xp.abs(z - height) < TABLE_BAND)) / xp.maximum(xp.sum(seen), 1)
    return height, flat, xp.nanmedian(xp.where(seen, depth, xp.nan))


def on_a_table(height, flat, median) -> bool:
    """Whether ``table_fit``'s numbers pass: the median point within TABLE_OFFSET of the table plane, TABLE_SHARE of
    the readings flat, the median reading within [MIN_DEPTH, MAX_DEPTH] (traceable)."""
    return (abs(height) <= TABLE_OFFSET) & (flat >= TABLE_SHARE) & (MIN_DEPTH <= median) & (median <= MAX_DEPTH)


def check_table(depth, camera: Camera, what: str) -> None:
    """FrameError naming ``what`` unless the frame shows a table where the camera says it is (``table_fit``, the rule
    of ``on_a_table``): its median reading within [MIN_DEPTH, MAX_DEPTH] m, its readings as world points (through the
    camera's intrinsics and pose) with a median height within TABLE_OFFSET of z = 0, and TABLE_SHARE of them within
    TABLE_BAND of that median (a flat table, not noise). Catches metres saved as millimetres, a depth scaled by
    mistake, a camera file of another camera or pose, and frames of no table."""
    height, flat, median = (float(x) for x in table_fit(np.asarray(depth), camera))
    if not MIN_DEPTH <= median <= MAX_DEPTH:
        raise FrameError(f"{what}: its median reading is {median:g} m; a table-top camera sees [{MIN_DEPTH}, "
                         f"{MAX_DEPTH}] m (depth must be saved in millimetres)")
    if not (np.isfinite(height) and abs(height) <= TABLE_OFFSET):
        raise FrameError(f"{what}: the frame's median point lies {height:+.3f} m from the table plane the camera "
                         f"implies (at most {TABLE_OFFSET} m): the depth is scaled, or the camera's intrinsics or pose "
                         "are another camera's")
    if flat < TABLE_SHARE:
        raise FrameError(f"{what}: only {flat:.0%} of the readings lie within {TABLE_BAND} m of the table's height "
                         f"(a table top gives at least {TABLE_SHARE:.0%}): the depth is noise, or not of a table top")


def save_goal(path: str, mask) -> str:
    """Write a goal mask [H, W] bool as a black-and-white PNG (white = goal), atomically; ``load_goal`` reads it."""
    files.write_image(path, np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8))
    return path


def load_goal(path: str, camera: Camera) -> np.ndarray:
    """A goal mask [H, W] bool from a PNG (white = goal) of the camera's size."""
    image = read_mask(path, "goal file")
    if image.shape != (camera.height, camera.width):
        raise FrameError(f"goal file {path!r} is {image.shape}, the camera's images are "
                         f"{(camera.height, camera.width)}")
    if not (image > 127).any():
        raise FrameError(f"goal file {path!r} has no goal pixel (white, > 127)")
    return image > 127
