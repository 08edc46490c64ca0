"""Recorded RGBD frames as depth cameras save them: depth in millimetres as a 16-bit PNG (0 = no reading), colour
as an 8-bit PNG, the camera as JSON (``Camera.to_json``), a goal as a black-and-white PNG. The simulator writes the
same format (``save_frame``), so real and simulated frames go through one loader."""

from __future__ import annotations

import os

import cv2
import numpy as np

from dynres_jax.io import files
from dynres_jax.sim.camera import Camera, Observation
from dynres_jax.sim.sensor import NO_READING


def save_frame(folder: str, obs: Observation, camera: Camera) -> dict[str, str]:
    """Write depth.png (uint16 mm), rgb.png and camera.json into ``folder``; returns their paths."""
    os.makedirs(folder, exist_ok=True)
    paths = {name: os.path.join(folder, name) for name in ("depth.png", "rgb.png", "camera.json")}
    depth_mm = np.clip(np.round(np.asarray(obs.depth, np.float64) * 1000), 0, 65535).astype(np.uint16)
    files.write_image(paths["depth.png"], depth_mm)
    files.write_image(paths["rgb.png"], cv2.cvtColor(np.asarray(obs.rgb, np.uint8), cv2.COLOR_RGB2BGR))
    files.write_text(paths["camera.json"], camera.to_json())
    return paths


def _read(path: str, what: str, flags: int) -> np.ndarray:
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{what} file {path!r} does not exist")
    image = cv2.imread(path, flags)
    if image is None:
        raise ValueError(f"{what} file {path!r} is not a readable image")
    return image


def load_frame(depth_path: str, rgb_path: str, camera_path: str) -> tuple[Observation, Camera]:
    """Read a recorded frame. Depth must be a single-channel 16-bit PNG in millimetres (0, no reading, becomes
    ``NO_READING`` metres: beyond the table, so never foreground);
    colour an 8-bit image of the same size; the camera's width and height must match. Segmentation is unknown
    (-1). Raises FileNotFoundError or ValueError naming the file and the problem."""
    if not os.path.isfile(camera_path):
        raise FileNotFoundError(f"camera file {camera_path!r} does not exist")
    with open(camera_path) as f:
        camera = Camera.from_json(f.read())
    depth = _read(depth_path, "depth", cv2.IMREAD_UNCHANGED)
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise ValueError(f"depth file {depth_path!r} must be a single-channel 16-bit PNG in millimetres, got "
                         f"{depth.dtype} with shape {depth.shape}")
    rgb = cv2.cvtColor(_read(rgb_path, "colour", cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    if depth.shape != (camera.height, camera.width) or rgb.shape[:2] != depth.shape:
        raise ValueError(f"image sizes differ: depth {depth.shape}, colour {rgb.shape[:2]}, camera "
                         f"{(camera.height, camera.width)}")
    metres = np.where(depth > 0, depth.astype(np.float32) / 1000, NO_READING).astype(np.float32)
    unknown = np.full(depth.shape, -1, np.int32)
    return Observation(metres, unknown, unknown, rgb), camera


def load_goal(path: str, camera: Camera) -> np.ndarray:
    """A goal mask [H, W] bool from a PNG (white = goal) of the camera's size."""
    image = _read(path, "goal", cv2.IMREAD_GRAYSCALE)
    if image.shape != (camera.height, camera.width):
        raise ValueError(f"goal file {path!r} is {image.shape}, the camera's images are "
                         f"{(camera.height, camera.width)}")
    return image > 127
