"""Closed loop (model-predictive control) at a fixed resolution ω: observe -> h(y, ω) -> plan -> push, repeated.

Each step samples ω particles from the current observation, plans pushes on the task objective c of the particles
the dynamics model predicts (``planner.plan``), executes the first push of the best sequence in the simulator, and
records: ω, c of the particles before planning, the c the planner predicted, the distribution distance d and the
share of pieces inside the goal after the push, and the planning time. The previous plan, shifted, warm-starts the
next. Dynamics: a trained ``Dynamics`` model (``learned_dynamics``) or the sweep heuristic (``sweep_dynamics``).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.tree_util import Partial

from dynres_jax.dynamics import Dynamics, resolution_code, rollout
from dynres_jax.graph import sweep_rollout
from dynres_jax.objective import Goal, distribution_distance, inside_share, objective
from dynres_jax.perception import sample_particles
from dynres_jax.planner import PlannerConfig, plan
from dynres_jax.sim.env import PileEnv, State


@dataclass(frozen=True)
class MPCConfig:
    """steps: MPC steps per episode (reference 20); omega: particles (fixed resolution); n_max: particle slots;
    max_points: perception's point cap; planner: the shooting optimiser's settings."""

    steps: int = 20
    omega: int = 50
    n_max: int = 100
    max_points: int | None = 4096
    planner: PlannerConfig = field(default_factory=PlannerConfig)

    def __post_init__(self):
        if not 1 <= self.omega <= self.n_max:
            raise ValueError(f"omega={self.omega} must lie in [1, n_max={self.n_max}]")
        if self.steps < 1:
            raise ValueError(f"steps must be positive, got {self.steps}")


def _learned(graphdef, state, code, positions, mask, actions):
    return rollout(graphdef, state, positions, mask, actions, code)


def _sweep(plate_half_width, positions, mask, actions):
    return sweep_rollout(positions, mask, actions, plate_half_width)


def learned_dynamics(model: Dynamics):
    """radius (m) -> planner dynamics ``(positions, mask, actions [T, 4]) -> [T, N, 3]`` of a trained model."""
    graphdef, state = nnx.split(model)
    return lambda radius: Partial(_learned, graphdef, state, resolution_code(radius))


def sweep_dynamics(plate_half_width: float):
    """radius -> planner dynamics of the sweep heuristic alone (the resolution is irrelevant to it)."""
    return lambda radius: Partial(_sweep, jnp.float32(plate_half_width))


def load_dynamics(choice: str, ckpt_dir: str, plate_half_width: float):
    """The planner's model. choice: "learned" (the checkpoint in ``ckpt_dir``), "sweep" (the heuristic), or "auto"
    (the checkpoint when there is one). Returns (radius -> dynamics, n_max the model was trained for, a name)."""
    from dynres_jax import ckpt
    from dynres_jax.train import build_model

    if choice not in ("auto", "learned", "sweep"):
        raise ValueError(f"dynamics must be 'auto', 'learned' or 'sweep', got {choice!r}")
    if choice == "learned" or (choice == "auto" and ckpt.latest_step(ckpt_dir) is not None):
        model, meta, _ = ckpt.load_module(ckpt_dir, build_model)
        return learned_dynamics(model), meta["train"]["n_max"], f"learned ({ckpt_dir}, step {meta.get('step')})"
    return sweep_dynamics(plate_half_width), 100, "sweep heuristic"


def _cost(camera, goal, positions, mask):
    return objective(positions, mask, goal, camera)


def goal_cost(goal: Goal, camera) -> Partial:
    """The planner's cost: the task objective c of predicted particles against ``goal``."""
    return Partial(functools.partial(_cost, camera), goal)


def overlay(rgb: np.ndarray, goal_mask: np.ndarray, particles: np.ndarray | None, camera, scale: int = 3):
    """An RGB frame [H, W, 3] uint8 with the goal tinted green and particles [n, 3] (world, m) as red dots."""
    img = rgb.astype(np.float32)
    img[goal_mask] = 0.6 * img[goal_mask] + 0.4 * np.array([60.0, 200.0, 60.0])
    img = cv2.resize(img.astype(np.uint8), (rgb.shape[1] * scale, rgb.shape[0] * scale),
                     interpolation=cv2.INTER_NEAREST)
    if particles is not None and len(particles):
        uv, _ = camera.world_to_pixel(np.asarray(particles, np.float64))
        for u, v in np.asarray(uv) * scale:
            cv2.circle(img, (int(u), int(v)), max(2, scale), (220, 30, 30), -1)
    return img


def run_episode(env: PileEnv, state: State, goal: Goal, goal_mask: np.ndarray, dynamics, cfg: MPCConfig, key,
                log=print) -> tuple[State, list[dict], list[np.ndarray]]:
    """One episode from ``state`` towards ``goal``. dynamics: ``learned_dynamics(model)`` or ``sweep_dynamics(hw)``.
    Returns the final state, one record per step, and GIF frames (observation, goal and particles)."""
    camera = env.camera
    cost = goal_cost(goal, camera)
    records, frames, init = [], [], None
    for t in range(cfg.steps):
        k_h, k_plan = jax.random.split(jax.random.fold_in(key, t))
        particles = sample_particles(state.obs, camera, cfg.omega, k_h, cfg.n_max, max_points=cfg.max_points)
        c_now = float(objective(particles.positions, particles.mask, goal, camera))
        frames.append(overlay(np.asarray(state.obs.rgb), goal_mask, np.asarray(particles.positions)[
            np.asarray(particles.mask)], camera))
        t0 = time.perf_counter()
        result = plan(dynamics(particles.radius), cost, particles.positions, particles.mask, k_plan, cfg.planner,
                      init=init)
        action = np.asarray(jax.block_until_ready(result.best[0]))
        planning = time.perf_counter() - t0
        state = env.push(state, action)
        init = jnp.concatenate([result.best[1:], result.best[-1:]])  # shift the plan: warm start of the next step
        record = dict(step=t, omega=cfg.omega, objective=c_now, predicted_objective=float(result.best_cost),
                      distance=float(distribution_distance(state.obs, goal, camera)),
                      success=float(inside_share(state.pos, jnp.ones(env.scene.n_pieces, bool), goal, camera)),
                      planning_s=planning, action=action.tolist(), broken=bool(state.broken))
        records.append(record)
        log(f"step {t + 1:2d}/{cfg.steps}  ω={cfg.omega}  c={c_now:7.2f} -> predicted "
            f"{record['predicted_objective']:7.2f}  d={record['distance']:7.2f}  inside={record['success']:5.1%}  "
            f"plan {planning:5.2f}s")
        if record["broken"]:
            log("the simulated world broke (NaN or a piece out of the bin); stopping the episode")
            break
    frames.append(overlay(np.asarray(state.obs.rgb), goal_mask, None, camera))
    return state, records, frames
