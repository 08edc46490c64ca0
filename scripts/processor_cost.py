"""Planner cost of each dynamics processor shape (docs/dynamics_scale): one 50 x 100 plan at ω = 50 in 64 slots (its
bucket until 2026-11-29; since then 50) with untrained weights of each shape, timed after its compile, on this
machine's JAX device.

    python scripts/processor_cost.py
"""

import time

import jax
import numpy as np
from flax import nnx

from dynres_jax.config import CameraConfig
from dynres_jax.control.decision import goal_cost
from dynres_jax.control.goals import disc_goal, make_goal
from dynres_jax.control.planner import PlannerConfig, plan
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig
from dynres_jax.models.registry import learned_dynamics
from dynres_jax.sim.camera import Camera

SHAPES = {"PropNet 64 x 3 (shipped)": DynamicsConfig(),
          "PropNet 128 x 5": DynamicsConfig(hidden=128, propagation_steps=5),
          "GNS 64 x 3": DynamicsConfig(processor="gns"),
          "GNS 128 x 5": DynamicsConfig(processor="gns", hidden=128, propagation_steps=5)}


def main():
    camera = Camera.top_down(CameraConfig())
    cost = goal_cost(make_goal(disc_goal(camera, np.zeros(2), 0.08), camera), camera, 64)
    rng = np.random.default_rng(0)
    positions = np.zeros((64, 3), np.float32)
    positions[:50, :2] = rng.uniform(-0.1, 0.1, (50, 2))
    positions[:50, 2] = 0.007
    mask = np.arange(64) < 50
    config = PlannerConfig(samples=50, adam_steps=100)
    base = None
    for name, shape in SHAPES.items():
        dynamics = learned_dynamics(Dynamics(shape, rngs=nnx.Rngs(0)))(0.02)
        jax.block_until_ready(plan(dynamics, cost, positions, mask, jax.random.PRNGKey(0), config).best)  # compile
        t0 = time.perf_counter()
        jax.block_until_ready(plan(dynamics, cost, positions, mask, jax.random.PRNGKey(1), config).best)
        seconds = time.perf_counter() - t0
        base = base or seconds
        print(f"{name}: {seconds:.2f} s a plan ({seconds / base:.1f}x), {jax.devices()[0].device_kind}", flush=True)


if __name__ == "__main__":
    main()
