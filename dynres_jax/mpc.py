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
from typing import TYPE_CHECKING

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

if TYPE_CHECKING:  # annotations only: the planning half of this module needs no simulator (nor MuJoCo)
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


def decide(obs, goal: Goal, key, init, dynamics, cfg: MPCConfig, camera):
    """One MPC decision: particles from ``obs`` (h at ω), c of them, and the plan. Pure, so it vmaps over episodes.
    Returns (Particles, c [], PlanResult)."""
    k_h, k_plan = jax.random.split(key)
    particles = sample_particles(obs, camera, cfg.omega, k_h, cfg.n_max, max_points=cfg.max_points)
    c_now = objective(particles.positions, particles.mask, goal, camera)
    result = plan(dynamics(particles.radius), goal_cost(goal, camera), particles.positions, particles.mask, k_plan,
                  cfg.planner, init=init)
    return particles, c_now, result


def _shift(best):
    """The plan of the next step: the remaining pushes, the last one repeated (warm start)."""
    return jnp.concatenate([best[..., 1:, :], best[..., -1:, :]], axis=-2)


def run_episode(env: PileEnv, state: State, goal: Goal, goal_mask: np.ndarray, dynamics, cfg: MPCConfig, key,
                log=print) -> tuple[State, list[dict], list[np.ndarray]]:
    """One episode from ``state`` towards ``goal``. dynamics: ``learned_dynamics(model)`` or ``sweep_dynamics(hw)``.
    Returns the final state, one record per step, and GIF frames (observation, goal and particles)."""
    camera = env.camera
    records, frames, init = [], [], None
    for t in range(cfg.steps):
        t0 = time.perf_counter()
        particles, c_now, result = decide(state.obs, goal, jax.random.fold_in(key, t), init, dynamics, cfg, camera)
        action = np.asarray(jax.block_until_ready(result.best[0]))
        planning = time.perf_counter() - t0
        frames.append(overlay(np.asarray(state.obs.rgb), goal_mask, np.asarray(particles.positions)[
            np.asarray(particles.mask)], camera))
        state = env.push(state, action)
        init = _shift(result.best)
        record = dict(step=t, omega=cfg.omega, objective=float(c_now), predicted_objective=float(result.best_cost),
                      distance=float(distribution_distance(state.obs, goal, camera)),
                      success=float(inside_share(state.pos, jnp.ones(env.scene.n_pieces, bool), goal, camera)),
                      planning_s=planning, action=action.tolist(), broken=bool(state.broken))
        records.append(record)
        log(f"step {t + 1:2d}/{cfg.steps}  ω={cfg.omega}  c={record['objective']:7.2f} -> predicted "
            f"{record['predicted_objective']:7.2f}  d={record['distance']:7.2f}  inside={record['success']:5.1%}  "
            f"plan {planning:5.2f}s")
        if record["broken"]:
            log("the simulated world broke (NaN or a piece out of the bin); stopping the episode")
            break
    frames.append(overlay(np.asarray(state.obs.rgb), goal_mask, None, camera))
    return state, records, frames


def run_episodes(env: PileEnv, states: State, goals: Goal, dynamics, cfg: MPCConfig, keys,
                 log=print) -> tuple[State, list[dict]]:
    """Many episodes at once (backend "mjx"): states and goals batched on a leading axis [B], keys [B]. Each MPC step
    is one compiled call over all episodes (perception, planning, objective) and one batched push. Returns the final
    states and one record per step whose values are arrays [B] (c, predicted c, d, inside share, broken)."""
    if env.backend != "mjx":
        raise ValueError("run_episodes needs backend='mjx' (its pushes are vmapped); loop run_episode otherwise")
    camera = env.camera
    n = env.scene.n_pieces

    def step(obs, goal, key, init):
        return decide(obs, goal, key, init, dynamics, cfg, camera)

    def measure(obs, pos, goal):
        return distribution_distance(obs, goal, camera), inside_share(pos, jnp.ones(n, bool), goal, camera)

    first, later = jax.jit(jax.vmap(lambda o, g, k: step(o, g, k, None))), jax.jit(jax.vmap(step))
    push, measure = jax.jit(jax.vmap(env.push)), jax.jit(jax.vmap(measure))
    records, init = [], None
    for t in range(cfg.steps):
        t0 = time.perf_counter()
        step_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, t)
        if init is None:
            _, c_now, result = first(states.obs, goals, step_keys)
        else:
            _, c_now, result = later(states.obs, goals, step_keys, init)
        states = push(states, result.best[:, 0])
        init = _shift(result.best)
        distance, success = measure(states.obs, states.pos, goals)
        record = {k: np.asarray(v) for k, v in dict(objective=c_now, predicted_objective=result.best_cost,
                                                     distance=distance, success=success, broken=states.broken).items()}
        records.append(dict(step=t, omega=cfg.omega, seconds=time.perf_counter() - t0, **record))
        log(f"step {t + 1:2d}/{cfg.steps}  {len(keys)} episodes  ω={cfg.omega}  mean d={record['distance'].mean():7.2f}"
            f"  mean inside={record['success'].mean():5.1%}  {records[-1]['seconds']:5.2f}s")
    return states, records
