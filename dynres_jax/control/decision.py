"""One MPC decision, pure: a frame perceived once (``perception.perceive``), c of its particles, and the plan.

``DecisionSpec`` (particle capacity, planner, perception settings) is what keys compilation; everything that changes
from call to call (ω, the Adam steps, the warm start, the keys, the goal) is an argument, so one compiled
``decide_batch`` serves a whole run per resolution bucket. The planner's starting pushes pass through random points of
the perception cloud, not of the particles, so one key gives the same pushes at every ω (common random numbers).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import Partial

from dynres_jax.chunks import in_chunks
from dynres_jax.control.goals import Goal, KindGoals
from dynres_jax.control.objective import SAMPLES_PER_PARTICLE
from dynres_jax.control.planner import PlannerConfig, plan, sample_pushes
from dynres_jax.perception import Perceived, check_particles, cloud_particles, perceive
from dynres_jax.sim.env import State


@dataclass(frozen=True)
class DecisionSpec:
    """What a compiled decision is specialised to. capacity: particle slots (a resolution bucket, ``budget``);
    planner: the shooting optimiser (its ``adam_steps``: the most a decision may run); max_points: perception's
    point cap; real_depth: perception treats the depth as a real camera's (``perception.foreground``)."""

    capacity: int
    planner: PlannerConfig
    max_points: int | None = 4096
    real_depth: bool = False


def goal_cost(goal: Goal | KindGoals, camera, capacity: int | None = None, kinds=None, baseline=None) -> Partial:
    """The planner's cost: the task objective c of predicted particles against ``goal``, as the goal carries it
    (``Goal.planner_cost``; KindGoals: Sort's objective with the particles' kinds [N] and each kind's c now, baseline
    [K]). capacity: the particle slots; the goal's samples are cut to the SAMPLES_PER_PARTICLE × capacity that c can
    use at ω <= capacity (the same c, on fewer samples)."""
    if capacity is not None:
        goal = goal.cut(SAMPLES_PER_PARTICLE * capacity)
    return goal.planner_cost(camera, kinds, baseline)


def decide(seen: Perceived, goal: Goal | KindGoals, key, init, warm, adam_steps, *, spec: DecisionSpec, dynamics,
           camera, resampled=None):
    """c of the perceived particles and the plan. init [T, 4]: the warm start (the previous plan, shifted), used where
    ``warm`` (may be traced), or None; adam_steps: may be traced. goal: a Goal, or KindGoals (Sort: ``seen.kinds``
    label the particles, c is ``kind_objective`` with each kind's c now as the held kinds' baseline). dynamics:
    radius -> the planner's model (``registry``). resampled: (positions [R, N, 3], mask [R, N]), the R re-samplings
    the plan scores each push on (spec.planner.resamples; the first is seen.particles), or None for R = 1. Returns
    (c [], PlanResult)."""
    p = seen.particles
    if goal.labels_kinds and resampled is not None:
        raise ValueError("Sort plans on one re-sampling of the particles: its kinds label the first only")
    c_now, baseline = goal.cost_now(p.positions, p.mask, seen.kinds, camera)
    initial = sample_pushes(key, seen.points, seen.valid, spec.planner)
    init = initial[0] if init is None else jnp.where(warm, init, initial[0])  # no warm start: sample 0 stands in
    positions, mask = (p.positions, p.mask) if resampled is None else resampled
    result = plan(dynamics(p.radius), goal_cost(goal, camera, spec.capacity, seen.kinds, baseline), positions,
                  mask, key, spec.planner, init=init, adam_steps=adam_steps, initial=initial)
    return c_now, result


def perceive_and_decide(obs, goal, key, init, warm, omega, adam_steps, kind=None, *, spec: DecisionSpec, dynamics,
                        camera):
    """One whole decision from a frame: h at ω (``perception.perceive`` with the first half of ``key``; with
    spec.planner.resamples R > 1, R - 1 more re-samplings of the same cloud, FPS from other starts), then ``decide``
    with the second. kind: perceive only this piece kind (None: every piece; KindGoals need every piece). Returns
    (Particles, c [], PlanResult)."""
    k_h, k_plan = jax.random.split(key)
    seen = perceive(obs, camera, omega, k_h, spec.capacity, max_points=spec.max_points, real_depth=spec.real_depth,
                    kind=kind, with_kinds=goal.labels_kinds)
    resampled = None
    if spec.planner.resamples > 1:
        keys = jax.random.split(jax.random.fold_in(k_h, 1), spec.planner.resamples - 1)
        more = jax.vmap(lambda k: cloud_particles(seen.points, seen.valid, obs.depth, omega, k, spec.capacity))(keys)
        p = seen.particles
        resampled = (jnp.concatenate([p.positions[None], more.positions]), jnp.concatenate([p.mask[None], more.mask]))
    c_now, result = decide(seen, goal, k_plan, init, warm, adam_steps, spec=spec, dynamics=dynamics, camera=camera,
                           resampled=resampled)
    return seen.particles, c_now, result


@functools.partial(jax.jit, static_argnames=("spec", "dynamics", "camera"))
def _decide_batch(obs, goal, key, init, warm, omega, adam_steps, kinds, *, spec, dynamics, camera):
    def one(obs, goal, key, init, warm, omega, adam_steps, kind):
        return perceive_and_decide(obs, goal, key, init, warm, omega, adam_steps, kind, spec=spec, dynamics=dynamics,
                                   camera=camera)

    return per_episode(one)(obs, goal, key, init, warm, omega, adam_steps, kinds)


def decide_batch(obs, goals, keys, init, warm, omega, adam_steps, kinds=None, *, spec: DecisionSpec, dynamics,
                 camera):
    """``perceive_and_decide`` over a batch of episodes (every argument with a leading axis [B], warm may be one for
    all) as one compiled function per spec (and model and camera), run in chunks of a fixed size
    (``chunks.in_chunks``), so an episode decides alike whatever runs beside it. init [B, T, 4] (used where warm);
    warm [] or [B], omega [B], adam_steps [B] and kinds [B] (None: every piece) are traced. The particles are
    checked: bad perception input raises a ValueError naming it (``perception.check_particles``). Returns
    (Particles [B], c [B], PlanResult [B])."""
    if kinds is not None and goals.labels_kinds:
        raise ValueError("KindGoals score every kind's particles: a decision perceives every piece (kinds=None)")
    omega = np.asarray(omega, np.int32)
    warm = jnp.broadcast_to(jnp.asarray(warm, bool), omega.shape)
    decide_chunk = functools.partial(_decide_batch, spec=spec, dynamics=dynamics, camera=camera)
    particles, c_now, result = in_chunks(decide_chunk, obs, goals, keys, jnp.asarray(init, jnp.float32), warm,
                                         jnp.asarray(omega), jnp.asarray(adam_steps, jnp.int32),
                                         None if kinds is None else jnp.asarray(kinds, jnp.int32))
    check_particles(particles, omega, spec.capacity, "perception failed in episodes")
    return particles, c_now, result


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


def fold(keys, n: int):
    """keys [B] each with ``n`` folded in (``jax.random.fold_in``): a step's keys, a sensor's, a plan draw's."""
    return jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, n)


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
