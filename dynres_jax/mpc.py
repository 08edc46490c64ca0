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
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.tree_util import Partial

from dynres_jax.dynamics import Dynamics, edge_table, resolution_code, rollout
from dynres_jax.graph import sweep_rollout
from dynres_jax.objective import Goal, distribution_distance, inside_share, objective
from dynres_jax.perception import sample_particles
from dynres_jax.planner import PlannerConfig, budget_steps, plan, steps_for_budget

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


EDGE_DTYPES = ("float32", "bfloat16")  # ``learned_dynamics``'s choices for the GNN's per-edge network


@dataclass(frozen=True)
class _Learned:
    """A trained model's rollout as a planner dynamics, called with ``(graphdef, state, code)`` bound by
    ``learned_dynamics``' Partial. With ``pair_table`` it offers the planner's per-plan hook ``prepare``: the pair
    table of each re-sampling, built once per plan instead of once per Adam step (XLA does not hoist it out of the
    step loop itself: the table is larger than its inputs). Instances compare by value, so equal options share one
    compiled plan."""

    edge_dtype: str
    pair_table: bool

    def __call__(self, graphdef, state, code, positions, mask, actions, context=None):
        return rollout(graphdef, state, positions, mask, actions, code, edge_dtype=self.edge_dtype,
                       pair_table=self.pair_table, table=context)

    def prepare(self, graphdef, state, code, positions, mask):
        """positions [N, 3], mask [N] -> the context of ``__call__``: the pair table [N, N, H], or None."""
        if not self.pair_table:
            return None
        return edge_table(graphdef, state, positions, mask, code, edge_dtype=self.edge_dtype)


def _sweep(plate_half_width, positions, mask, actions):
    return sweep_rollout(positions, mask, actions, plate_half_width)


def learned_dynamics(model: Dynamics, edge_dtype: str = "float32"):
    """radius (m) -> planner dynamics ``(positions, mask, actions [T, 4]) -> [T, N, 3]`` of a trained model.
    edge_dtype: "float32", or "bfloat16" for a GNN's per-edge network (predictions within about half a
    millimetre, ``dynamics`` module docstring, "Mixed precision"; no faster on the H100 and H200: README, "Planner
    speed"). A GNN whose edges are not in the push frame takes the first push's edge codes from a pair table
    (``dynamics`` module docstring, "Pair table"): the planner's pushes all start from the same particles, so the
    table is built once per plan, not per push and Adam step."""
    edge_dtype = jnp.dtype(edge_dtype).name
    if edge_dtype not in EDGE_DTYPES:
        raise ValueError(f"edge_dtype must be one of {EDGE_DTYPES}, got {edge_dtype!r}")
    if edge_dtype != "float32" and not isinstance(model, Dynamics):
        raise ValueError(f"edge_dtype={edge_dtype!r} needs the graph network (Dynamics), got {type(model).__name__}")
    pair_table = isinstance(model, Dynamics) and not model.config.edges_in_push_frame
    graphdef, state = nnx.split(model)
    return lambda radius: Partial(_Learned(edge_dtype, pair_table), graphdef, state, resolution_code(radius))


def sweep_dynamics(plate_half_width: float):
    """radius -> planner dynamics of the sweep heuristic alone (the resolution is irrelevant to it)."""
    return lambda radius: Partial(_sweep, jnp.float32(plate_half_width))


def load_dynamics(choice: str, ckpt_dir: str, plate_half_width: float, edge_dtype: str = "float32"):
    """The planner's model. choice: "learned" (the checkpoint in ``ckpt_dir``), "sweep" (the heuristic), or "auto"
    (the checkpoint when there is one); edge_dtype: a learned model's (``learned_dynamics``; the sweep has no
    network). Returns (radius -> dynamics, n_max the model was trained for, a name)."""
    from dynres_jax import ckpt
    from dynres_jax.train import build_model

    if choice not in ("auto", "learned", "sweep"):
        raise ValueError(f"dynamics must be 'auto', 'learned' or 'sweep', got {choice!r}")
    if choice == "learned" or (choice == "auto" and ckpt.latest_step(ckpt_dir) is not None):
        model, meta, _ = ckpt.load_module(ckpt_dir, build_model)
        dynamics = learned_dynamics(model, edge_dtype)
        edges = "" if jnp.dtype(edge_dtype) == jnp.float32 else f", {jnp.dtype(edge_dtype).name} edges"
        return dynamics, meta["train"]["n_max"], f"learned ({ckpt_dir}, step {meta.get('step')}{edges})"
    return sweep_dynamics(plate_half_width), 100, "sweep heuristic"


