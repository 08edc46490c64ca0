"""Closed loop (model-predictive control) at a fixed resolution ω: observe -> h(y, ω) -> plan -> push, repeated.

Each step samples ω particles from the current observation into the smallest resolution bucket that holds ω
(``budget.bucket_for``), gives the planner the Adam steps its budget affords at that bucket (``budget.plan_steps``:
a plain count, or a time budget in seconds through a ``budget.TimingTable``), plans pushes on the task objective c
of the particles the dynamics model predicts (``planner.plan``), executes the first push of the best sequence in the
simulator, and records: ω, the bucket, the Adam steps run, c of the particles before planning, the c the planner
predicted, the distribution distance d and the share of pieces inside the goal after the push, and the planning
time. The previous plan, shifted, warm-starts the next. Dynamics: a trained ``Dynamics`` model (``learned_dynamics``)
or the sweep heuristic (``sweep_dynamics``).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import Partial

from dynres_jax.control import budget
from dynres_jax.control.objective import (
    SAMPLES_PER_PARTICLE,
    Goal,
    KindGoals,
    distribution_distance,
    inside_share,
    kind_costs,
    kind_objective,
    objective,
)
from dynres_jax.control.planner import PlannerConfig, plan, sample_pushes
from dynres_jax.perception import calibrate, check_particles, particle_kinds, point_cloud, sample_particles

if TYPE_CHECKING:  # annotations only: the planning half of this module needs no simulator (nor MuJoCo)
    from dynres_jax.sim.env import PileEnv, State
    from dynres_jax.sim.sensor import DepthSensor


@dataclass(frozen=True)
class MPCConfig:
    """steps: MPC steps per episode (reference 20); omega: particles (fixed resolution); buckets: the particle
    capacities ω is padded to (``budget``); max_points: perception's point cap; planner: the shooting optimiser's
    settings (its steps: the Adam steps of a decision without a time budget, and the most with one); time_budget:
    seconds per decision on the planning device (None: planner.steps every decision); real_depth: perception treats the
    depth as a real camera's (``perception.foreground``: a median filter, the table plane fitted; ``sim.sensor``)."""

    steps: int = 20
    omega: int = 50
    buckets: tuple[int, ...] = budget.BUCKETS
    max_points: int | None = 4096
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    time_budget: float | None = None
    real_depth: bool = False

    def __post_init__(self):
        object.__setattr__(self, "buckets", budget.check_buckets(self.buckets))
        if not 1 <= self.omega <= self.buckets[-1]:
            raise ValueError(f"omega={self.omega} must lie in [1, {self.buckets[-1]}] (the largest bucket)")
        if self.steps < 1:
            raise ValueError(f"steps must be positive, got {self.steps}")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError(f"time_budget must be a positive number of seconds or None, got {self.time_budget}")

    def plan_steps(self, bucket: int, table: budget.TimingTable | None = None) -> int:
        """The Adam steps of a decision at ``bucket`` (``budget.plan_steps`` with this config's budget). ValueError
        when the table was measured for another planner batch (samples, horizon)."""
        if self.time_budget is not None and table is not None and (table.samples, table.horizon) != (
                self.planner.samples, self.planner.horizon):
            raise ValueError(f"the timing table was measured for {table.samples} samples x horizon {table.horizon}, "
                             f"the planner has {self.planner.samples} x {self.planner.horizon}: measure it again")
        return budget.plan_steps(bucket, self.planner.steps, self.time_budget, table)

    def allot(self, omegas, table: budget.TimingTable | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per decision of a batch at omegas [B]: its bucket [B] and the Adam steps [B] it runs (``plan_steps``)."""
        buckets = np.array([budget.bucket_for(int(w), self.buckets) for w in np.asarray(omegas)])
        return buckets, np.array([self.plan_steps(int(b), table) for b in buckets], np.int32)


def _cost(camera, goal, positions, mask):
    return objective(positions, mask, goal, camera)


def _kind_cost(camera, goals, kinds, baseline, positions, mask):
    return kind_objective(positions, mask, kinds, goals, camera, baseline)


@functools.cache
def _camera_cost(camera, per_kind: bool):
    """One function object per camera: the planner's compile cache keys a cost by its function's identity."""
    return functools.partial(_kind_cost if per_kind else _cost, camera)


def goal_cost(goal: Goal | KindGoals, camera, bucket: int | None = None, kinds=None, baseline=None) -> Partial:
    """The planner's cost: the task objective c of predicted particles against ``goal`` (a pytree argument, so a new
    goal for the same camera reuses the compiled plan); for KindGoals, Sort's objective (``kind_objective``) with the
    particles' kinds [N] and each kind's c now, baseline [K]. bucket: the particle capacity; the goal's samples are
    cut to the SAMPLES_PER_PARTICLE × bucket that c can use at ω <= bucket (the same c, on fewer samples)."""
    per_kind = isinstance(goal, KindGoals)
    if per_kind != (kinds is not None) or per_kind != (baseline is not None):
        raise ValueError("particle kinds and a baseline go with KindGoals (Sort's per-kind goals), and only with them")
    if bucket is not None:
        cut = SAMPLES_PER_PARTICLE * bucket
        def fewer(g: Goal) -> Goal:
            return g._replace(samples=g.samples[..., :cut, :], sample_mask=g.sample_mask[..., :cut])

        goal = goal._replace(goals=fewer(goal.goals)) if per_kind else fewer(goal)
    if per_kind:
        return Partial(_camera_cost(camera, True), goal, kinds, baseline)
    return Partial(_camera_cost(camera, False), goal)


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


def decide(obs, goal: Goal, key, init, dynamics, cfg: MPCConfig, camera, omega=None, *, bucket=None, steps=None,
           warm=True, kind=None):
    """One MPC decision: particles from ``obs`` (h at ω in ``bucket`` slots), c of them, and the plan. Pure, so it
    vmaps over episodes. init [T, 4]: the warm start (the previous plan, shifted), used where ``warm`` (may be
    traced), or None; omega: this step's ω (default cfg.omega; may be traced); bucket: static particle slots
    (default the smallest of cfg.buckets holding a concrete ω; with a traced ω, a bucket holding every ω);
    steps: Adam steps (may be traced; default cfg.planner.steps). The planner's starting pushes pass through random
    points of the perception cloud, not of the particles, so one key gives the same pushes at every ω (common random
    numbers). kind: perceive only the pieces of this kind index (may be traced; None: every piece). goal: a Goal, or
    KindGoals (Sort: every piece perceived, each particle labelled with its kind, ``perception.particle_kinds``, and
    c of ``kind_objective`` with each kind's c now as the held kinds' baseline). Returns (Particles, c [],
    PlanResult)."""
    k_h, k_plan = jax.random.split(key)
    omega = cfg.omega if omega is None else omega
    if bucket is None:
        if isinstance(omega, jax.core.Tracer):
            raise ValueError("decide with a traced omega needs its bucket (a static capacity holding every ω)")
        bucket = budget.bucket_for(int(omega), cfg.buckets)
    particles = sample_particles(obs, camera, omega, k_h, bucket, max_points=cfg.max_points, real_depth=cfg.real_depth,
                                 kind=kind)
    if isinstance(goal, KindGoals):
        if kind is not None:
            raise ValueError("KindGoals score every kind's particles: decide perceives every piece (kind=None)")
        kinds = particle_kinds(obs, camera, particles, cfg.real_depth)
        baseline = kind_costs(particles.positions, particles.mask, kinds, goal, camera)
        c_now = kind_objective(particles.positions, particles.mask, kinds, goal, camera, baseline)
    else:
        kinds = baseline = None
        c_now = objective(particles.positions, particles.mask, goal, camera)
    initial = sample_pushes(k_plan, *point_cloud(obs, camera, max_points=cfg.max_points, real_depth=cfg.real_depth,
                                                 kind=kind), cfg.planner)
    init = initial[0] if init is None else jnp.where(warm, init, initial[0])  # no warm start: sample 0 stands in
    cost = goal_cost(goal, camera, bucket, kinds, baseline)
    result = plan(dynamics(particles.radius), cost, particles.positions, particles.mask, k_plan, cfg.planner, init=init,
                  steps=steps, initial=initial)
    return particles, c_now, result


@functools.partial(jax.jit, static_argnames=("dynamics", "cfg", "camera", "bucket"))
def _decide_batch(obs, goal, key, init, warm, omega, steps, kinds, *, dynamics, cfg, camera, bucket):
    def one(obs, goal, key, init, omega, steps, kind):
        return decide(obs, goal, key, init, dynamics, cfg, camera, omega, bucket=bucket, steps=steps, warm=warm,
                      kind=kind)

    return per_episode(one)(obs, goal, key, init, omega, steps, kinds)


def decide_batch(obs, goal: Goal, key, init, warm, omega, steps, dynamics, cfg: MPCConfig, camera, bucket: int,
                 kinds=None):
    """``decide`` over a batch of episodes (every argument but warm with a leading axis [B]) as one compiled function
    per bucket (and model, camera and planner): what the closed loop runs and its timing table measures. init
    [B, T, 4] (ignored unless warm); warm, omega [B], steps [B] and kinds [B] (``decide``'s kind; None: every
    piece) are traced. The particles are checked: bad
    perception input raises a ValueError naming it (``perception.check_particles``)."""
    key_cfg = replace(cfg, steps=1, omega=1, time_budget=None)  # fields a decision does not read: one compile
    omega = np.asarray(omega, np.int32)
    particles, c_now, result = _decide_batch(obs, goal, key, jnp.asarray(init, jnp.float32), jnp.asarray(warm),
                                             jnp.asarray(omega), jnp.asarray(steps, jnp.int32),
                                             None if kinds is None else jnp.asarray(kinds, jnp.int32),
                                             dynamics=dynamics, cfg=key_cfg, camera=camera, bucket=bucket)
    check_particles(particles, omega, bucket, "perception failed in episodes")
    return particles, c_now, result


def measure_timing(obs, goal: Goal, dynamics, cfg: MPCConfig, camera, repeats: int = 3) -> budget.TimingTable:
    """A timing table of this device for decisions like ``cfg``'s on ``obs`` and ``goal`` (one decision per call, the
    planner's batch), for every bucket of cfg.buckets, each at its largest ω that ``obs`` has the points for
    (``budget.measure``)."""
    key = jax.random.PRNGKey(0)
    if cfg.planner.steps < 1:
        raise ValueError("measuring a timing table needs PlannerConfig.steps >= 1")

    points = int(np.sum(np.asarray(point_cloud(obs, camera, max_points=cfg.max_points)[1])))

    init = jnp.zeros((cfg.planner.horizon, 4), jnp.float32)

    def run(bucket, steps):  # as ``run_episodes`` decides one episode: the first push of the best sequence
        omega = min(bucket, points)  # a bucket's work does not depend on how many of its slots are valid
        result = decide_batch(batch(obs), batch(goal), batch(jax.random.fold_in(key, 0)), batch(init), True,
                              [omega], [steps], dynamics, cfg, camera, bucket)[2]
        return result.best[0, 0]

    return budget.measure(run, cfg.buckets, samples=cfg.planner.samples, horizon=cfg.planner.horizon,
                          max_steps=cfg.planner.steps, repeats=repeats)


class StepTarget(NamedTuple):
    """A policy's orders for one MPC step of ``run_episodes(policy=)``, arrays with a leading axis [B]: goals (a
    batched Goal: this step's goal of each decision; the step's d and inside share are scored against it), omega
    [B], kinds [B] int (the piece kind each decision perceives; None: every piece), record (extra record fields,
    arrays [B]), draw (optional ``(rgb [H, W, 3], particles [n, 3] or None) -> frame`` of episode 0)."""

    goals: Goal
    omega: np.ndarray
    kinds: np.ndarray | None = None
    record: dict = {}
    draw: object = None


def per_episode(fn):
    """``jax.vmap(fn)``, except that a batch of one calls fn on its one episode: XLA may round a vmapped reduction
    differently, and a batch of one should decide bit for bit as the episode alone."""
    def batched(*args):
        if len(jax.tree.leaves(args)[0]) == 1:
            return batch(fn(*episode(args)))
        return jax.vmap(fn)(*args)

    return batched


def batch(tree):
    """A pytree of one episode as a batch of one: a leading axis [1] on every leaf."""
    return jax.tree.map(lambda x: jnp.asarray(x)[None], tree)


def episode(tree, b: int = 0):
    """Episode b of a batched pytree: leaf [b] of every leaf (the inverse of ``batch`` for b = 0)."""
    return jax.tree.map(lambda x: x[b], tree)


def _shift(best):
    """The plan of the next step: the remaining pushes, the last one repeated (warm start)."""
    return jnp.concatenate([best[..., 1:, :], best[..., -1:, :]], axis=-2)


def run_episode(env: PileEnv, state: State, goal: Goal | None, goal_mask: np.ndarray | None, dynamics, cfg: MPCConfig,
                key, log=print, choose_omega=None, timing: budget.TimingTable | None = None, policy=None
                ) -> tuple[State, list[dict], list[np.ndarray]]:
    """One episode: ``run_episodes`` on a batch of one, its records unbatched to Python numbers and GIF frames drawn
    with ``goal_mask`` [H, W] (or by the policy; goal and goal_mask are then None). Returns the final state, one
    record per step and the frames."""
    final, records, frames = run_episodes(env, batch(state), batch(goal), dynamics, cfg, batch(key), log=log,
                                          choose_omega=choose_omega, timing=timing, policy=policy,
                                          goal_masks=None if goal_mask is None else goal_mask[None])
    return episode(final), [episode_record(r, 0) for r in records], frames


def episode_record(record: dict, b: int) -> dict:
    """Episode b's share of a ``run_episodes`` record, as Python numbers (JSON-ready)."""
    return {k: (v if k in ("step", "seconds") else np.asarray(v)[b].tolist()) for k, v in record.items()}


