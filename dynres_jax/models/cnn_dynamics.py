"""The paper's CNN-dynamics baseline: f(z, u, ω) as a convolutional network on a top-down image of the particles.

Same interface as ``dynamics.Dynamics`` (``model(positions [N, 3] m, mask [N], action [4] m, code []) -> [N, 3] m``,
masked rows returned unchanged, and ``rollout``), so training, checkpoints, evaluation and the planner use it
unchanged; the pure ``dynamics.predict`` / ``dynamics.rollout`` of ``nnx.split(model)`` work on it as they are.

One call:

1. Image. A grid of G x G cells (``grid``) covers the bin square [-b, b]² (b = ``bin_half_width``, cell size
   c = 2b / G); array index [iy, ix] is the cell centred at (-b + (ix + ½) c, -b + (iy + ½) c). Channels (``splat``,
   ``cell_centres``):
   - occupancy: every valid particle is splatted bilinearly onto its four nearest cell centres (``tent_weights``;
     positions clamped to the square of cell centres, so each particle deposits its full weight, also within half a
     cell of a wall) and the image is normalised per ω: multiplied by ``PILE_SHARE * G² / n_valid``, so the total
     is ``PILE_SHARE * G²`` at every ω and a uniform pile covering the share ``PILE_SHARE`` of the bin reads about 1
     per cell. Differentiable in the positions.
   - the sweep heuristic's displacement (x, y) at the cell centres (``graph.sweep_displacement`` with every cell
     valid) divided by ``length_scale``: where the plate passes and how far it carries what lies there.
     Differentiable in the action.
   - the resolution code (``dynamics.resolution_code``) as a constant channel.
2. A small U-Net, width C (``channels``) at every level, 3 x 3 convolutions with ReLU: G -> two convs -> stride-2
   conv (G/2) -> conv -> stride-2 conv (G/4) -> conv -> nearest up-sampling x 2, concatenated with the G/2 features
   -> conv -> up-sampling x 2, concatenated with the G features -> conv -> 1 x 1 conv to 2 channels: a displacement
   field (x, y) in ``length_scale`` units. The receptive field is about 29 cells (36 cm at the defaults), longer
   than any push (25 cm).
3. Each valid particle moves by the field sampled bilinearly at its (x, y) (the transpose of the splat), z unchanged.
   ``residual`` (default on): plus the particle's own sweep displacement (exact, not sampled from the grid); the
   last layer starts at zero, so an untrained model IS the sweep heuristic, as ``Dynamics(residual=True)``.

Defaults (G = 32, C = 32) give 84,418 parameters (the GNN: 38,403).

Masks: masked particles are inert: their positions are replaced by zeros before anything is computed and they
deposit no weight, so garbage (even NaN) goes nowhere; their output equals their input.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
from flax import nnx
from jax.lax import Precision

from dynres_jax.config import SceneConfig, check_fields
from dynres_jax.models.dynamics import LENGTH_SCALE, rollout
from dynres_jax.models.graph import sweep_displacement

PILE_SHARE = 0.125  # share of the bin a typical pile covers: a uniform pile of that size reads about 1 per cell
IN_CHANNELS = 4  # occupancy, sweep displacement x and y, resolution code
HIGHEST = Precision.HIGHEST  # float32 products in the splat and the sampling (no TF32 on GPUs)


@dataclass(frozen=True)
class CNNDynamicsConfig:
    """Static configuration of the CNN f. grid: cells per side G over the bin square (a multiple of 4, >= 8);
    channels: width C of every convolution; bin_half_width (m): half the side of the imaged square; plate_half_width
    (m): the sweep heuristic's plate; length_scale (m): the model's unit of length; residual: predict a correction to
    the sweep heuristic."""

    grid: int = 32
    channels: int = 32
    bin_half_width: float = SceneConfig.bin_half_width
    plate_half_width: float = SceneConfig.plate_half_width
    length_scale: float = LENGTH_SCALE
    residual: bool = True

    def __post_init__(self):
        check_fields(self)
        if not 8 <= self.grid <= 512 or self.grid % 4:
            raise ValueError(f"grid must be a multiple of 4 in [8, 512] (two stride-2 levels), got {self.grid}")
        if not 1 <= self.channels <= 4096:
            raise ValueError(f"channels must be in [1, 4096], got {self.channels}")
        if not all(0 < x <= 1 for x in (self.bin_half_width, self.length_scale, self.plate_half_width)):
            raise ValueError("bin_half_width, plate_half_width and length_scale must be positive and at most 1 m")


def cell_centres(grid: int, half_width: float):
    """Cell centres [G * G, 3] m (z = 0) in the order of a flattened [G, G] image (row iy, column ix)."""
    c = 2 * half_width / grid
    axis = -half_width + (jnp.arange(grid, dtype=jnp.float32) + 0.5) * c
    y, x = jnp.meshgrid(axis, axis, indexing="ij")
    return jnp.stack([x.ravel(), y.ravel(), jnp.zeros(grid * grid)], axis=-1)


def tent_weights(points, grid: int, half_width: float):
    """Bilinear weights of points [N, 2+] m on the grid, per axis: (wx [N, G], wy [N, G]), w[i, j] = max(0, 1 -
    |u_i - j|) with u_i the point's coordinate in cell-centre units, clamped to [0, G - 1] (so each row sums to 1 and
    points near a wall or outside the bin go to the border cells). A point's weight on cell [iy, ix] is
    wy[i, iy] * wx[i, ix]. Differentiable in the points."""
    u = jnp.clip((points[:, :2] + half_width) / (2 * half_width / grid) - 0.5, 0.0, grid - 1.0)  # [N, 2]: (x, y)
    w = jnp.maximum(1.0 - jnp.abs(u[:, :, None] - jnp.arange(grid, dtype=jnp.float32)), 0.0)  # [N, 2, G]
    return w[:, 0], w[:, 1]


def splat(positions, mask, grid: int, half_width: float):
    """Occupancy image [G, G] of the valid particles (positions [N, 3] m, mask [N] bool): bilinear splat normalised
    per ω to a total of ``PILE_SHARE * G²`` (zero when no particle is valid); see the module docstring. Written as
    a product of the per-axis weights (no scatter), so it is deterministic on GPUs too."""
    wx, wy = tent_weights(jnp.where(mask[:, None], positions, 0.0), grid, half_width)
    wy = jnp.where(mask[:, None], wy, 0.0) * (PILE_SHARE * grid * grid / jnp.maximum(jnp.sum(mask), 1))
    return jnp.einsum("ny,nx->yx", wy, wx, precision=HIGHEST)


def sample(image, points, half_width: float):
    """Bilinear sample of image [G, G, K] at points [N, 2+] m -> [N, K] (the transpose of ``splat``'s weights)."""
    wx, wy = tent_weights(points, image.shape[0], half_width)
    return jnp.einsum("ny,nx,yxk->nk", wy, wx, image, precision=HIGHEST)


def _up(x):
    """Nearest-neighbour up-sampling x 2 of [1, H, W, K]."""
    return jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)


