"""Closed loop (model-predictive control): observe -> h(y, ω) -> plan -> push, repeated, for many episodes at once.

Worlds (``sim.pool.Worlds``) push a batch of simulated piles. A chooser (``choosers``; ``sort.SortPolicy``) orders at
each MPC step the goals, candidate plans and piece kinds, and how to keep one. The decision (``decision.decide_batch``)
perceives every frame once and plans, compiled once per resolution bucket. ``run`` joins them: each decision gets the
Adam steps its ω affords (``MPCConfig.allot``: a count, or a time budget through a ``budget.TimingTable``), the kept
plan's first push is executed, the step scored on the true state and the next warm-started with the plan shifted. A
real camera's view is a ``SensorView``; GIF frames and other per-step work are ``on_step`` callbacks.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import check_fields
from dynres_jax.control import budget
from dynres_jax.control.choosers import Candidate, Chooser
from dynres_jax.control.decision import DecisionSpec, batch, decide_batch, episode, per_episode
from dynres_jax.control.goals import Goal, KindGoals
from dynres_jax.control.objective import distribution_distance, inside_share
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.errors import InputError
from dynres_jax.perception import calibrate, visible_points
from dynres_jax.sim.env import PileEnv, State
from dynres_jax.sim.pool import EnvWorlds, Worlds
from dynres_jax.sim.sensor import DepthSensor

PLAN_DRAWS = 1 << 20  # plan draw d > 0 folds PLAN_DRAWS + d into a step's keys (away from the sensor's fold 1)
SIMULATED_WORLDS = 512  # worlds per push call when the simulator scores proposals (``keep_lowest_distance``)


@dataclass(frozen=True)
class MPCConfig:
    """mpc_steps: MPC steps per episode (reference 20); buckets: the particle capacities ω is padded to (``budget``);
    max_points: perception's point cap; planner: the shooting optimiser's settings (its steps: the Adam steps of a
    decision without a time budget, and the most with one); time_budget: seconds per decision on the planning device
    (None: planner.adam_steps every decision); real_depth: perception treats the depth as a real camera's
    (``sim.sensor``); warm_start: each plan starts from the last, shifted (False: fresh samples, as the reference)."""

    mpc_steps: int = 20
    buckets: tuple[int, ...] = budget.BUCKETS
    max_points: int | None = 4096
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    time_budget: float | None = None
    real_depth: bool = False
    warm_start: bool = True

    def __post_init__(self):
        check_fields(self)
        object.__setattr__(self, "buckets", budget.check_buckets(self.buckets))
        if self.mpc_steps < 1:
            raise ValueError(f"mpc_steps must be positive, got {self.mpc_steps}")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError(f"time_budget must be a positive number of seconds or None, got {self.time_budget}")

    def spec(self, capacity: int) -> DecisionSpec:
        """The compiled decision's settings at particle capacity ``capacity``."""
        return DecisionSpec(capacity, self.planner, self.max_points, self.real_depth)

    def adam_steps(self, omega: int, table: budget.TimingTable | None = None, share: float = 1.0) -> int:
        """The Adam steps of a decision at ``omega``: ``budget.adam_steps`` with ``share`` of the budget, priced by
        ``table`` (by bucket, or by ω). ValueError when the table was measured for another planner batch."""
        if self.time_budget is not None and table is not None and (table.samples, table.horizon) != (
                self.planner.samples, self.planner.horizon):
            raise InputError(f"the timing table was measured for {table.samples} samples x horizon {table.horizon}, "
                             f"the planner has {self.planner.samples} x {self.planner.horizon}: measure it again")
        seconds = None if self.time_budget is None else self.time_budget * share
        key = budget.bucket_for(int(omega), self.buckets) if table is None else table.key(omega, self.buckets)
        return budget.adam_steps(key, self.planner.adam_steps, seconds, table)

    def allot(self, omegas, table: budget.TimingTable | None = None, share: float = 1.0
              ) -> tuple[np.ndarray, np.ndarray]:
        """Per decision of a batch at omegas [B]: its bucket [B] and the Adam steps [B] it runs (``adam_steps``, with
        ``share`` of the budget)."""
        buckets = np.array([budget.bucket_for(int(w), self.buckets) for w in np.asarray(omegas)])
        return buckets, np.array([self.adam_steps(int(w), table, share) for w in np.asarray(omegas)], np.int32)