def _select(trees: list, pick) -> object:
    """Per episode b, leaf [b] of trees[pick[b]]: trees K pytrees of arrays with a leading [B] axis, pick [B] ints."""
    rows = jnp.arange(len(pick))
    return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x])[jnp.asarray(pick), rows], *trees)


def run_episodes(env, states: State, goals: Goal, dynamics, cfg: MPCConfig, keys, choose_omega=None,
                 log=print, timing: budget.TimingTable | None = None, oracle: tuple[int, ...] | None = None,
                 goal_masks: np.ndarray | None = None, sensor: DepthSensor | None = None, policy=None
                 ) -> tuple[State, list[dict]] | tuple[State, list[dict], list]:
    """The closed loop, for one episode or many at once: states and goals batched on a leading axis [B], keys [B].
    Each MPC step is one compiled decision over all episodes (perception, planning, objective: ``decide_batch``) and
    one batched push: ``env`` is a PileEnv (backend "mjx": pushes vmapped on the device; "mujoco": one world after
    another), a ``WorldPool`` (pushes in C worker processes) or an ``MJXPool``. dynamics:
    ``registry.learned_dynamics(model)`` or ``registry.sweep_dynamics(hw)``. choose_omega: optional
    ``(obs [B], goals [B]) -> ω [B]`` called every step (adaptive resolution, ``resolution.load_chooser``); default
    cfg.omega everywhere. oracle: candidate ω values instead: every step plans at each (same keys), pushes each on a
    copy of the worlds and keeps, per episode, the one whose push left the lowest d (a greedy upper bound of any
    chooser of ω).

    Each episode's decision runs the Adam steps its own bucket affords (``cfg.plan_steps``); the call runs at the
    largest bucket of the batch, which pads inertly. Under a time budget the steps come from ``timing``
    (``measure_timing``), which one episode (B = 1) refines from every decision's wall time unless it is frozen (one
    decision of a larger batch cannot be timed alone). A record per step holds arrays [B]:
    ω, bucket, plan_steps, planning_s (B = 1: the decision's wall time, perception included; else the table's price
    of it, NaN without a budget), c before, predicted c, d and inside share after the push, the push, broken; and
    the step's wall time ``seconds``. The loop stops early when every world broke. goal_masks [B, H, W]: also
    return GIF frames of episode 0 (goal, particles). sensor: a real camera's errors (``sim.sensor.DepthSensor``):
    every decision (and choose_omega) sees its noisy depth, through the camera it believes in (``believed_camera``),
    refined from episode 0's first frame as a robot checks its calibration (``perception.calibrate``); d and the
    inside share are measured on the true state. policy: a task's policy on top of
    the loop (Sort's A* waypoints, ``sort.SortPolicy``): ``policy(t, obs [B]) -> StepTarget`` sets every step's goals,
    ω and perceived kind (goals may then be None), and ``policy.score(states) -> {name: [B, ...]}`` adds the task's
    own scores to each record. Returns the final states and the records (and the frames)."""
    from dynres_jax.sim.pool import MJXPool, WorldPool

    if oracle is not None and (choose_omega is not None or not oracle):
        raise ValueError("oracle takes a non-empty tuple of candidate ω, and no choose_omega beside it")
    if policy is not None and (oracle is not None or choose_omega is not None):
        raise ValueError("a policy sets each step's ω itself: no oracle or choose_omega beside it")
    if cfg.time_budget is not None and timing is None:
        raise ValueError("run_episodes under a time budget needs a timing table (mpc.measure_timing, --timing FILE)")
    episodes, camera = len(keys), env.camera
    seen_camera = camera if sensor is None else sensor.believed_camera(camera)
    sense = jax.jit(jax.vmap(sensor.observe)) if sensor is not None else None
    if isinstance(env, WorldPool | MJXPool):
        push = env.push
    elif env.backend == "mjx":
        push = jax.jit(jax.vmap(env.push))
    else:
        def push(states, actions):  # C MuJoCo: one world after another
            worlds = [env.push(episode(states, b), np.asarray(actions[b])) for b in range(episodes)]
            return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *worlds)
    measure = jax.jit(per_episode(functools.partial(_measure, camera, jnp.asarray(env.scene.kind))))
    records, frames, warm = [], [], False
    init = jnp.zeros((episodes, cfg.planner.horizon, 4), jnp.float32)  # no warm start at the first step
    for t in range(cfg.steps):
        t0 = time.perf_counter()
        step_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, t)
        seen = states.obs if sensor is None else sense(states.obs, jax.vmap(jax.random.fold_in, in_axes=(0, None))(
            step_keys, 1))
        if sensor is not None and t == 0:
            seen_camera = _calibrated(env, episode(seen), seen_camera, log)
        target = None if policy is None else policy(t, seen)
        step_goals = goals if target is None else target.goals
        kinds = None if target is None else target.kinds
        if target is not None:
            candidates = [np.asarray(target.omega, np.int32)]
        elif oracle is not None:
            candidates = [np.full(episodes, w, np.int32) for w in oracle]
        elif choose_omega is not None:
            candidates = [np.asarray(choose_omega(seen, goals), np.int32)]
        else:
            candidates = [np.full(episodes, cfg.omega, np.int32)]
        outcomes, drawn = [], []  # drawn: episode 0's particles of each candidate, for its frame
        for omega in candidates:
            buckets, steps = cfg.allot(omega, timing)
            bucket = int(buckets.max())
            t_plan = time.perf_counter()
            particles, c_now, result = decide_batch(seen, step_goals, step_keys, init, warm, omega, steps, dynamics,
                                                    cfg, seen_camera, bucket, kinds)
            action = np.asarray(jax.block_until_ready(result.best[:, 0]))
            wall = time.perf_counter() - t_plan
            after = push(states, action)
            distance, success = measure(after.obs, after.pos, step_goals)
            outcomes.append(dict(omega=omega, bucket=buckets, plan_steps=steps, objective=c_now,
                                 predicted_objective=result.best_cost, best=result.best, states=after,
                                 distance=distance, success=success, action=action, wall=np.full(episodes, wall)))
            drawn.append(np.asarray(particles.positions[0])[np.asarray(particles.mask[0])])
        pick = np.argmin(np.stack([np.asarray(o["distance"]) for o in outcomes]), axis=0)  # [B]: the kept candidate
        kept = _select(outcomes, pick)
        if episodes == 1:
            planning = np.asarray(kept["wall"])
            if timing is not None:
                timing.refine(int(kept["bucket"][0]), int(kept["plan_steps"][0]), float(planning[0]))
        elif timing is not None:
            planning = np.array([timing.seconds(int(b), int(s)) for b, s in zip(kept["bucket"], kept["plan_steps"],
                                                                                strict=True)])
        else:
            planning = np.full(episodes, np.nan)
        if target is not None and target.draw is not None:
            frames.append(target.draw(np.asarray(states.obs.rgb[0]), drawn[pick[0]]))
        elif goal_masks is not None:
            frames.append(overlay(np.asarray(states.obs.rgb[0]), goal_masks[0], drawn[pick[0]], camera,
                                  label=f"step {t + 1}  ω = {int(kept['omega'][0])}"))
        states, init, warm = kept["states"], _shift(kept["best"]), True
        record = {k: np.asarray(kept[k]) for k in ("omega", "bucket", "plan_steps", "objective", "predicted_objective",
                                                   "distance", "success", "action")}
        record.update(planning_s=planning, broken=np.asarray(states.broken))
        if target is not None:
            record.update({k: np.asarray(v) for k, v in target.record.items()},
                          **{k: np.asarray(v) for k, v in policy.score(states).items()})
        records.append(dict(step=t, seconds=time.perf_counter() - t0, **record))
        _log_step(log, records[-1], cfg.steps)
        if record["broken"].all():
            log("every simulated world broke (NaN or a piece out of the bin); stopping")
            break
    if target is not None and target.draw is not None:
        frames.append(target.draw(np.asarray(states.obs.rgb[0]), None))
        return states, records, frames
    if goal_masks is None:
        return states, records
    frames.append(overlay(np.asarray(states.obs.rgb[0]), goal_masks[0], None, camera))
    return states, records, frames


