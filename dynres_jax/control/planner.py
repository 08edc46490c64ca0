"""The shooting planner of the paper (Algorithm 1): sample pushes, refine them by gradient descent through f.

Mapping to Algorithm 1 (and the reference code):

1. Sample M action sequences u_{1:T} (``sample_pushes``; by default each push passes near a random particle of the
   pile; ``starts="fixed"``: the reference's one set of pushes spread over the workspace, the same every plan). A warm
   start (the previous MPC step's plan, shifted) replaces sample 0.
2. For N steps, all M sequences at once (``jax.vmap``) inside one ``jax.lax.scan``: roll the dynamics out
   (``dynamics_fn``), score the final state with the task cost c (``cost_fn``), take an Adam step on the actions
   (optax) and project them back into the workspace (``project``; the reference clamps after every step).
3. Return the best sequence; MPC executes its first action.

The planner knows nothing about the task or the model: ``dynamics_fn(positions [N, 3], mask [N], actions [T, 4]) ->
[T, N, 3]`` and ``cost_fn(final_positions [N, 3], mask [N]) -> []`` are any differentiable JAX functions. With R
re-samplings of the particles (the reference evaluates every push on 30 of them), positions and mask get a leading
[R] axis and a sequence's cost is the mean over them; or, with ``vote`` (the reference's), each sample is refined on
each re-sampling separately and the plan is the sample that is best on the most re-samplings. A dynamics may do its
work that depends on the particles only once per plan rather than once per Adam step (``_prepared``: the learned
model's pair table, about 5 % of a step).

Compilation: ``plan`` is jitted with the functions passed as pytrees (``jax.tree_util.Partial``), so a
``Partial(f, arrays...)`` reuses one compiled plan for new arrays (model weights, resolution code, goal), while a
plain function or lambda is keyed by identity (a new lambda compiles again). The particle count N is the shape of
the positions: a bucket (``budget``), so a coarse ω plans on fewer slots than a fine one, and the ω valid particles
of a bucket are a mask (one compiled plan for every ω of a bucket). The Adam step count is traced (a
``lax.fori_loop`` that runs exactly that many steps, at most ``PlannerConfig.adam_steps``), so any step count, a time
budget's included, reuses the compiled plan; the config's seed is not part of the compiled function's key.

Units: metres. An action is (x_start, y_start, x_end, y_end) of the action space ``sim.pushes`` defines: it ends
within ±bound, starts there or (with a reach) outside a wall, and its length lies within [min_length, max_length].
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.tree_util import Partial

from dynres_jax.config import PushConfig, check_fields
from dynres_jax.errors import InputError
from dynres_jax.sim.pushes import check_reach, pile_points, project, sample_actions

STARTS = ("pile", "workspace", "fixed")  # where the planner's first pushes come from (PlannerConfig.starts)
FIXED_STARTS_SEED = 0  # the key of starts="fixed": one set of pushes for every plan
REFERENCE_LR_SHARE = 0.05 / 10.0  # the reference's Adam step (lr 0.05) as a share of its action range's width (±5)


@dataclass(frozen=True)
class PlannerConfig:
    """Static configuration of the planner.

    samples: M action sequences optimised at once (paper 20, reference demo 50).
    horizon: T pushes per sequence (paper 1).
    adam_steps: N Adam steps (paper 200); the most a plan may run (its history's length, static).
    lr: Adam learning rate in metres (the reference's 0.05 on its 1-unit bin, scaled to our 0.4 m bin).
    bound: pushes end within ±bound m, and start there unless outside a wall (PileEnv.action_bound; 0.181 m for
      coffee).
    reach: m, a push may start at ±reach, outside a wall (PileEnv.reach; ``sim.pushes``), and a share of the first
      samples does; None: every push starts within ±bound (no walls, or no pushes from beyond them).
    min_length, max_length: push length range in m (PushConfig).
    resamples: R re-samplings of the particles each sequence is scored on (mean cost); positions then carry a
      leading [R] axis when R > 1.
    vote: (R > 1) the reference's aggregation instead of the mean: every sample refined on each re-sampling alone
      (R copies), each re-sampling's best sample a vote, the plan the most voted sample's copy that scored best.
    starts: the first pushes (``STARTS``): "pile", through points near random particles (a share from beyond a wall
      with reach); "workspace", anywhere in the workspace, drawn every plan; "fixed", anywhere in the workspace, the
      same set every plan (the reference's fixed initial pushes; key FIXED_STARTS_SEED, no wall starts).
    spread: m, the radius of the disc around each chosen particle the "pile" pushes pass through.
    seed: PRNG seed used when ``plan`` gets key=None.
    """

    samples: int = 50
    horizon: int = 1
    adam_steps: int = 200
    lr: float = 0.02
    bound: float = 0.181
    reach: float | None = None
    min_length: float = PushConfig.min_length
    max_length: float = PushConfig.max_length
    resamples: int = 1
    vote: bool = False
    starts: str = "pile"
    spread: float = 0.03
    seed: int = 0

    def __post_init__(self):
        check_fields(self)
        if self.samples < 1:
            raise ValueError(f"PlannerConfig.samples (M) must be >= 1, got {self.samples}")
        if self.horizon < 1:
            raise ValueError(f"PlannerConfig.horizon (T) must be >= 1, got {self.horizon}")
        if self.adam_steps < 0:
            raise ValueError(f"PlannerConfig.adam_steps (N) must be >= 0, got {self.adam_steps}")
        if not self.lr > 0:
            raise ValueError(f"PlannerConfig.lr (Adam's step, m) must be > 0, got {self.lr}")
        if not self.spread > 0:
            raise ValueError(f"PlannerConfig.spread must be > 0 m, got {self.spread}")
        if self.resamples < 1:
            raise ValueError(f"PlannerConfig.resamples (R) must be >= 1, got {self.resamples}")
        if self.vote and self.resamples < 2:
            raise ValueError("PlannerConfig.vote needs resamples (R) >= 2: one re-sampling has nothing to vote on")
        if self.starts not in STARTS:
            raise ValueError(f"PlannerConfig.starts must be one of {', '.join(STARTS)}, got {self.starts!r}")
        if self.bound <= 0:
            raise ValueError(f"PlannerConfig.bound must be > 0 m, got {self.bound}")
        if not 0 < self.min_length <= self.max_length <= 2 * self.bound:
            raise ValueError(f"PlannerConfig push lengths must satisfy 0 < min_length <= max_length <= 2 * bound, got "
                             f"min_length={self.min_length}, max_length={self.max_length}, bound={self.bound}")
        check_reach(self.bound, self.reach, self.min_length, self.max_length)


def reference_lr(bound: float) -> float:
    """The reference's Adam step in our workspace (m): REFERENCE_LR_SHARE of the action range's width, 2 bound."""
    return REFERENCE_LR_SHARE * 2.0 * bound


def planner_config(env, **settings) -> PlannerConfig:
    """The planner's settings for pushes in ``env``'s bin (its action space: bound, reach, push lengths)."""
    push = env.config.push
    return PlannerConfig(bound=env.action_bound, reach=env.reach, min_length=push.min_length,
                         max_length=push.max_length, **settings)


# Error bits, one table with perception's (1-8) and the exported decision's (16, 32, 2048): each bit one cause.
NO_PARTICLES = 512  # PlanResult.error bit: a particle set with no valid particle
BAD_POSITIONS = 1024  # PlanResult.error bit: a valid particle's position is NaN or infinite
NOT_FINITE = 256  # PlanResult.error bit: the plan came out NaN or infinite (any other cause)
BAD_STEPS = 64  # PlanResult.error bit: adam_steps outside [0, PlannerConfig.adam_steps] (the exported decision's too)
BAD_START = 128  # PlanResult.error bit: the warm start (init) or the starting sequences (initial) are not finite
PLAN_ERRORS = {NO_PARTICLES: "no valid particle to plan with (the mask is all False)",
               BAD_POSITIONS: "positions of valid particles are NaN or infinite",
               BAD_START: "the warm start (init) or the starting sequences (initial) are NaN or infinite",
               BAD_STEPS: "adam_steps lies outside [0, PlannerConfig.adam_steps]",
               NOT_FINITE: "the plan is NaN or infinite"}


class PlanResult(NamedTuple):
    """best [T, 4]: the lowest-cost sequence seen (projected); best_cost []: its cost; costs [M] and actions
    [M, T, 4]: every sequence after the final step; history [PlannerConfig.adam_steps]: the best cost seen up to each
    step run, NaN past the steps run (one slot when PlannerConfig.adam_steps is 0). With a vote, all of these are the
    winning copy's re-sampling's (its cost on that re-sampling alone). error [] int32: 0, or bits of ``PLAN_ERRORS``
    (the checks ``plan`` makes before work, made again inside the computation so that they hold under jit and vmap);
    where it is not 0, best and best_cost are NaN: never a push that looks usable."""

    best: jax.Array
    best_cost: jax.Array
    costs: jax.Array
    history: jax.Array
    actions: jax.Array
    error: jax.Array | None = None


def _as_pytree_fn(fn):
    """A function as a jit argument: a ``Partial`` passes as is (its arrays traced), anything else is wrapped
    (keyed by identity)."""
    return fn if isinstance(fn, Partial) else Partial(fn)


def _batched(positions, mask, resamples):
    """positions [N, 3] or [R, N, 3], mask [N] or [R, N] -> ([R, N, 3] float32, [R, N] bool), R checked."""
    positions, mask = jnp.asarray(positions, jnp.float32), jnp.asarray(mask, bool)
    if positions.ndim == 2:
        positions, mask = positions[None], mask[None]
    if positions.ndim != 3 or positions.shape[-1] != 3 or mask.shape != positions.shape[:2]:
        raise ValueError(f"positions must be [N, 3] or [R, N, 3] with mask [N] or [R, N]; got {positions.shape} "
                         f"and {mask.shape}")
    if positions.shape[0] != resamples:
        raise ValueError(f"PlannerConfig.resamples is {resamples} but positions have {positions.shape[0]} "
                         "re-samplings (a leading [R] axis is needed when R > 1)")
    return positions, mask


def sample_pushes(key, points, valid, config: PlannerConfig):
    """The planner's M starting sequences [M, T, 4] m (``sample_actions``), as config.starts says: through random
    valid points [P, 3] (valid [P]) of the pile, anywhere in the workspace, or the fixed set (key ignored). ``plan``
    draws them through the particles; drawn through the perception cloud instead (``decision.decide``), they are the
    same for every ω: common random numbers."""
    c = config
    if c.starts == "fixed":
        key = jax.random.PRNGKey(FIXED_STARTS_SEED)
    k_points, k_actions = jax.random.split(key)
    shape = (c.samples, c.horizon)
    centre = pile_points(k_points, points, valid, shape) if c.starts == "pile" else None
    wall = None if c.reach is None or c.starts == "fixed" else pile_points(jax.random.fold_in(k_points, 1), points,
                                                                           valid, shape, c.reach)
    return sample_actions(k_actions, c.samples, c.horizon, c.bound, c.min_length, c.max_length, centre, c.spread,
                          None if c.starts == "fixed" else c.reach, wall)


def _check_particles(positions, mask, config: PlannerConfig) -> None:
    """InputError, before any work, for particles no plan can start from: positions not floating-point (metres),
    a valid one NaN or infinite or out of every push's reach (x or y beyond the pushes' ends, ±max(bound, reach),
    plus a push's length: millimetres or another frame's coordinates), or a particle set with no valid particle.
    Traced arguments are not checked."""
    if isinstance(positions, jax.core.Tracer) or isinstance(mask, jax.core.Tracer):
        return
    positions, mask = np.asarray(positions), np.asarray(mask)
    if not np.issubdtype(positions.dtype, np.floating):
        raise InputError(f"positions must be floating-point metres, got {positions.dtype}")
    if mask.shape != positions.shape[:-1]:
        return  # _batched names the shapes
    mask = mask.astype(bool)
    if not np.all(np.isfinite(positions[mask])):
        raise InputError("positions of valid particles are NaN or infinite")
    reach = max(config.bound, config.reach or 0.0) + config.max_length
    far = np.abs(positions[mask][:, :2]).max(initial=0.0)
    if far > reach:
        raise InputError(f"a valid particle lies {far:g} m from the workspace centre in x or y, beyond any push's "
                         f"reach (±{reach:g} m): positions are metres in the table frame (origin at the bin's centre)")
    if not np.all(mask.reshape(-1, mask.shape[-1]).any(axis=-1)):
        raise InputError("no valid particle to plan with (the mask is all False)")


def _prepared(dynamics_fn, positions, mask):
    """The per-plan hook: (dynamics taking a context, contexts [R, ...]) for positions [R, N, 3] and mask [R, N]. A
    dynamics ``Partial(fn, *args)`` whose fn has a ``prepare(*args, positions [N, 3], mask [N])`` method gets its
    context (work that depends on the particles only, such as ``registry.learned_dynamics``' pair table) computed here,
    once per plan, and is called as ``fn(*args, positions, mask, actions, context)``; any other dynamics ignores the
    context (None)."""
    prepare = getattr(dynamics_fn.func, "prepare", None)
    if prepare is None:
        return (lambda p, m, seq, ctx: dynamics_fn(p, m, seq)), None
    context = jax.vmap(lambda p, m: prepare(*dynamics_fn.args, p, m, **dynamics_fn.keywords))(positions, mask)
    return dynamics_fn, context


def _refine(dynamics_fn, cost_fn, actions, positions, mask, context, adam_steps, config):
    """Adam steps on the M sequences actions [M, T, 4], each scored by its mean cost over the re-samplings positions
    [R, N, 3], mask [R, N] (context: ``_prepared``'s, [R, ...]): (PlanResult, the index of the best sample seen)."""
    c = config

    def objective(seq):  # [T, 4] -> mean over the R re-samplings of the final-state cost
        final = jax.vmap(lambda p, m, ctx: dynamics_fn(p, m, seq, ctx)[-1])(positions, mask, context)
        return jnp.mean(jax.vmap(cost_fn)(final, mask)).astype(jnp.float32)  # float32 under JAX_ENABLE_X64 too

    value_and_grad = jax.vmap(jax.value_and_grad(objective))
    optimiser = optax.adam(c.lr)

    def keep_best(best, best_cost, best_index, actions, costs):
        i = jnp.argmin(costs).astype(jnp.int32)  # the carry's int32 also under JAX_ENABLE_X64 (argmin's is int64)
        better = costs[i] < best_cost
        return (jnp.where(better, actions[i], best), jnp.where(better, costs[i], best_cost),
                jnp.where(better, i, best_index))

    def step(i, carry):
        actions, opt_state, best, history = carry
        costs, grads = value_and_grad(actions)
        best = keep_best(*best, actions, costs)
        updates, opt_state = optimiser.update(grads, opt_state, actions)
        actions = project(optax.apply_updates(actions, updates), c.bound, c.min_length, c.max_length,
                          c.reach)
        return actions, opt_state, best, history.at[i].set(best[1])

    best = (actions[0], jnp.asarray(jnp.inf, jnp.float32), jnp.asarray(0, jnp.int32))
    carry = (actions, optimiser.init(actions), best,
             jnp.full(max(c.adam_steps, 1), jnp.nan, jnp.float32))  # one slot at least, so the loop body traces
    adam_steps = jnp.clip(jnp.asarray(adam_steps, jnp.int32), 0, c.adam_steps)
    actions, _, best, history = jax.lax.fori_loop(0, adam_steps, step, carry)
    costs = jax.vmap(objective)(actions)
    best, best_cost, best_index = keep_best(*best, actions, costs)
    return PlanResult(best, best_cost, costs, history, actions), best_index


def _plan(dynamics_fn, cost_fn, positions, mask, key, init, initial, adam_steps, config):
    """The jitted planner; see ``plan``. positions [R, N, 3], mask [R, N], init [T, 4] or None, initial [M, T, 4] or
    None, adam_steps [] int32 (may be traced, at most config.adam_steps)."""
    c = config
    actions = sample_pushes(key, positions[0], mask[0], c) if initial is None else project(
        initial, c.bound, c.min_length, c.max_length, c.reach)
    if init is not None:
        actions = actions.at[0].set(project(init, c.bound, c.min_length, c.max_length, c.reach))

    starts_finite = jnp.array(True)
    for x in (init, initial):
        if x is not None:
            starts_finite &= jnp.all(jnp.isfinite(x))
    inputs_bad = (jnp.where(starts_finite, 0, BAD_START)
                  | jnp.where((adam_steps < 0) | (adam_steps > c.adam_steps), BAD_STEPS, 0))
    dynamics_fn, context = _prepared(dynamics_fn, positions, mask)
    if not c.vote:
        return _checked(_refine(dynamics_fn, cost_fn, actions, positions, mask, context, adam_steps, c)[0],
                        positions, mask, inputs_bad)
    one = lambda x: x[None]  # noqa: E731  one re-sampling as a set of one
    plans, best_index = jax.vmap(lambda p, m, ctx: _refine(dynamics_fn, cost_fn, actions, one(p), one(m),
                                                           jax.tree.map(one, ctx), adam_steps, c))(
        positions, mask, context)
    votes = jnp.zeros(c.samples, jnp.int32).at[best_index].add(1)  # each re-sampling votes for its best sample
    r = jnp.argmin(jnp.where(best_index == jnp.argmax(votes), plans.best_cost, jnp.inf))  # the winner's best copy
    return _checked(jax.tree.map(lambda x: x[r], plans), positions, mask, inputs_bad)


def _checked(result: PlanResult, positions, mask, inputs_bad) -> PlanResult:
    """``result`` with its error bits (PlanResult; ``inputs_bad``: the start and step bits found before refining);
    best and best_cost NaN where any is set."""
    error = (jnp.where(~jnp.all(jnp.any(mask, axis=-1)), NO_PARTICLES, 0)
             | jnp.where(jnp.all(jnp.isfinite(positions) | ~mask[..., None]), 0, BAD_POSITIONS) | inputs_bad)
    error = error | jnp.where((error == 0) & ~(jnp.all(jnp.isfinite(result.best)) & jnp.isfinite(result.best_cost)),
                              NOT_FINITE, 0)
    ok = error == 0
    return result._replace(best=jnp.where(ok, result.best, jnp.nan), best_cost=jnp.where(ok, result.best_cost, jnp.nan),
                           error=error.astype(jnp.int32))


_plan_jit = jax.jit(_plan, static_argnames="config")


def plan(dynamics_fn, cost_fn, positions, mask, key, config: PlannerConfig = PlannerConfig(), init=None, *,
         adam_steps=None, initial=None) -> PlanResult:
    """Optimise M action sequences for one MPC step (paper Algorithm 1); returns a ``PlanResult``.

    dynamics_fn(positions [N, 3], mask [N], actions [T, 4]) -> [T, N, 3] m; cost_fn(final [N, 3], mask [N]) -> [].
    positions [N, 3] m and mask [N] bool, or [R, N, 3] and [R, N] with config.resamples = R; N is the bucket.
    key: a jax.random key (None: PRNGKey(config.seed)). init [T, 4]: warm start, replaces sample 0 (projected).
    initial: optional [M, T, 4], the starting sequences (projected) instead of ``sample_pushes`` through the first
    re-sampling's particles.
    adam_steps: an int or a traced int32 (``budget.adam_steps``; vmap it over episodes), within
    [0, config.adam_steps]; default config.adam_steps. The best is the lowest-cost sequence evaluated at any step, so
    its cost never exceeds the warm start's. Out of range, or a non-finite init or initial: ValueError where they are
    concrete, an error bit (``PLAN_ERRORS``) where traced.
    """
    if not isinstance(config, PlannerConfig):
        raise InputError(f"config must be a PlannerConfig, got {type(config).__name__}")
    _check_particles(positions, mask, config)
    positions, mask = _batched(positions, mask, config.resamples)
    if adam_steps is None:
        adam_steps = config.adam_steps
    concrete = not isinstance(adam_steps, jax.core.Tracer)
    if concrete and not 0 <= int(np.min(adam_steps)) <= int(np.max(adam_steps)) <= config.adam_steps:
        raise ValueError(f"adam_steps={adam_steps} must lie in [0, PlannerConfig.adam_steps={config.adam_steps}]")
    if init is not None:
        init = jnp.asarray(init, jnp.float32)
        if init.shape != (config.horizon, 4):
            raise ValueError(f"init must be [T, 4] = [{config.horizon}, 4], got {init.shape}")
    if initial is not None:
        initial = jnp.asarray(initial, jnp.float32)
        if initial.shape != (config.samples, config.horizon, 4):
            raise ValueError(f"initial must be [M, T, 4] = [{config.samples}, {config.horizon}, 4], got "
                             f"{initial.shape}")
    for name, x in (("init", init), ("initial", initial)):
        if x is not None and not isinstance(x, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(x))):
            raise ValueError(f"{name} (the warm start) holds NaN or infinite values")
    if key is None:
        key = jax.random.PRNGKey(config.seed)
    return _plan_jit(_as_pytree_fn(dynamics_fn), _as_pytree_fn(cost_fn), positions, mask, key, init, initial,
                     jnp.asarray(adam_steps, jnp.int32), config=replace(config, seed=0))


__all__ = ["BAD_POSITIONS", "BAD_START", "BAD_STEPS", "NOT_FINITE", "NO_PARTICLES", "PLAN_ERRORS", "PlanResult",
           "PlannerConfig", "plan",
           "planner_config", "reference_lr", "sample_pushes"]