def measure_timing(obs, goal: Goal, dynamics, cfg: MPCConfig, camera, repeats: int = 3,
                   log=print, omegas=None) -> budget.TimingTable:
    """A timing table of this device for decisions like ``cfg``'s on ``obs`` and ``goal`` (one decision per call),
    for the buckets of ``omegas`` (the fixed ω a run decides at; None: every bucket of cfg.buckets), each at its
    largest ω that ``obs`` has the points for (``budget.measure``; log: its progress lines)."""
    if cfg.planner.adam_steps < 1:
        raise ValueError("measuring a timing table needs PlannerConfig.adam_steps >= 1")
    points = visible_points(obs, camera, cfg.max_points)
    key, init = batch(jax.random.fold_in(jax.random.PRNGKey(0), 0)), jnp.zeros((1, cfg.planner.horizon, 4))

    def run(bucket, steps):  # as ``run`` decides one episode: the first push of the best sequence
        omega = min(bucket, points)  # a bucket's work does not depend on how many of its slots are valid
        result = decide_batch(batch(obs), batch(goal), key, init, True, [omega], [steps], spec=cfg.spec(bucket),
                              dynamics=dynamics, camera=camera)[2]
        return result.best[0, 0]

    buckets = cfg.buckets if omegas is None else sorted({budget.bucket_for(int(w), cfg.buckets) for w in omegas})
    return budget.measure(run, buckets, samples=cfg.planner.samples, horizon=cfg.planner.horizon,
                          max_steps=cfg.planner.adam_steps, repeats=repeats, log=log)


class ExactView:
    """The planner sees the simulator's frames through the true camera."""

    def __init__(self, camera):
        self.camera = camera

    def __call__(self, t: int, states: State, keys) -> tuple:
        return states.obs, self.camera


class SensorView:
    """The planner sees a real depth camera's frames (``sim.sensor.DepthSensor``: noise drawn from each step's keys)
    through the camera it believes in, refined from episode 0's first frame as a robot checks its calibration
    (``perception.calibrate``)."""

    def __init__(self, sensor: DepthSensor, env: PileEnv, log=print):
        self.sense = jax.jit(jax.vmap(sensor.observe))
        self.camera, self.scene, self.log = sensor.believed_camera(env.camera), env.config.scene, log

    def __call__(self, t: int, states: State, keys) -> tuple:
        seen = self.sense(states.obs, fold(keys, 1))
        if t == 0:
            refined = calibrate(episode(seen), self.camera, bin_half_width=self.scene.bin_half_width,
                                wall_height=self.scene.wall_height)
            turn = np.degrees(np.arccos(np.clip((np.trace(refined.rotation @ self.camera.rotation.T) - 1) / 2, -1, 1)))
            self.log(f"camera pose refined from the first frame: moved "
                     f"{1000 * np.linalg.norm(refined.centre - self.camera.centre):.1f} mm, turned {turn:.2f}°")
            self.camera = refined
        return seen, self.camera


class Situation(NamedTuple):
    """What every candidate decision of one MPC step starts from: states [B] (the true worlds), seen (the frames [B]
    the planner sees, through ``camera``), goals [B] and kinds [B] (or None) of the chooser's orders, keys [B], the
    warm start init [B, T, 4] and whether to use it (warm)."""

    states: State
    seen: object
    camera: object
    goals: object
    kinds: np.ndarray | None
    keys: jax.Array
    init: jax.Array
    warm: bool


def propose(now: Situation, candidate: Candidate, *, cfg: MPCConfig, timing: budget.TimingTable | None,
            dynamics) -> dict:
    """One candidate's decision (``choosers.Candidate``: its ω [B], plan draw and share of the budget) from ``now``,
    and what it puts forward. Returns arrays [B]: omega, bucket, adam_steps, objective (c before),
    predicted_objective (NaN for proposals the simulator scores), particles, proposals [B, K, T, 4] (the model's best
    plan, K = 1; the planner's M first samples, no Adam step; or its M candidates after the Adam steps and its best)
    and wall (the decision's seconds)."""
    now = _drawn(now, candidate.draw)
    buckets, steps = cfg.allot(candidate.omega, timing, candidate.share)
    if candidate.proposals == "samples":
        steps = np.zeros(len(buckets), np.int32)
    t0 = time.perf_counter()
    particles, c_now, result = decide_batch(now.seen, now.goals, now.keys, now.init, now.warm, candidate.omega, steps,
                                            now.kinds, spec=cfg.spec(int(buckets.max())), dynamics=dynamics,
                                            camera=now.camera)
    predicted = np.full(len(buckets), np.nan, np.float32)
    if candidate.proposals == "plan":
        proposals, predicted = result.best[:, None], result.best_cost
    elif candidate.proposals == "samples":
        proposals = result.actions
    else:  # the model's best (kept from any step) as candidate M + 1
        proposals = jnp.concatenate([result.actions, result.best[:, None]], axis=1)
    proposals = np.asarray(jax.block_until_ready(proposals))
    return dict(omega=np.asarray(candidate.omega), bucket=buckets, adam_steps=steps, objective=c_now,
                predicted_objective=predicted, particles=particles, proposals=proposals,
                wall=np.full(len(buckets), time.perf_counter() - t0))


