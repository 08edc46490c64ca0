"""Closed loop (model-predictive control): observe -> h(y, ω) -> plan -> push, repeated, for many episodes at once.

Worlds (``sim.pool.Worlds``) push a batch of simulated piles. A chooser (``choosers``; ``sort.SortPolicy``) orders at
each MPC step the goals, candidate plans and piece kinds, and how to keep one (``keep``). The decision
(``decision.decide_batch``) perceives every frame once and plans, compiled once per resolution bucket. ``run`` joins
them: each decision gets the Adam steps its ω affords (``MPCConfig.allot``: a count, or a time budget through a
``budget.TimingTable``), the kept plan's first push is executed, the step scored on the true state and the next
warm-started with the plan shifted. What the planner sees is a view (``views``: the simulator's frames, or a real
camera's); GIF frames and other per-step work are ``on_step`` callbacks.
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
from dynres_jax.control.choosers import Candidate, Chooser, Orders
from dynres_jax.control.decision import DecisionSpec, Situation, batch, decide_batch, episode, fold, per_episode
from dynres_jax.control.goals import Goal
from dynres_jax.control.keep import KEEPS, keep_lowest_distance, planning_price, scorer
from dynres_jax.control.objective import seen_inside
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.control.views import ExactView
from dynres_jax.errors import InputError
from dynres_jax.perception import visible_points
from dynres_jax.sim.env import PileEnv, State
from dynres_jax.sim.pool import EnvWorlds, Worlds

PLAN_DRAWS = 1 << 20  # plan draw d > 0 folds PLAN_DRAWS + d into a step's keys (away from the sensor's fold 1)


@dataclass(frozen=True)
class MPCConfig:
    """mpc_steps: MPC steps per episode (reference 20); buckets: the particle capacities ω is padded to (``budget``);
    max_points: perception's point cap; planner: the shooting optimiser's settings (its steps: the Adam steps of a
    decision without a time budget, and the most with one); time_budget: seconds per decision on the planning device
    (None: planner.adam_steps every decision); real_depth: perception treats the depth as a real camera's
    (``sim.sensor``); warm_start: each plan starts from the last, shifted (False: fresh samples, as the reference);
    stop_share: an episode holds (pushes no more) from the first frame on which this share of the foreground its
    camera sees lies inside the goal (``objective.seen_inside``; Sort: the share of each kind's perceived particles
    inside its goal, the lower kind's; None: it pushes every step)."""

    mpc_steps: int = 20
    buckets: tuple[int, ...] = budget.BUCKETS
    max_points: int | None = 4096
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    time_budget: float | None = None
    real_depth: bool = False
    warm_start: bool = True
    stop_share: float | None = None

    def __post_init__(self):
        check_fields(self)
        if self.stop_share is not None and not 0 < self.stop_share <= 1:
            raise ValueError(f"stop_share must be in (0, 1] or None, got {self.stop_share}")
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


def act(worlds: Worlds, now: Situation, omega, *, cfg: MPCConfig, timing: budget.TimingTable | None, dynamics,
        score: Callable) -> dict:
    """The model's plan at omega [B] from ``now``, pushed in ``worlds``, scored (``keep_lowest_distance``'s [B])."""
    plan = propose(now, Candidate(omega), cfg=cfg, timing=timing, dynamics=dynamics)
    return keep_lowest_distance(worlds, now, [plan], score)


class Progress(NamedTuple):
    """Where a closed loop stands after a step, enough to go on from it: the records so far (``run``'s), the worlds
    after the last push, the next decision's warm start init [B, T, 4] and whether to use it (one for all, or [B]),
    and held [B] (the stop rule's)."""

    records: list[dict]
    states: State
    init: jax.Array
    warm: bool | np.ndarray
    held: np.ndarray


class Episodes(NamedTuple):
    """What ``run`` returns: the final states [B] and one record per MPC step (arrays [B]; ``run``)."""

    states: State
    records: list[dict]


def run(worlds: Worlds, states: State, chooser: Chooser, dynamics, cfg: MPCConfig, keys, *,
        timing: budget.TimingTable | None = None, view=None, on_step: Sequence[Callable] = (), log=print,
        resume: Progress | None = None, on_progress: Callable[[Progress], None] | None = None) -> Episodes:
    """The closed loop over a batch of episodes: states [B] in ``worlds``, keys [B]; every MPC step the chooser's
    orders (``choosers.Orders``), one compiled decision over all episodes per candidate (``propose``) and, per
    episode, the proposal the orders' keep rule keeps (``KEEPS``; one that returns warm [B] says which episodes' next
    decisions start from the kept plan, else cfg.warm_start for all). dynamics: ``registry`` (radius -> the planner's
    model); timing: the table a time budget is spent by (required with cfg.time_budget; a batch of one refines it
    from its decisions' wall times unless frozen); view: what the planner sees (``ExactView``; ``SensorView``);
    on_step: callbacks ``(t, states before the push, kept Particles [B], record)`` (GIF frames: ``io.draw.Frames``);
    log: one line per step; resume: a ``Progress`` to go on from (its states replace ``states``; the steps it
    recorded are not run again, and with the same keys and an ``ExactView`` the rest is decided as the whole run
    would); on_progress: called with the ``Progress`` after every step (the task commands save it). Stops early when
    every world broke. A record holds arrays [B]: omega, bucket, adam_steps, planning_s (B = 1: the decision's wall
    time; else the table's price of it, NaN without a budget), objective (c before the push), predicted_objective,
    distance (d after the push) and inside (the share of pieces inside the goal, on the true state), action, broken,
    the chooser's record fields and scores; and step and seconds; seen_inside (the share its camera saw inside the
    goal before the push, ``objective.seen_inside``; Sort: the lower kind's perceived share, ``_seen``) and held
    (cfg.stop_share: the episode pushed nothing this step; its action and prediction NaN, its state and scores
    unchanged; a step where every episode holds plans nothing: its adam_steps and planning_s 0, its objective NaN,
    the rest as the step before). Every run has cfg.mpc_steps records unless every world broke."""
    if cfg.time_budget is not None and timing is None:
        raise ValueError("a closed loop under a time budget needs a timing table (mpc.measure_timing, --timing FILE)")
    view = view or ExactView(worlds.camera)
    score = scorer(worlds.camera, tuple(np.asarray(worlds.scene.kind).tolist()))
    records, warm, held = [], False, np.zeros(len(keys), bool)
    init = jnp.zeros((len(keys), cfg.planner.horizon, 4), jnp.float32)  # no warm start at the first step
    if resume is not None:
        records, states, init, warm, held = list(resume.records), resume.states, resume.init, resume.warm, resume.held
        if records and np.all(records[-1]["broken"]):
            return Episodes(states, records)  # it had stopped: every world broke
    for t in range(len(records), cfg.mpc_steps):
        t0 = time.perf_counter()
        step_keys = fold(keys, t)
        seen, camera = view(t, states, step_keys)
        orders = chooser(t, seen)
        stop = _seen(seen, orders, camera, cfg)
        if stop and cfg.stop_share is not None:
            held |= np.asarray(stop["seen_inside"], np.float64) >= cfg.stop_share  # as ``tasks.stopped`` compares
            if held.all() and records:  # nothing left to push: the last step's scores stand
                records.append(dict(records[-1], step=t, seconds=time.perf_counter() - t0, **stop,
                                    **_holding(held, records[-1]), adam_steps=np.zeros_like(records[-1]["adam_steps"]),
                                    planning_s=np.zeros(len(held)), objective=np.full(len(held), np.nan)))
                _log_step(log, records[-1], cfg.mpc_steps)
                if on_progress is not None:
                    on_progress(Progress(records, states, init, warm, held))
                continue
        now = Situation(states, seen, camera, orders.goals, orders.kinds, step_keys, init, warm)
        for candidate in orders.candidates:
            announce(cfg, candidate.omega, log)
        plans = [propose(now, c, cfg=cfg, timing=timing, dynamics=dynamics) for c in orders.candidates]
        kept = (orders.keep if callable(orders.keep) else KEEPS[orders.keep])(worlds, now, plans, score, timing)
        record = dict(step=t, **{k: np.asarray(kept[k]) for k in ("omega", "bucket", "adam_steps", "objective",
                                                                  "predicted_objective", "distance", "inside",
                                                                  "action")})
        if held.any():  # held episodes keep their state: d and the share inside as before the push
            kept = dict(kept, states=_where(held, states, kept["states"]))
            before = score(states, orders.goals)
            record.update({k: np.where(held, np.asarray(before[k]), record[k]) for k in ("distance", "inside")})
        if cfg.stop_share is not None:
            record.update(_holding(held, record))
        record.update(planning_s=_planning_seconds(kept, timing), broken=np.asarray(kept["states"].broken),
                      **stop, **{k: np.asarray(v) for k, v in orders.record.items()},
                      **{k: np.asarray(v) for k, v in chooser.score(kept["states"]).items()})
        for callback in on_step:
            callback(t, states, kept["particles"], record)
        states, init, warm = kept["states"], shift(kept["best"]), kept.get("warm", cfg.warm_start)
        records.append(dict(record, seconds=time.perf_counter() - t0))
        _log_step(log, records[-1], cfg.mpc_steps)
        if on_progress is not None:
            on_progress(Progress(records, states, init, warm, held))
        if record["broken"].all():
            log("every simulated world broke (NaN or a piece out of the bin); stopping")
            break
    return Episodes(states, records)


def run_episode(env: PileEnv, state: State, chooser: Chooser, dynamics, cfg: MPCConfig, key, **kwargs
                ) -> tuple[State, list[dict]]:
    """One episode in one PileEnv: ``run`` on a batch of one (the chooser's goals batched too), its records unbatched
    to Python numbers (``episode_record``). kwargs: ``run``'s timing, view, on_step, log, resume, on_progress."""
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


def _seen(seen, orders: Orders, camera, cfg: MPCConfig) -> dict:
    """{seen_inside [B]}: the share of each frame's foreground its camera sees inside the goal; with Sort's goals
    (one a kind), the lower kind's share of its perceived particles inside its own goal (``sort.SortPolicy``'s
    perceived_inside; {} for a chooser that records none, refused with cfg.stop_share)."""
    if orders.goals.labels_kinds:
        if "perceived_inside" in orders.record:
            return dict(seen_inside=np.min(np.asarray(orders.record["perceived_inside"], np.float64), axis=-1))
        if cfg.stop_share is not None:
            raise InputError("the stop rule on goals one a kind reads each kind's perceived share (SortPolicy's "
                             "perceived_inside), which this chooser's orders do not record")
        return {}
    return dict(seen_inside=np.asarray(_seen_inside(camera, cfg.real_depth)(seen, orders.goals)))


@functools.cache
def _seen_inside(camera, real_depth: bool):
    """A jitted ``(frames [B], goals [B]) -> seen_inside [B]`` (``objective.seen_inside``)."""
    one = per_episode(functools.partial(seen_inside, camera=camera, real_depth=real_depth))
    return jax.jit(lambda seen, goals: one(seen, goals))


def _where(held, before: State, after: State) -> State:
    """Per episode b, ``before``'s leaves [b] where held[b], else ``after``'s."""
    return jax.tree.map(lambda x, y: jnp.where(jnp.reshape(held, held.shape + (1,) * (jnp.ndim(y) - 1)), x, y),
                        before, after)


def _holding(held, record: dict) -> dict:
    """A record's fields under the stop rule: held [B], and the held episodes' action and predicted_objective NaN."""
    return dict(held=held.copy(), action=np.where(held[:, None], np.nan, record["action"]),
                predicted_objective=np.where(held, np.nan, record["predicted_objective"]))


def _drawn(now: Situation, draw: int) -> Situation:
    """``now`` with the keys of independent plan ``draw`` (0: the step's own)."""
    return now if draw == 0 else now._replace(keys=draw_keys(now.keys, draw))


def draw_keys(keys, draw: int):
    """keys [B] of independent plan ``draw``: the keys themselves for draw 0, else with PLAN_DRAWS + draw folded in."""
    return keys if draw == 0 else fold(keys, PLAN_DRAWS + draw)


def shift(best):
    """The plan of the next step: the remaining pushes, the last one repeated (warm start)."""
    return jnp.concatenate([best[..., 1:, :], best[..., -1:, :]], axis=-2)


def _planning_seconds(kept: dict, timing: budget.TimingTable | None) -> np.ndarray:
    """planning_s [B]: one episode's own wall time (refining the table), else the table's price, else NaN."""
    if len(kept["wall"]) == 1:
        if timing is not None:
            timing.refine(int(kept["bucket"][0]), int(kept["adam_steps"][0]), float(kept["wall"][0]))
        return np.asarray(kept["wall"])
    if timing is None:
        return np.full(len(kept["wall"]), np.nan)
    return planning_price(kept, timing)


def _inside_text(r: dict) -> str:
    """The share inside as the task's success reads it: Sort's per kind, each in its own goal (kind_inside [B, 2],
    averaged over a batch), else the pieces inside the goal."""
    if "kind_inside" in r:
        return "inside each kind's goal " + " / ".join(f"{x:.0%}" for x in np.mean(r["kind_inside"], axis=0))
    return f"inside={float(np.mean(r['inside'])):5.1%}"


def _log_step(log, r: dict, steps: int) -> None:
    """One line per MPC step: the episode's values, or the means of a batch; and which episodes the stop rule holds."""
    held = np.asarray(r.get("held", np.zeros(len(r["omega"]), bool)))
    if len(r["omega"]) == 1 and held[0]:
        log(f"step {r['step'] + 1:2d}/{steps}  held by the stop rule (the camera saw {float(r['seen_inside'][0]):.0%} "
            f"inside before this push): no push  d={float(r['distance'][0]):7.2f}  {_inside_text(r)}")
    elif len(r["omega"]) == 1:
        log(f"step {r['step'] + 1:2d}/{steps}  ω={int(r['omega'][0]):3d} (bucket {int(r['bucket'][0]):3d}, "
            f"{int(r['adam_steps'][0]):3d} Adam steps)  c={float(r['objective'][0]):7.2f} -> predicted "
            f"{float(r['predicted_objective'][0]):7.2f}  d={float(r['distance'][0]):7.2f}  "
            f"{_inside_text(r)}  plan {float(r['planning_s'][0]):5.2f}s")
    else:
        log(f"step {r['step'] + 1:2d}/{steps}  {len(r['omega'])} episodes  mean ω={r['omega'].mean():5.1f}  mean "
            f"Adam steps={r['adam_steps'].mean():5.1f}  mean d={r['distance'].mean():7.2f}  "
            f"mean {_inside_text(r)}{f'  {int(held.sum())} held by the stop rule' if held.any() else ''}  "
            f"{r['seconds']:5.2f}s")