def _calibrated(env, obs, camera, log):
    """``perception.calibrate`` on one frame of the env's bin, logged: how far it moved and turned the camera."""
    scene = env.config.scene
    refined = calibrate(obs, camera, bin_half_width=scene.bin_half_width, wall_height=scene.wall_height)
    turn = np.degrees(np.arccos(np.clip((np.trace(refined.rotation @ camera.rotation.T) - 1) / 2, -1.0, 1.0)))
    log(f"camera pose refined from the first frame: moved {1000 * np.linalg.norm(refined.centre - camera.centre):.1f} "
        f"mm, turned {turn:.2f}°")
    return refined


def _measure(camera, piece_kinds, obs, pos, goal):
    """A step's scores on the true state: d of the foreground and the share of pieces inside the goal; for KindGoals,
    the mean over kinds of d of that kind's foreground to its goal, and the share of pieces inside their own kind's
    goal."""
    if not isinstance(goal, KindGoals):
        return distribution_distance(obs, goal, camera), inside_share(pos, jnp.ones(len(piece_kinds), bool), goal,
                                                                     camera)

    def one(g, k):
        mine = piece_kinds == k
        return distribution_distance(obs, g, camera, kind=k), inside_share(pos, mine, g, camera) * jnp.sum(mine)

    distance, inside = jax.vmap(one)(goal.goals, jnp.arange(goal.hold.shape[0]))
    return jnp.mean(distance), jnp.sum(inside) / len(piece_kinds)


def _log_step(log, r: dict, steps: int) -> None:
    """One line per MPC step: the episode's values, or the means of a batch."""
    if len(r["omega"]) == 1:
        log(f"step {r['step'] + 1:2d}/{steps}  ω={int(r['omega'][0]):3d} (bucket {int(r['bucket'][0]):3d}, "
            f"{int(r['plan_steps'][0]):3d} Adam steps)  c={float(r['objective'][0]):7.2f} -> predicted "
            f"{float(r['predicted_objective'][0]):7.2f}  d={float(r['distance'][0]):7.2f}  "
            f"inside={float(r['success'][0]):5.1%}  plan {float(r['planning_s'][0]):5.2f}s")
    else:
        log(f"step {r['step'] + 1:2d}/{steps}  {len(r['omega'])} episodes  mean ω={r['omega'].mean():5.1f}  mean "
            f"Adam steps={r['plan_steps'].mean():5.1f}  mean d={r['distance'].mean():7.2f}  "
            f"mean inside={r['success'].mean():5.1%}  {r['seconds']:5.2f}s")