def keep_lowest_distance(worlds: Worlds, now: Situation, plans: list[dict], score: Callable,
                         timing: budget.TimingTable | None = None) -> dict:
    """Keep rule "distance": every proposal of every plan (``propose``) pushed on a copy of the worlds (a plan's
    proposals SIMULATED_WORLDS // B to a call, so every core works; one proposal: the worlds themselves), per episode
    the one whose push left the lowest d kept, the first on ties. Returns the kept plan's arrays [B] with best (its
    action sequence), action (its first push), states (after) and ``score(states, goals)``'s."""
    b, kept = len(now.keys), None
    per_call = max(1, SIMULATED_WORLDS // b)
    for plan in plans:
        samples, common = plan["proposals"], {k: v for k, v in plan.items() if k != "proposals"}
        for first in range(0, samples.shape[1], per_call):
            k = min(per_call, samples.shape[1] - first)
            tile = (lambda x: x) if k == 1 else lambda x, k=k: jnp.concatenate([jnp.asarray(x)] * k)  # [k * B, ...]
            actions = samples[:, first:first + k, 0].transpose(1, 0, 2).reshape(k * b, 4)
            after = worlds.push(jax.tree.map(tile, now.states), actions)
            scores = score(after, jax.tree.map(tile, now.goals))
            for j in range(k):
                rows = (lambda x: x) if k == 1 else lambda x, j=j: x[j * b:(j + 1) * b]
                outcome = dict(common, best=jnp.asarray(samples[:, first + j]), action=samples[:, first + j, 0],
                               states=jax.tree.map(rows, after), **{key: rows(v) for key, v in scores.items()})
                kept = outcome if kept is None else _lowest_distance([kept, outcome])
    return kept


def keep_best_rate(worlds: Worlds, now: Situation, plans: list[dict], score: Callable,
                   timing: budget.TimingTable | None = None) -> dict:
    """Keep rule "rate": per episode the plan whose model predicts the largest fall of c per second of planning (the
    table's price of its bucket and steps; without a table, its wall time); only its push is executed, nothing is
    simulated. Returns ``keep_lowest_distance``'s arrays [B]."""
    return keep_lowest_distance(worlds, now, [best_rate(plans, timing)], score)


def best_rate(plans: list[dict], timing: budget.TimingTable | None) -> dict:
    """Per episode the plan (``propose``'s, proposing the model's best) whose model predicts the largest fall of c per
    second of planning; one plan is its own best."""
    if any(p["proposals"].shape[1] != 1 for p in plans):
        raise ValueError("keep rule 'rate' judges the model's plans: every candidate must propose its best plan")
    if len(plans) == 1:
        return plans[0]
    rates = np.stack([(np.asarray(p["objective"]) - np.asarray(p["predicted_objective"])) / _seconds(p, timing)
                      for p in plans])
    return _pick(plans, np.argmax(rates, axis=0))


KEEPS = {"distance": keep_lowest_distance, "rate": keep_best_rate}  # Orders.keep -> how the loop keeps a candidate


def act(worlds: Worlds, now: Situation, omega, *, cfg: MPCConfig, timing: budget.TimingTable | None, dynamics,
        score: Callable) -> dict:
    """The model's plan at omega [B] from ``now``, pushed in ``worlds``, scored (``keep_lowest_distance``'s [B])."""
    plan = propose(now, Candidate(omega), cfg=cfg, timing=timing, dynamics=dynamics)
    return keep_lowest_distance(worlds, now, [plan], score)


class Episodes(NamedTuple):
    """What ``run`` returns: the final states [B] and one record per MPC step (arrays [B]; ``run``)."""

    states: State
    records: list[dict]


def run(worlds: Worlds, states: State, chooser: Chooser, dynamics, cfg: MPCConfig, keys, *,
        timing: budget.TimingTable | None = None, view=None, on_step: Sequence[Callable] = (), log=print) -> Episodes:
    """The closed loop over a batch of episodes: states [B] in ``worlds``, keys [B]; every MPC step the chooser's
    orders (``choosers.Orders``), one compiled decision over all episodes per candidate (``propose``) and, per
    episode, the proposal the orders' keep rule keeps (``KEEPS``). dynamics: ``registry`` (radius -> the planner's
    model); timing: the table a time budget is spent by (required with cfg.time_budget; a batch of one refines it
    from its decisions' wall times unless frozen); view: what the planner sees (``ExactView``; ``SensorView``); on_step:
    callbacks ``(t, states before the push, kept Particles [B], record)`` (GIF frames: ``io.draw.Frames``); log: one
    line per step. Stops early when every world broke. A record holds arrays [B]: omega, bucket, adam_steps,
    planning_s (B = 1: the decision's wall time; else the table's price of it, NaN without a budget), objective (c
    before the push), predicted_objective, distance (d after the push) and inside (the share of pieces inside the
    goal, on the true state), action, broken, the chooser's record fields and scores; and step and seconds."""
    if cfg.time_budget is not None and timing is None:
        raise ValueError("a closed loop under a time budget needs a timing table (mpc.measure_timing, --timing FILE)")
    view = view or ExactView(worlds.camera)
    score = scorer(worlds.camera, tuple(np.asarray(worlds.scene.kind).tolist()))
    records, warm = [], False
    init = jnp.zeros((len(keys), cfg.planner.horizon, 4), jnp.float32)  # no warm start at the first step
    for t in range(cfg.mpc_steps):
        t0 = time.perf_counter()
        step_keys = fold(keys, t)
        seen, camera = view(t, states, step_keys)
        orders = chooser(t, seen)
        now = Situation(states, seen, camera, orders.goals, orders.kinds, step_keys, init, warm)
        for candidate in orders.candidates:
            announce(cfg, candidate.omega, log)
        plans = [propose(now, c, cfg=cfg, timing=timing, dynamics=dynamics) for c in orders.candidates]
        kept = (orders.keep if callable(orders.keep) else KEEPS[orders.keep])(worlds, now, plans, score, timing)
        record = dict(step=t, **{k: np.asarray(kept[k]) for k in ("omega", "bucket", "adam_steps", "objective",
                                                                  "predicted_objective", "distance", "inside",
                                                                  "action")})
        record.update(planning_s=_planning_seconds(kept, timing), broken=np.asarray(kept["states"].broken),
                      **{k: np.asarray(v) for k, v in orders.record.items()},
                      **{k: np.asarray(v) for k, v in chooser.score(kept["states"]).items()})
        for callback in on_step:
            callback(t, states, kept["particles"], record)
        states, init, warm = kept["states"], shift(kept["best"]), cfg.warm_start
        records.append(dict(record, seconds=time.perf_counter() - t0))
        _log_step(log, records[-1], cfg.mpc_steps)
        if record["broken"].all():
            log("every simulated world broke (NaN or a piece out of the bin); stopping")
            break
    return Episodes(states, records)


def run_episode(env: PileEnv, state: State, chooser: Chooser, dynamics, cfg: MPCConfig, key, **kwargs
                ) -> tuple[State, list[dict]]:
    """One episode in one PileEnv: ``run`` on a batch of one (the chooser's goals batched too), its records unbatched
    to Python numbers (``episode_record``). kwargs: ``run``'s timing, view, on_step, log."""
    final, records = run(EnvWorlds(env), batch(state), chooser, dynamics, cfg, batch(key), **kwargs)
    return episode(final), [episode_record(r, 0) for r in records]


def episode_record(record: dict, b: int) -> dict:
    """Episode b's share of a ``run`` record, as Python numbers (JSON-ready)."""
    return {k: (v if k in ("step", "seconds") else np.asarray(v)[b].tolist()) for k, v in record.items()}


_planned: set = set()  # (DecisionSpec, batch size) of the decisions this process has run: the first compiles


def announce(cfg: MPCConfig, omega, log) -> None:
    """One line before the first decision of a bucket and batch size, which compiles (tens of seconds on a CPU)."""
    spec = cfg.spec(max(budget.bucket_for(int(w), cfg.buckets) for w in np.asarray(omega)))
    if (spec, len(omega)) not in _planned:
        _planned.add((spec, len(omega)))
        log(f"compiling the decision at bucket {spec.capacity} for {len(omega)} episode(s) (once per bucket; "
            "tens of seconds on a CPU)")


def _drawn(now: Situation, draw: int) -> Situation:
    """``now`` with the keys of independent plan ``draw`` (0: the step's own)."""
    if draw == 0:
        return now
    return now._replace(keys=fold(now.keys, PLAN_DRAWS + draw))


def fold(keys, n: int):
    """keys [B] each with ``n`` folded in (``jax.random.fold_in``): a step's keys, a sensor's, a plan draw's."""
    return jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, n)


