"""The regressor g(y_0, y_g) -> ω (paper Sec. IV-C), trained on the labels of ``resolution.bo`` (``learn.regressor``).

``regressor_input`` turns a foreground mask and a goal mask into the paper's six channels (current mask, goal mask,
their distance transforms, current minus goal, goal minus current) on a coarse ``FEATURE_SIZE`` grid; ``Regressor``
is a small CNN (about 60k parameters; the reference's has 114M) that maps them to ω.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from dynres_jax.config import OMEGA_MAX, OMEGA_MIN
from dynres_jax.io import ckpt
from dynres_jax.models.registry import describe
from dynres_jax.perception import foreground

FEATURE_SIZE = 32  # regressor input grid (pixels a side)


def _pool_mask(mask, size):
    """Boolean [H, W] -> [size, size] float: share of covered pixels per cell (H and W multiples of size)."""
    h, w = mask.shape
    if h % size or w % size:
        raise ValueError(f"image {h}x{w} must be a multiple of the feature grid {size}")
    return mask.astype(jnp.float32).reshape(size, h // size, size, w // size).mean(axis=(1, 3))


def _distance_transform(occupied):
    """Distance (in grid cells / size) from each cell of [S, S] to the nearest occupied cell (> 0.5); 0 inside;
    sqrt(2) when nothing is occupied. Exact, by brute force over cell pairs (S² x S², fine at S = 32)."""
    s = occupied.shape[0]
    ij = jnp.stack(jnp.meshgrid(jnp.arange(s), jnp.arange(s), indexing="ij"), -1).reshape(-1, 2).astype(jnp.float32)
    d = jnp.linalg.norm(ij[:, None] - ij[None], axis=-1)
    d = jnp.where(occupied.reshape(-1)[None] > 0.5, d, jnp.inf).min(axis=1)
    return jnp.minimum(d / s, jnp.sqrt(2.0)).reshape(s, s)


def regressor_input(current_mask, goal_mask, size: int = FEATURE_SIZE):
    """The paper's six input channels on a [size, size] grid: current [H, W] bool (foreground) and goal [H, W]
    bool masks -> [size, size, 6] (current, goal, their distance transforms, current minus goal, goal minus
    current). Pure JAX; vmap over scenes."""
    cur, goal = _pool_mask(jnp.asarray(current_mask), size), _pool_mask(jnp.asarray(goal_mask), size)
    return jnp.stack([cur, goal, _distance_transform(cur), _distance_transform(goal), jnp.maximum(cur - goal, 0),
                      jnp.maximum(goal - cur, 0)], -1)


class Regressor(nnx.Module):
    """g: [size, size, 6] regressor input -> ω in [OMEGA_MIN, OMEGA_MAX] (float). Four stride-2 3x3 convolutions
    (channels ``width`` .. 4 x width), global average pooling, an MLP, and a sigmoid scaled to the ω range."""

    def __init__(self, width: int = 16, *, rngs: nnx.Rngs):
        chans = (6, width, 2 * width, 4 * width, 4 * width)
        self.convs = nnx.List([nnx.Conv(a, b, (3, 3), strides=2, rngs=rngs) for a, b in zip(chans[:-1], chans[1:],
                                                                                            strict=True)])
        self.hidden = nnx.Linear(chans[-1], 32, rngs=rngs)
        self.out = nnx.Linear(32, 1, rngs=rngs)

    def __call__(self, x):
        """x [..., S, S, 6] -> ω [...]."""
        lead = x.shape[:-3]
        h = x.reshape((-1,) + x.shape[-3:])
        for conv in self.convs:
            h = nnx.relu(conv(h))
        h = nnx.relu(self.hidden(h.mean(axis=(1, 2))))
        unit = nnx.sigmoid(self.out(h))[:, 0]
        return (OMEGA_MIN + (OMEGA_MAX - OMEGA_MIN) * unit).reshape(lead)


def observation_input(obs, goal_mask, camera, size: int = FEATURE_SIZE):
    """``regressor_input`` of an Observation (its foreground, ``perception.foreground``) and a goal mask [H, W]:
    what labelling stores and what the adaptive MPC feeds g, computed one way. Pure JAX; vmap over scenes."""
    current = foreground(obs, camera)[1].reshape(camera.height, camera.width)
    return regressor_input(current, goal_mask, size)


def choose_omega(graphdef, state, inputs):
    """Adaptive ω of a trained regressor (``nnx.split``): regressor inputs [..., S, S, 6] -> integer ω [...] in
    range."""
    omega = nnx.merge(graphdef, state)(inputs)
    return jnp.clip(jnp.round(omega), OMEGA_MIN, OMEGA_MAX).astype(jnp.int32)


def build_regressor(meta: dict) -> Regressor:
    """A fresh regressor from a checkpoint card (``ckpt.load_module``'s ``build``)."""
    if "width" not in meta or "dynamics" in meta:
        raise ValueError(f"it holds {describe(meta)}, not an ω regressor")
    return Regressor(width=meta["width"], rngs=nnx.Rngs(0))


def load_regressor(regressor_dir: str, camera):
    """The regressor g of a trained checkpoint as a jitted ``(obs [B], goals [B]) -> ω [B]`` (Observation and Goal
    batched): what ``choosers.AdaptiveOmega`` asks every MPC step."""
    graphdef, state = nnx.split(ckpt.load_module(regressor_dir, build_regressor)[0])

    @jax.jit
    def choose(obs, goals):
        inputs = jax.vmap(lambda o, m: observation_input(o, m, camera))(obs, goals.mask)
        return choose_omega(graphdef, state, inputs)

    return choose
