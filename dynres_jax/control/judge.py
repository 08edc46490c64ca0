"""The judge (issue 65): two models, the fast one proposes and a second, more accurate one chooses. The planner
refines its M candidates with the fast model (``choosers.Candidate.proposals == "plans"``: the M candidates after the
Adam steps and the model's best); the judge rolls each one out from the decision's own particles and scores its final
state on the task objective c; the candidate with the lowest judged c is pushed. Nothing is simulated, so a robot can
run it; the simulator choosing among the same candidates (``SimulatorScored(..., refine=True)``, the ``rerank`` rung)
is the judge's ceiling. The judge is any planner dynamics (``models.registry``: radius -> model), so any checkpoint
the registry loads can judge: ``JudgeScored(FixedOmega(goals, 50), load_dynamics("learned", CKPT, ...).dynamics)``.
The robot's loop (``control.robot.run_robot``) takes it too: its keep rule chooses without worlds
(``JudgeKeep.choose``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.control.choosers import Chooser, Orders, one_plan
from dynres_jax.control.decision import goal_cost
from dynres_jax.control.goals import KindGoals
from dynres_jax.control.keep import keep_lowest_distance


@functools.partial(jax.jit, static_argnames=("dynamics", "camera"))
def judged_costs(particles, goals, proposals, *, dynamics, camera):
    """c of each proposal's final state as the judge predicts it: particles [B] (``perception.Particles``: positions
    [B, N, 3] m, mask [B, N], radius [B]), goals [B] (a batched Goal), proposals [B, K, T, 4] (push sequences, m) ->
    [B, K]. dynamics: radius -> the judge's model ``(positions, mask, actions [T, 4]) -> [T, N, 3]``."""
    capacity = particles.positions.shape[1]

    def one(positions, mask, radius, goal, sequences):
        model, cost = dynamics(radius), goal_cost(goal, camera, capacity)
        return jax.vmap(lambda seq: cost(model(positions, mask, seq)[-1], mask))(sequences)

    return jax.vmap(one)(particles.positions, particles.mask, particles.radius, goals, proposals)


def lowest_judged(costs):
    """costs [..., K] (judged c) -> (the index [...] of the lowest finite one, the first on ties; that c, +inf where
    none is finite): a candidate the judge cannot score is never chosen."""
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    pick = jnp.argmin(costs, axis=-1)
    return pick, jnp.take_along_axis(costs, pick[..., None], axis=-1)[..., 0]


class JudgeKeep(NamedTuple):
    """Keep rule of ``JudgeScored`` (``Orders.keep``; called as ``keep.KEEPS``' rules are): per episode the proposal of
    the one plan whose judged c is lowest (the first on ties) is pushed in the worlds; its judged c is the record's
    predicted_objective. ``choose`` is the same choice without worlds (a robot's loop). dynamics: radius -> the
    judge's model."""

    dynamics: object

    def choose(self, plan: dict, now) -> dict:
        """The plan (``mpc.propose``'s, proposals [B, K, T, 4]) with its one proposal per episode, the judge's pick
        ([B, 1, T, 4]), and the judged c as predicted_objective [B]; ValueError for an episode the judge cannot score
        at all (non-finite c for every candidate)."""
        pick, cost = (np.asarray(x) for x in lowest_judged(judged_costs(
            plan["particles"], now.goals, jnp.asarray(plan["proposals"]), dynamics=self.dynamics, camera=now.camera)))
        lost = np.flatnonzero(np.isinf(cost))
        if lost.size:
            raise ValueError(f"the judge scored no candidate of episodes {lost.tolist()} (non-finite c for all)")
        return dict(plan, proposals=np.asarray(plan["proposals"])[np.arange(len(pick)), pick][:, None],
                    predicted_objective=cost.astype(np.float32))

    def __call__(self, worlds, now, plans: list[dict], score, timing=None) -> dict:
        if len(plans) != 1:
            raise ValueError(f"the judge chooses among one plan's proposals, got {len(plans)} plans")
        return keep_lowest_distance(worlds, now, [self.choose(plans[0], now)], score)


class JudgeScored(Chooser):
    """Another chooser's orders (one candidate ω each step), the push chosen by the judge among the planner's M
    candidates after the fast model's Adam steps and its best (``JudgeKeep``). Gather and Redistribute goals."""

    def __init__(self, chooser: Chooser, judge):
        self.chooser, self.keep = chooser, JudgeKeep(judge)

    def __call__(self, t, obs) -> Orders:
        orders = one_plan(self.chooser(t, obs), "the judge's choice")
        if isinstance(orders.goals, KindGoals):
            raise ValueError("the judge scores Gather and Redistribute goals; Sort's per-kind goals are not supported")
        return orders._replace(candidates=(orders.candidates[0]._replace(proposals="plans"),), keep=self.keep)

    def score(self, states) -> dict:
        return self.chooser.score(states)