def shift(best):
    """The plan of the next step: the remaining pushes, the last one repeated (warm start)."""
    return jnp.concatenate([best[..., 1:, :], best[..., -1:, :]], axis=-2)


def _lowest_distance(outcomes: list[dict]) -> dict:
    """Per episode b, leaf [b] of the outcome whose push left the lowest d (``keep_lowest_distance``'s dicts,
    arrays [B])."""
    return _pick(outcomes, np.argmin(np.stack([np.asarray(o["distance"]) for o in outcomes]), axis=0))


def _pick(outcomes: list[dict], pick) -> dict:
    """Per episode b, leaf [b] of outcome pick[b] (dicts of arrays [B]; particles of candidates in smaller buckets
    padded with masked slots to the largest)."""
    slots = max(o["particles"].mask.shape[1] for o in outcomes)
    pad = lambda x: jnp.pad(x, [(0, 0), (0, slots - x.shape[1])] + [(0, 0)] * (x.ndim - 2))  # noqa: E731
    outcomes = [dict(o, particles=o["particles"]._replace(positions=pad(o["particles"].positions),
                                                          mask=pad(o["particles"].mask))) for o in outcomes]
    pick, rows = jnp.asarray(pick), jnp.arange(len(pick))
    return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x])[pick, rows], *outcomes)


