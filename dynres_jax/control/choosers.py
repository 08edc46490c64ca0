"""Choosers: what the closed loop plans for at each MPC step (``mpc.run``). A chooser is called with the step and
the frames the planner sees, and answers with ``Orders``: the goals, the plans to make (``Candidate``: ω of every
episode, plan draw, budget share, what is put forward), how the loop keeps one per episode (the lowest d after a push,
or the one the model rates best), and which piece kinds to perceive; the loop (``mpc.run``) has one path for all.
Fixed ω, the regressor g (adaptive ω, paper Sec. IV-C), a probe of several ω judged by the model (no labels), the
oracle over ω, the best of K plans at one ω, the simulator as the model (the ``sim`` ceiling), a second model as the
judge (``judge.JudgeScored``) and Sort's A* waypoints (``sort.SortPolicy``) are choosers; a new way of choosing is a
new chooser, not a new parameter of the loop.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from dynres_jax.config import check_omega
from dynres_jax.control.goals import Goal, KindGoals

ORACLE_OMEGAS = (10, 25, 50, 75, 100)  # the oracle's candidates at every step
PROBE_OMEGAS = (25, 50, 100)  # the probe's candidates: one in each bucket above 16


class Candidate(NamedTuple):
    """One plan the loop makes at an MPC step (``mpc.propose``). omega [B]: its ω per episode; draw: which independent
    plan (0: the step's own keys, the same for every ω; d > 0: keys of their own, ``mpc.PLAN_DRAWS``); share: its share
    of the decision's time budget; proposals: what it puts forward to be kept: "plan" (the model's best plan),
    "samples" (the planner's M first samples: no Adam step, no model) or "plans" (its M candidates after the Adam
    steps with the model, and its best)."""

    omega: np.ndarray
    draw: int = 0
    share: float = 1.0
    proposals: str = "plan"


class Orders(NamedTuple):
    """A chooser's orders for one MPC step, arrays with a leading axis [B]. goals: this step's goal of each
    decision (a batched Goal or KindGoals; the step's d and inside share are scored against it); candidates: the
    plans to make (``Candidate``); kinds [B]: the piece kind each decision perceives (None: every piece); record:
    extra record fields, arrays [B]; keep: how the loop keeps one proposal per episode (``keep.KEEPS``): "distance"
    (each pushed on a copy of the worlds, the lowest d kept; one proposal is simply pushed) or "rate" (the plan whose
    model predicts the largest fall of c per second of planning, pushed; nothing simulated), or a callable with
    their signature (``judge.JudgeKeep``: the proposal a second model rates best)."""

    goals: Goal | KindGoals
    candidates: tuple[Candidate, ...]
    kinds: np.ndarray | None = None
    record: dict = {}
    keep: str | Callable = "distance"


def at(omegas: tuple[int, ...], b: int, **kwargs) -> tuple[Candidate, ...]:
    """One candidate per ω of ``omegas``, the same for all b episodes (kwargs: ``Candidate``'s draw, share)."""
    return tuple(Candidate(np.full(b, w, np.int32), **kwargs) for w in omegas)


class Chooser:
    """Base of the choosers: ``__call__(t, obs [B]) -> Orders``; ``score(states) -> {name: [B, ...]}`` adds a task's
    own scores to each step's record (none here)."""

    def __call__(self, t: int, obs) -> Orders:
        raise NotImplementedError

    def score(self, states) -> dict:
        return {}


class FixedOmega(Chooser):
    """The same ω for every episode and step, against fixed goals [B]."""

    def __init__(self, goals, omega: int):
        self.goals, self.omega = goals, check_omega(omega)

    def __call__(self, t, obs) -> Orders:
        return Orders(self.goals, at((self.omega,), len(obs.depth)))


class AdaptiveOmega(Chooser):
    """Adaptive resolution: ω of each episode at each step from the regressor g(y, y_g) (``resolution.load_regressor``:
    a ``(obs [B], goals [B]) -> ω [B]`` function)."""

    def __init__(self, goals, regressor):
        self.goals, self.regressor = goals, regressor

    def __call__(self, t, obs) -> Orders:
        return Orders(self.goals, (Candidate(np.asarray(self.regressor(obs, self.goals), np.int32)),))


class OracleOmega(Chooser):
    """Every step plans at each candidate ω (same keys), pushes each on a copy of the worlds and keeps, per episode,
    the one whose push left the lowest d: a greedy upper bound of any chooser of ω."""

    def __init__(self, goals, omegas=ORACLE_OMEGAS):
        if not omegas:
            raise ValueError("the oracle needs at least one candidate ω")
        self.goals, self.omegas = goals, tuple(check_omega(w, "an oracle candidate") for w in omegas)

    def __call__(self, t, obs) -> Orders:
        return Orders(self.goals, at(self.omegas, len(obs.depth)))


class ProbeOmega(Chooser):
    """ω without labels: every step plans at each candidate ω (the same keys), each with an equal share of the
    decision's time budget, and keeps per episode the plan whose predicted fall of c per second of planning is the
    largest (``Orders.keep`` "rate"). The model judges its own plans; no world is pushed twice. A step's record
    (Adam steps, planning seconds) is the kept plan's; the step spent the whole budget."""

    def __init__(self, goals, omegas=PROBE_OMEGAS):
        if len(omegas) < 2:
            raise ValueError("the probe needs at least two candidate ω")
        self.goals, self.omegas = goals, tuple(check_omega(w, "a probe candidate") for w in omegas)

    def __call__(self, t, obs) -> Orders:
        return Orders(self.goals, at(self.omegas, len(obs.depth), share=1 / len(self.omegas)), keep="rate")


class BestOfK(Chooser):
    """K plans of another chooser's orders (one candidate ω each step) from independent keys (draw 0 is that chooser's
    own plan), pushed on copies of the worlds, the one that left the lowest d kept: what choosing among K plans gains
    without choosing ω (the oracle's control). ``BestOfK(FixedOmega(goals, 50), 5)``; Sort's ``SortPolicy`` too."""

    def __init__(self, chooser: Chooser, k: int):
        if isinstance(k, bool) or int(k) != k or k < 1:
            raise ValueError(f"best-of-K needs K >= 1 plans, got {k!r}")
        self.chooser, self.k = chooser, int(k)

    def __call__(self, t, obs) -> Orders:
        orders = one_plan(self.chooser(t, obs), "best-of-K")
        return orders._replace(candidates=tuple(orders.candidates[0]._replace(draw=d) for d in range(self.k)))

    def score(self, states) -> dict:
        return self.chooser.score(states)


class SimulatorScored(Chooser):
    """Another chooser's orders (one candidate ω each step), the push chosen by the simulator among the planner's M
    candidates: each pushed on a copy of the worlds, the one that left the lowest d kept. refine False (the `sim`
    rung): the M first samples (drawn as every method draws them from the step's keys), no learned model and no Adam
    step: the ceiling of the action space and the sampling alone. refine True (the `rerank` rung): the M candidates
    after the model's Adam steps: how much a perfect ranking of the model's own plans would gain.
    ``SimulatorScored(FixedOmega(goals, 50))``; Sort's ``SortPolicy`` too."""

    def __init__(self, chooser: Chooser, refine: bool = False):
        self.chooser, self.refine = chooser, refine

    def __call__(self, t, obs) -> Orders:
        orders = one_plan(self.chooser(t, obs), "the simulator's choice")
        return orders._replace(candidates=(orders.candidates[0]._replace(proposals="plans" if self.refine else
                                                                         "samples"),))

    def score(self, states) -> dict:
        return self.chooser.score(states)


def one_plan(orders: Orders, what: str) -> Orders:
    """orders, checked to hold one plain candidate (one ω, draw 0, the whole budget, the model's plan): what
    ``what`` builds on."""
    c = orders.candidates
    off = [name for name, odd in (("drawn", any(x.draw for x in c)),
                                  ("a share of the budget", any(x.share != 1 for x in c)),
                                  ("simulated", any(x.proposals != "plan" for x in c))) if odd]
    if len(c) != 1 or off:
        raise ValueError(f"{what} builds on a chooser of one plan per step, got {len(c)} candidate"
                         f"{'s' if len(c) > 1 else ''}{''.join(', ' + o for o in off)}")
    return orders


def best_of(method: str) -> int:
    """K of a best-of-K method name ("best5" -> 5), else 0."""
    match = re.fullmatch(r"best([1-9][0-9]*)", method)
    return int(match.group(1)) if match else 0


def on_ladder(method: str) -> bool:
    """Whether ``method`` names a rung of the ladder (docs/ladder): "bestK", "sim" or "rerank"."""
    return bool(best_of(method)) or method in ("sim", "rerank")


def climb(chooser: Chooser, method: str) -> Chooser:
    """``chooser`` (one plan a step) on the ladder's rung ``method``: "bestK" (``BestOfK``), "sim" (the simulator
    chooses among the first samples) or "rerank" (among the plans after the model's Adam steps; ``SimulatorScored``)."""
    if best_of(method):
        return BestOfK(chooser, best_of(method))
    if method in ("sim", "rerank"):
        return SimulatorScored(chooser, refine=method == "rerank")
    raise ValueError(f"not a rung of the ladder: {method!r} (bestK, sim or rerank)")
