"""What a real depth camera adds to the simulator's perfect depth: ``DepthSensor`` (defaults: an Intel RealSense
D455 one metre above the table, from its public specifications and the stereo error model).

- Depth noise grows with distance squared: σ(z) = z² ε / (f B), ε the stereo matcher's subpixel error (0.08 px, the
  RealSense white paper's typical figure), f the focal length in pixels (447 px: 848 px across an 87° field of view)
  and B the baseline (95 mm): ``noise_per_m2`` = 0.0019 m⁻¹, 1.9 mm at 1 m. (The data sheet's bound, under 2 % at
  4 m, allows more; the profile is the typical camera, not the worst.)
- Missing pixels: at depth edges (stereo occlusion) a reading is missing with probability ``edge_drop``; anywhere
  with ``dropout``. A missing reading is ``NO_READING`` metres (beyond the table), as ``io.frames.load_frame`` reads a
  saved 0.
- Flying pixels: with probability ``flying`` an edge pixel takes the mean depth of its 3 x 3 neighbourhood, a point
  floating between the pile and the table.
- Quantisation: depth is saved in whole millimetres (a 16-bit PNG), ``quantum``.
- Extrinsic calibration error: the planner's believed camera is the true one turned by ``tilt_deg`` about a random
  horizontal axis and moved by ``shift_m`` in a random direction (``believed_camera``).

Perception meets this with ``perception.calibrate`` (the camera's pose refined from the bin in the first frame: the
table plane and the walls) and ``perception.foreground(real_depth=True)`` (``MPCConfig.real_depth``): a 3 x 3 median
of the readings given removes isolated flying and noisy pixels and keeps edges, and heights are taken over the table
plane fitted from the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.sim.camera import Camera, Observation, neighbourhoods, rotation_about

NO_READING = 100.0  # m: the depth of a missing reading (beyond the table, so never foreground)


def is_reading(depth):
    """Where a depth image [..] (m) holds a reading: finite, above 0 and below ``NO_READING``. The one rule every path
    (perception, the robot's loop, the exported decision, recorded frames) uses: 0 (what depth cameras write for a
    missing pixel), NaN, ±inf, negative depths and ``NO_READING`` are no reading, never a point. NumPy in, NumPy out;
    JAX (traceable) otherwise."""
    xp = jnp if isinstance(depth, jax.Array) else np
    depth = xp.asarray(depth)
    return xp.isfinite(depth) & (depth > 0) & (depth < NO_READING)


def readings(depth):
    """depth [..] (m) with every pixel that is no reading (``is_reading``) set to ``NO_READING``, float32."""
    xp = jnp if isinstance(depth, jax.Array) else np
    depth = xp.asarray(depth, xp.float32)
    return xp.where(is_reading(depth), depth, xp.float32(NO_READING))


@dataclass(frozen=True)
class DepthSensor:
    """A depth camera's errors (module docstring); every field's unit is in its name or there."""

    noise_per_m2: float = 0.0019  # m of depth σ per m² of depth
    edge_step: float = 0.004  # m: a pixel whose depth differs from a 4-neighbour's by more is at an edge
    edge_drop: float = 0.3
    dropout: float = 0.005
    flying: float = 0.3
    quantum: float = 0.001  # m
    tilt_deg: float = 0.3
    shift_m: float = 0.002

    def observe(self, obs: Observation, key) -> Observation:
        """The observation as this camera would give it: noisy, with holes and flying pixels, quantised. Pure JAX
        (vmap it over episodes)."""
        k_noise, k_edge, k_drop, k_fly = jax.random.split(key, 4)
        depth = jnp.asarray(obs.depth, jnp.float32)
        neighbours = neighbourhoods(depth)  # [9, H, W]
        edge = jnp.max(jnp.abs(neighbours[jnp.array([1, 3, 5, 7])] - depth), axis=0) > self.edge_step
        flying = edge & (jax.random.uniform(k_fly, depth.shape) < self.flying)
        depth = jnp.where(flying, jnp.mean(neighbours, axis=0), depth)
        depth = depth + self.noise_per_m2 * depth**2 * jax.random.normal(k_noise, depth.shape)
        depth = jnp.round(depth / self.quantum) * self.quantum
        missing = (edge & ~flying & (jax.random.uniform(k_edge, depth.shape) < self.edge_drop)) | (
            jax.random.uniform(k_drop, depth.shape) < self.dropout)
        return obs._replace(depth=jnp.where(missing, NO_READING, depth))

    def believed_camera(self, camera: Camera, seed: int = 0) -> Camera:
        """The camera the planner believes in: ``camera`` with this sensor's calibration error, drawn from seed."""
        rng = np.random.default_rng(seed)
        axis = np.array([*rng.normal(size=2), 0.0])
        axis /= np.linalg.norm(axis)
        turn = rotation_about(axis, np.radians(self.tilt_deg))
        shift = rng.normal(size=3)
        shift *= self.shift_m / np.linalg.norm(shift)
        return Camera(camera.K, turn @ camera.rotation, camera.centre + shift, camera.width, camera.height)


SENSORS = {  # --sensor's choices
    "none": None,
    "realsense": DepthSensor(),
    "realsense-calibrated": DepthSensor(tilt_deg=0.0, shift_m=0.0),  # the same camera without extrinsic error
}