def _seconds(planned: dict, timing: budget.TimingTable | None) -> np.ndarray:
    """A decision's planning seconds [B]: the table's price of its bucket and steps, else its wall time."""
    if timing is None:
        return np.asarray(planned["wall"])
    return np.array([timing.seconds(int(b), int(s)) for b, s in zip(planned["bucket"], planned["adam_steps"],
                                                                    strict=True)])


def _planning_seconds(kept: dict, timing: budget.TimingTable | None) -> np.ndarray:
    """planning_s [B]: one episode's own wall time (refining the table), else the table's price, else NaN."""
    if len(kept["wall"]) == 1:
        if timing is not None:
            timing.refine(int(kept["bucket"][0]), int(kept["adam_steps"][0]), float(kept["wall"][0]))
        return np.asarray(kept["wall"])
    if timing is None:
        return np.full(len(kept["wall"]), np.nan)
    return _seconds(kept, timing)


@functools.cache
def scorer(camera, piece_kinds: tuple[int, ...]):
    """A jitted ``(states [B], goals [B]) -> {distance, inside}`` on the true state (``_measure``)."""
    one = per_episode(functools.partial(_measure, camera, jnp.asarray(piece_kinds)))
    scores = jax.jit(lambda obs, pos, goals: one(obs, pos, goals))
    return lambda states, goals: dict(zip(("distance", "inside"), scores(states.obs, states.pos, goals), strict=True))


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
            f"{int(r['adam_steps'][0]):3d} Adam steps)  c={float(r['objective'][0]):7.2f} -> predicted "
            f"{float(r['predicted_objective'][0]):7.2f}  d={float(r['distance'][0]):7.2f}  "
            f"inside={float(r['inside'][0]):5.1%}  plan {float(r['planning_s'][0]):5.2f}s")
    else:
        log(f"step {r['step'] + 1:2d}/{steps}  {len(r['omega'])} episodes  mean ω={r['omega'].mean():5.1f}  mean "
            f"Adam steps={r['adam_steps'].mean():5.1f}  mean d={r['distance'].mean():7.2f}  "
            f"mean inside={r['inside'].mean():5.1%}  {r['seconds']:5.2f}s")