class CNNDynamics(nnx.Module):
    """f(z, u, ω) as a convolutional network on the particles' image; see the module docstring."""

    def __init__(self, config: CNNDynamicsConfig = CNNDynamicsConfig(), *, rngs: nnx.Rngs):
        c = config.channels
        self.config = config

        def conv(n_in, n_out, stride=1, kernel=3):
            return nnx.Conv(n_in, n_out, (kernel, kernel), strides=stride, padding="SAME", rngs=rngs)

        self.stem = nnx.Sequential(conv(IN_CHANNELS, c), nnx.relu, conv(c, c), nnx.relu)  # G
        self.down1 = nnx.Sequential(conv(c, c, 2), nnx.relu, conv(c, c), nnx.relu)  # G / 2
        self.down2 = nnx.Sequential(conv(c, c, 2), nnx.relu, conv(c, c), nnx.relu)  # G / 4
        self.up1 = conv(2 * c, c)  # [up-sampled G / 4 features, G / 2 features] -> G / 2
        self.up0 = conv(2 * c, c)  # [up-sampled G / 2 features, G features] -> G
        self.head = conv(c, 2, kernel=1)  # displacement field (x, y) in length_scale units
        if config.residual:  # the correction starts at zero: an untrained model is the sweep heuristic
            self.head.kernel[...] = jnp.zeros_like(self.head.kernel[...])
            self.head.bias[...] = jnp.zeros_like(self.head.bias[...])

    def field(self, positions, mask, action, code):
        """The predicted displacement field [G, G, 2] (x, y; ``length_scale`` units, without the residual sweep) of
        the scene: positions [N, 3] m, mask [N] bool, action [4] m, code []."""
        cfg, g = self.config, self.config.grid
        occupancy = splat(positions, mask, g, cfg.bin_half_width)
        centres = cell_centres(g, cfg.bin_half_width)
        sweep = sweep_displacement(centres, jnp.ones(g * g, bool), action, cfg.plate_half_width)[:, :2]
        image = jnp.concatenate([occupancy[..., None], (sweep / cfg.length_scale).reshape(g, g, 2),
                                 jnp.broadcast_to(jnp.asarray(code, jnp.float32), (g, g, 1))], axis=-1)[None]
        x0 = self.stem(image)
        x1 = self.down1(x0)
        x2 = self.down2(x1)
        x1 = nnx.relu(self.up1(jnp.concatenate([_up(x2), x1], axis=-1)))
        x0 = nnx.relu(self.up0(jnp.concatenate([_up(x1), x0], axis=-1)))
        return self.head(x0)[0]

    def __call__(self, positions, mask, action, code):
        """positions [N, 3] m, mask [N] bool, action [4] m, code [] (``resolution_code``) -> next positions [N, 3] m.
        Masked rows are returned unchanged."""
        cfg = self.config
        positions = jnp.asarray(positions, jnp.float32)
        mask = jnp.asarray(mask, bool)
        action = jnp.asarray(action, jnp.float32)
        clean = jnp.where(mask[:, None], positions, 0.0)
        moved = sample(self.field(clean, mask, action, code), clean, cfg.bin_half_width) * cfg.length_scale
        displacement = jnp.concatenate([moved, jnp.zeros_like(moved[:, :1])], axis=-1)
        if cfg.residual:
            displacement = displacement + sweep_displacement(clean, mask, action, cfg.plate_half_width)
        return jnp.where(mask[:, None], positions + displacement, positions)

    def rollout(self, positions, mask, actions, code):
        """positions [N, 3] m, mask [N], actions [T, 4] m, code [] -> positions after each action [T, N, 3] m."""
        return rollout(*nnx.split(self), positions, mask, actions, code)
