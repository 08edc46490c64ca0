"""Keep rules: how the closed loop keeps one proposal per episode from the candidates' plans (``choosers.Orders.keep``
names one of ``KEEPS``; a chooser may bring its own, as ``judge.JudgeScored`` does). "distance" pushes every proposal
on a copy of the worlds and keeps the one that left the lowest d (the simulator judges; one proposal: it is simply
pushed); "rate" keeps the plan whose model predicts the largest fall of c per second of planning. ``scorer`` gives
the step's scores (d, the share inside) on the true state.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.chunks import in_chunks
from dynres_jax.control import budget
from dynres_jax.control.decision import Situation, per_episode
from dynres_jax.control.goals import KindGoals
from dynres_jax.control.objective import distribution_distance, inside_share
from dynres_jax.sim.pool import Worlds

SIMULATED_WORLDS = 512  # worlds per push call when the simulator scores proposals (``keep_lowest_distance``)


def keep_lowest_distance(worlds: Worlds, now: Situation, plans: list[dict], score: Callable,
                         timing: budget.TimingTable | None = None) -> dict:
    """Keep rule "distance": every proposal of every plan (``mpc.propose``) pushed on a copy of the worlds (a plan's
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
    rates = np.stack([(np.asarray(p["objective"]) - np.asarray(p["predicted_objective"])) / planning_price(p, timing)
                      for p in plans])
    return _pick(plans, np.argmax(rates, axis=0))


KEEPS = {"distance": keep_lowest_distance, "rate": keep_best_rate}  # Orders.keep -> how the loop keeps a candidate


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


def planning_price(planned: dict, timing: budget.TimingTable | None) -> np.ndarray:
    """A decision's planning seconds [B]: the table's price of its bucket and steps, else its wall time."""
    if timing is None:
        return np.asarray(planned["wall"])
    return np.array([timing.seconds(int(b), int(s)) for b, s in zip(planned["bucket"], planned["adam_steps"],
                                                                    strict=True)])


@functools.cache
def scorer(camera, piece_kinds: tuple[int, ...]):
    """A jitted ``(states [B], goals [B]) -> {distance, inside}`` on the true state (``_measure``)."""
    one = per_episode(functools.partial(_measure, camera, jnp.asarray(piece_kinds)))
    scores = jax.jit(lambda obs, pos, goals: one(obs, pos, goals))
    return lambda states, goals: dict(zip(("distance", "inside"), in_chunks(scores, states.obs, states.pos, goals),
                                          strict=True))


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