def _cost(camera, goal, positions, mask):
    return objective(positions, mask, goal, camera)


@functools.cache
def _camera_cost(camera):
    """One function object per camera: the planner's compile cache keys a cost by its function's identity."""
    return functools.partial(_cost, camera)


def goal_cost(goal: Goal, camera) -> Partial:
    """The planner's cost: the task objective c of predicted particles against ``goal`` (a pytree argument, so a new
    goal for the same camera reuses the compiled plan)."""
    return Partial(_camera_cost(camera), goal)


def overlay(rgb: np.ndarray, goal_mask: np.ndarray, particles: np.ndarray | None, camera, scale: int = 3,
            label: str = ""):
    """An RGB frame [H, W, 3] uint8 with the goal tinted green, particles [n, 3] (world, m) as red dots and an
    optional text label in the top-left corner."""
    img = rgb.astype(np.float32)
    img[goal_mask] = 0.6 * img[goal_mask] + 0.4 * np.array([60.0, 200.0, 60.0])
    img = cv2.resize(img.astype(np.uint8), (rgb.shape[1] * scale, rgb.shape[0] * scale),
                     interpolation=cv2.INTER_NEAREST)
    if particles is not None and len(particles):
        uv, _ = camera.world_to_pixel(np.asarray(particles, np.float64))
        for u, v in np.asarray(uv) * scale:
            cv2.circle(img, (int(u), int(v)), max(2, scale), (220, 30, 30), -1)
    if label:
        cv2.putText(img, label.replace("ω", "w"), (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (20, 20, 20), 1, cv2.LINE_AA)
    return img


def decide(obs, goal: Goal, key, init, dynamics, cfg: MPCConfig, camera, omega=None):
    """One MPC decision: particles from ``obs`` (h at ω), c of them, and the plan. Pure, so it vmaps over episodes.
    omega: this step's ω (default cfg.omega; may be traced). With ``cfg.planner.max_particle_steps`` the plan gets
    budget // ω Adam steps (``budget_steps``), so a higher resolution plans with fewer steps (paper Sec. IV-C).
    Returns (Particles, c [], PlanResult)."""
    k_h, k_plan = jax.random.split(key)
    omega = cfg.omega if omega is None else omega
    particles = sample_particles(obs, camera, omega, k_h, cfg.n_max, max_points=cfg.max_points)
    c_now = objective(particles.positions, particles.mask, goal, camera)
    budget, steps, active = cfg.planner.max_particle_steps, cfg.planner.steps, None
    if budget is not None and isinstance(omega, int):  # a concrete ω: scan only the affordable steps
        steps = steps_for_budget(omega, budget, steps)
    elif budget is not None:  # a traced ω (vmapped episodes): one scan, steps past the budget are no-ops
        active = budget_steps(omega, budget, steps)
    result = plan(dynamics(particles.radius), goal_cost(goal, camera), particles.positions, particles.mask, k_plan,
                  replace(cfg.planner, max_particle_steps=None), init=init, steps=steps, active_steps=active)
    return particles, c_now, result


def _shift(best):
    """The plan of the next step: the remaining pushes, the last one repeated (warm start)."""
    return jnp.concatenate([best[..., 1:, :], best[..., -1:, :]], axis=-2)


def run_episode(env: PileEnv, state: State, goal: Goal, goal_mask: np.ndarray, dynamics, cfg: MPCConfig, key,
                log=print, choose_omega=None) -> tuple[State, list[dict], list[np.ndarray]]:
    """One episode from ``state`` towards ``goal``. dynamics: ``learned_dynamics(model)`` or ``sweep_dynamics(hw)``.
    choose_omega: optional batched ``(obs [B], goals [B]) -> ω [B]`` (``resolution.load_chooser``) picking ω every
    step; default cfg.omega. Returns the final state, one record per step, and GIF frames (observation, goal,
    particles and ω)."""
    camera = env.camera
    records, frames, init = [], [], None
    batch = lambda tree: jax.tree.map(lambda x: jnp.asarray(x)[None], tree)  # noqa: E731
    for t in range(cfg.steps):
        t0 = time.perf_counter()
        omega = cfg.omega if choose_omega is None else int(choose_omega(batch(state.obs), batch(goal))[0])
        particles, c_now, result = decide(state.obs, goal, jax.random.fold_in(key, t), init, dynamics, cfg, camera,
                                          omega)
        action = np.asarray(jax.block_until_ready(result.best[0]))
        planning = time.perf_counter() - t0
        frames.append(overlay(np.asarray(state.obs.rgb), goal_mask, np.asarray(particles.positions)[
            np.asarray(particles.mask)], camera, label=f"step {t + 1}  ω = {omega}"))
        state = env.push(state, action)
        init = _shift(result.best)
        record = dict(step=t, omega=omega, objective=float(c_now), predicted_objective=float(result.best_cost),
                      distance=float(distribution_distance(state.obs, goal, camera)),
                      success=float(inside_share(state.pos, jnp.ones(env.scene.n_pieces, bool), goal, camera)),
                      planning_s=planning, action=action.tolist(), broken=bool(state.broken))
        records.append(record)
        log(f"step {t + 1:2d}/{cfg.steps}  ω={omega:3d}  c={record['objective']:7.2f} -> predicted "
            f"{record['predicted_objective']:7.2f}  d={record['distance']:7.2f}  inside={record['success']:5.1%}  "
            f"plan {planning:5.2f}s")
        if record["broken"]:
            log("the simulated world broke (NaN or a piece out of the bin); stopping the episode")
            break
    frames.append(overlay(np.asarray(state.obs.rgb), goal_mask, None, camera))
    return state, records, frames


def run_episodes(env, states: State, goals: Goal, dynamics, cfg: MPCConfig, keys, choose_omega=None,
                 log=print) -> tuple[State, list[dict]]:
    """Many episodes at once: states and goals batched on a leading axis [B], keys [B]. Each MPC step is one
    compiled call over all episodes (perception, planning, objective) and one batched push: ``env`` is a PileEnv
    with backend "mjx" (pushes vmapped on the device) or a ``WorldPool`` (pushes in C worker processes).
    choose_omega: optional ``(obs [B], goals [B]) -> ω [B]`` called every step (adaptive resolution); default
    cfg.omega everywhere. Returns the final states and one record per step whose values are arrays [B] (ω, c,
    predicted c, d, inside share, broken)."""
    from dynres_jax.sim.pool import WorldPool

    if isinstance(env, WorldPool):
        push = env.push
    elif env.backend == "mjx":
        push = jax.jit(jax.vmap(env.push))
    else:
        raise ValueError("run_episodes needs a PileEnv with backend='mjx' or a WorldPool; loop run_episode otherwise")
    camera = env.camera
    n = env.scene.n_pieces

    def step(obs, goal, key, init, omega):
        return decide(obs, goal, key, init, dynamics, cfg, camera, omega)

    def measure(obs, pos, goal):
        return distribution_distance(obs, goal, camera), inside_share(pos, jnp.ones(n, bool), goal, camera)

    first, later = jax.jit(jax.vmap(lambda o, g, k, w: step(o, g, k, None, w))), jax.jit(jax.vmap(step))
    measure = jax.jit(jax.vmap(measure))
    records, init = [], None
    for t in range(cfg.steps):
        t0 = time.perf_counter()
        step_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, t)
        omega = (jnp.full(len(keys), cfg.omega, jnp.int32) if choose_omega is None
                 else jnp.asarray(choose_omega(states.obs, goals), jnp.int32))
        if init is None:
            _, c_now, result = first(states.obs, goals, step_keys, omega)
        else:
            _, c_now, result = later(states.obs, goals, step_keys, init, omega)
        states = push(states, result.best[:, 0])
        init = _shift(result.best)
        distance, success = measure(states.obs, states.pos, goals)
        record = {k: np.asarray(v) for k, v in dict(omega=omega, objective=c_now, predicted_objective=result.best_cost,
                                                     distance=distance, success=success, broken=states.broken).items()}
        records.append(dict(step=t, seconds=time.perf_counter() - t0, **record))
        log(f"step {t + 1:2d}/{cfg.steps}  {len(keys)} episodes  mean ω={record['omega'].mean():5.1f}  mean d="
            f"{record['distance'].mean():7.2f}  mean inside={record['success'].mean():5.1%}  "
            f"{records[-1]['seconds']:5.2f}s")
    return states, records
