"""The shooting planner (paper Algorithm 1): projection, sampling, optimisation through a stand-in dynamics, padding
and re-sampling invariants, a real model end to end (float32 and bfloat16 edges), warm start, traced step counts and
configuration errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from jax.tree_util import Partial

from dynres_jax.control.planner import PlannerConfig, plan
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig, resolution_code, rollout
from dynres_jax.models.graph import sweep_displacement
from dynres_jax.models.registry import learned_dynamics
from dynres_jax.sim.pushes import ZERO_LENGTH_DIRECTION, project, sample_actions

BOUND, MIN_LEN, MAX_LEN = 0.181, 0.01, 0.25
TARGET = jnp.array([0.05, 0.0])
CFG = PlannerConfig(samples=16, adam_steps=40, bound=BOUND)


def sweep_dynamics(positions, mask, actions):
    """Stand-in f: positions [N, 3], mask [N], actions [T, 4] -> [T, N, 3] through the sweep heuristic."""

    def step(current, action):
        nxt = current + sweep_displacement(current, mask, action, 0.04)
        return nxt, nxt

    return jax.lax.scan(step, positions, actions)[1]


def centroid_cost(final, mask):
    """Squared distance (m²) of the valid particles' centroid (x, y) to TARGET."""
    w = mask.astype(jnp.float32)[:, None]
    centre = jnp.sum(final[:, :2] * w, axis=0) / jnp.sum(w)
    return jnp.sum(jnp.square(centre - TARGET))


def pile(key, n=12, centre=(-0.05, 0.0)):
    """A small pile [n, 3] m around centre, particles at z = 5 mm, all valid."""
    xy = jax.random.normal(key, (n, 2)) * 0.01 + jnp.asarray(centre)
    return jnp.concatenate([xy, jnp.full((n, 1), 0.005)], axis=-1), jnp.ones(n, bool)


def lengths(actions):
    return np.hypot(actions[..., 2] - actions[..., 0], actions[..., 3] - actions[..., 1])


def test_project_bounds_lengths_idempotent():
    raw = jax.random.uniform(jax.random.PRNGKey(0), (500, 4), minval=-0.5, maxval=0.5)
    raw = raw.at[:50, 2:].set(raw[:50, :2])  # zero-length pushes
    raw = raw.at[50:100, 2:].set(raw[50:100, :2] + 1e-4)  # very short pushes
    out = np.asarray(project(raw, BOUND, MIN_LEN, MAX_LEN))
    assert np.all(np.abs(out) <= BOUND + 1e-6)
    assert np.all((lengths(out) >= MIN_LEN - 1e-6) & (lengths(out) <= MAX_LEN + 1e-6))
    np.testing.assert_allclose(project(out, BOUND, MIN_LEN, MAX_LEN), out, atol=1e-6)
    # A valid action is untouched; a zero-length push points along the documented direction.
    valid = jnp.array([0.01, -0.02, 0.1, 0.05])
    np.testing.assert_allclose(project(valid, BOUND, MIN_LEN, MAX_LEN), valid, atol=1e-7)
    np.testing.assert_allclose((out[0, 2:] - out[0, :2]) / MIN_LEN, ZERO_LENGTH_DIRECTION, atol=1e-5)
    # Too long: the start is kept, the end pulled in along the direction.
    long = project(jnp.array([-0.1, 0.0, 0.2, 0.0]), BOUND, MIN_LEN, MAX_LEN)
    np.testing.assert_allclose(long, [-0.1, 0.0, -0.1 + MAX_LEN, 0.0], atol=1e-7)


def test_project_gradient_finite_at_zero_length():
    for a in (jnp.zeros(4), jnp.array([0.1, 0.1, 0.1, 0.1]), jnp.array([0.3, -0.3, 0.3, -0.3])):
        grad = jax.grad(lambda x: jnp.sum(jnp.square(project(x, BOUND, MIN_LEN, MAX_LEN))))(a)
        assert np.all(np.isfinite(grad))


def test_sample_actions_inside_workspace_and_through_centre():
    key = jax.random.PRNGKey(3)
    anywhere = np.asarray(sample_actions(key, 64, 2, BOUND, MIN_LEN, MAX_LEN))
    assert anywhere.shape == (64, 2, 4)
    assert np.all(np.abs(anywhere) <= BOUND + 1e-6)
    assert np.all((lengths(anywhere) >= MIN_LEN - 1e-6) & (lengths(anywhere) <= MAX_LEN + 1e-6))
    near = np.asarray(sample_actions(key, 64, 1, BOUND, MIN_LEN, MAX_LEN, centre_xy=jnp.zeros(2), spread=0.03))
    start, end = near[..., :2], near[..., 2:]
    d = end - start
    s = np.clip(np.sum(-start * d, -1) / np.sum(d * d, -1), 0, 1)  # closest point of each push to the centre
    assert np.all(np.linalg.norm(start + s[..., None] * d, axis=-1) <= 0.03 + 1e-5)


def test_plan_reduces_cost_and_gradient_beats_sampling():
    key = jax.random.PRNGKey(1)
    positions, mask = pile(key)
    initial = float(centroid_cost(positions, mask))
    result = plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG)
    sampled_only = plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG, adam_steps=0)
    assert result.best.shape == (1, 4) and result.costs.shape == (16,) and result.actions.shape == (16, 1, 4)
    assert result.history.shape == (40,) and np.all(np.isnan(np.asarray(sampled_only.history)))
    assert float(result.best_cost) <= 0.5 * initial
    np.testing.assert_allclose(centroid_cost(sweep_dynamics(positions, mask, result.best)[-1], mask),
                               result.best_cost, rtol=1e-4, atol=1e-9)
    history = np.asarray(result.history)
    assert np.all(np.diff(history) <= 0) and history[-1] < 0.5 * history[0]
    assert float(result.best_cost) < 0.5 * float(sampled_only.best_cost)
    assert np.all(np.abs(np.asarray(result.actions)) <= BOUND + 1e-6)


def test_masked_garbage_particles_do_not_change_the_plan():
    key = jax.random.PRNGKey(2)
    positions, mask = pile(key)
    garbage = jax.random.uniform(jax.random.PRNGKey(9), (4, 3), minval=-0.15, maxval=0.15)
    padded = jnp.concatenate([positions[:4], garbage, positions[4:]])
    padded_mask = jnp.concatenate([mask[:4], jnp.zeros(4, bool), mask[4:]])
    a = plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG)
    b = plan(sweep_dynamics, centroid_cost, padded, padded_mask, key, CFG)
    np.testing.assert_allclose(a.best, b.best, atol=1e-5)
    np.testing.assert_allclose(a.costs, b.costs, atol=1e-7)


def test_resamples_equal_mean_cost_by_hand():
    key = jax.random.PRNGKey(4)
    (p0, m0), (p1, m1) = pile(jax.random.PRNGKey(5), n=8), pile(jax.random.PRNGKey(6), n=8)
    # Sampled anywhere: through-the-pile sampling draws from the first re-sampling, which the by-hand scene lacks.
    config = PlannerConfig(samples=8, adam_steps=20, bound=BOUND, resamples=2, starts="workspace")
    result = plan(sweep_dynamics, centroid_cost, jnp.stack([p0, p1]), jnp.stack([m0, m1]), key, config)

    # By hand: both re-samplings side by side in one scene (the sweep acts per particle), cost = mean of the two.
    def mean_cost(final, mask):
        return 0.5 * (centroid_cost(final[:8], mask[:8]) + centroid_cost(final[8:], mask[8:]))

    by_hand = plan(sweep_dynamics, mean_cost, jnp.concatenate([p0, p1]), jnp.concatenate([m0, m1]), key,
                   PlannerConfig(samples=8, adam_steps=20, bound=BOUND, starts="workspace"))
    np.testing.assert_allclose(result.best, by_hand.best, atol=1e-5)
    np.testing.assert_allclose(result.costs, by_hand.costs, rtol=1e-4, atol=1e-8)
    final = [sweep_dynamics(p, m, result.actions[0])[-1] for p, m in ((p0, m0), (p1, m1))]
    np.testing.assert_allclose(result.costs[0], 0.5 * (centroid_cost(final[0], m0) + centroid_cost(final[1], m1)),
                               rtol=1e-4, atol=1e-8)


def test_vote_picks_the_sample_best_on_most_resamplings_by_hand():
    """No Adam step: each re-sampling votes for its lowest-cost first sample (NumPy, from each (sample, re-sampling)
    cost computed alone); the plan is the most voted sample (the first on a tie), from the re-sampling where it scored
    lowest."""
    key = jax.random.PRNGKey(7)
    piles = [pile(jax.random.PRNGKey(10 + r), n=8, centre=(-0.08 + 0.04 * r, 0.02 * (r % 2))) for r in range(5)]
    positions, masks = jnp.stack([p for p, _ in piles]), jnp.stack([m for _, m in piles])
    config = PlannerConfig(samples=6, adam_steps=0, bound=BOUND, resamples=5, vote=True, starts="workspace")
    result = plan(sweep_dynamics, centroid_cost, positions, masks, key, config)
    first = np.asarray(plan(sweep_dynamics, centroid_cost, positions[0], masks[0], key,
                            PlannerConfig(samples=6, adam_steps=0, bound=BOUND, starts="workspace")).actions)
    costs = np.array([[float(centroid_cost(sweep_dynamics(p, m, jnp.asarray(a))[-1], m)) for a in first]
                      for p, m in piles])  # [R, M]
    votes = np.bincount(costs.argmin(axis=1), minlength=6)
    winner = int(np.argmax(votes))
    voters = [r for r in range(5) if costs[r].argmin() == winner]
    r_best = min(voters, key=lambda r: costs[r, winner])
    np.testing.assert_allclose(np.asarray(result.best), first[winner], atol=1e-6)
    np.testing.assert_allclose(float(result.best_cost), costs[r_best, winner], rtol=1e-5)
    np.testing.assert_allclose(np.asarray(result.costs), costs[r_best], rtol=1e-5)
    assert len(set(costs.argmin(axis=1).tolist())) > 1  # the re-samplings disagree: the vote decides


def test_vote_over_identical_resamplings_is_the_plan_on_one():
    """Each copy is refined on its own re-sampling alone: with every re-sampling the same, every copy follows the
    plan on one re-sampling, Adam steps included."""
    positions, mask = pile(jax.random.PRNGKey(8))
    key = jax.random.PRNGKey(9)
    one = plan(sweep_dynamics, centroid_cost, positions, mask, key, PlannerConfig(samples=8, adam_steps=15,
                                                                                  bound=BOUND))
    voted = plan(sweep_dynamics, centroid_cost, jnp.stack([positions] * 3), jnp.stack([mask] * 3), key,
                 PlannerConfig(samples=8, adam_steps=15, bound=BOUND, resamples=3, vote=True))
    np.testing.assert_allclose(np.asarray(voted.best), np.asarray(one.best), atol=1e-6)
    np.testing.assert_allclose(np.asarray(voted.history), np.asarray(one.history), rtol=1e-4, atol=1e-9)
    with pytest.raises(ValueError, match="vote needs resamples"):
        PlannerConfig(vote=True)


def test_fixed_starts_are_one_set_over_the_workspace():
    """starts="fixed" gives the same first pushes for any key and any pile, spread over the whole workspace (every
    quadrant); "workspace" draws new ones per key; "pile" passes near the particles."""
    from dynres_jax.control.planner import sample_pushes

    points, valid = pile(jax.random.PRNGKey(0), n=30, centre=(0.1, 0.1))
    other, _ = pile(jax.random.PRNGKey(1), n=30, centre=(-0.1, -0.1))
    fixed = PlannerConfig(samples=64, bound=BOUND, starts="fixed", reach=0.2)
    a = np.asarray(sample_pushes(jax.random.PRNGKey(2), points, valid, fixed))
    b = np.asarray(sample_pushes(jax.random.PRNGKey(3), other, valid, fixed))
    np.testing.assert_array_equal(a, b)
    assert np.all(np.abs(a) <= BOUND + 1e-6)  # no start from beyond a wall
    mid = (a[..., :2] + a[..., 2:]) / 2
    assert {(bool(x > 0), bool(y > 0)) for x, y in mid.reshape(-1, 2)} == {(i, j) for i in (0, 1) for j in (0, 1)}
    workspace = PlannerConfig(samples=64, bound=BOUND, starts="workspace")
    assert not np.allclose(sample_pushes(jax.random.PRNGKey(2), points, valid, workspace),
                           sample_pushes(jax.random.PRNGKey(3), points, valid, workspace))
    near = np.asarray(sample_pushes(jax.random.PRNGKey(2), points, valid, PlannerConfig(samples=64, bound=BOUND)))
    assert np.mean(np.linalg.norm((near[..., :2] + near[..., 2:]) / 2 - 0.1, axis=-1)) < np.mean(
        np.linalg.norm(mid - 0.1, axis=-1))
    with pytest.raises(ValueError, match="starts must be one of"):
        PlannerConfig(starts="grid")


def _model_dynamics(graphdef, state, code, positions, mask, actions):
    return rollout(graphdef, state, positions, mask, actions, code)


@pytest.mark.slow  # about 25-40 s on a 2-core CPU: CI's second tier
def test_real_dynamics_end_to_end():
    graphdef, state = nnx.split(Dynamics(DynamicsConfig(hidden=16), rngs=nnx.Rngs(0)))
    positions, mask = pile(jax.random.PRNGKey(7), n=12)
    mask = mask.at[-3:].set(False)
    config = PlannerConfig(samples=4, horizon=2, adam_steps=3, bound=BOUND)
    dynamics = Partial(_model_dynamics, graphdef, state, resolution_code(0.01))
    result = plan(dynamics, centroid_cost, positions, mask, jax.random.PRNGKey(0), config)
    best = np.asarray(result.best)
    assert best.shape == (2, 4) and np.all(np.isfinite(best)) and np.isfinite(float(result.best_cost))
    assert np.all(np.abs(best) <= BOUND + 1e-6)
    assert np.all((lengths(best) >= MIN_LEN - 1e-6) & (lengths(best) <= MAX_LEN + 1e-6))


@pytest.mark.slow
def test_pair_table_prepared_once_per_plan_plans_the_same():
    """``learned_dynamics`` builds each re-sampling's pair table once per plan (the planner's ``prepare`` hook, outside
    the step loop); the plan equals one through the same model that builds no table (per-edge codes), to float
    rounding, over two re-samplings with padding."""
    model = Dynamics(DynamicsConfig(hidden=16), rngs=nnx.Rngs(0))
    piles = [pile(jax.random.PRNGKey(s), n=12) for s in (7, 8)]
    positions, mask = jnp.stack([p for p, _ in piles]), jnp.stack([m for _, m in piles]).at[1, -3:].set(False)
    config = PlannerConfig(samples=4, horizon=2, adam_steps=3, bound=BOUND, resamples=2)
    plain = Partial(_model_dynamics, *nnx.split(model), resolution_code(0.01))
    a, b = (plan(d, centroid_cost, positions, mask, jax.random.PRNGKey(0), config)
            for d in (plain, learned_dynamics(model)(0.01)))
    np.testing.assert_allclose(b.actions, a.actions, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(b.costs, a.costs, rtol=1e-4, atol=1e-9)


@pytest.mark.slow  # about 25-40 s on a 2-core CPU: CI's second tier
def test_bfloat16_edges_plan():
    """The MPC's option ``learned_dynamics(model, "bfloat16")``: the sampled pushes cost what float32 says to within
    2 % (measured: under 1 %), the plan's pushes are in bounds and garbage in the masked slots changes nothing; dtypes
    are named and checked, and each dtype is one function to the compile cache. (The random model throws the pile
    metres, so over two pushes or a few Adam steps float32 and bfloat16 part ways by more: the benchmark compares
    full plans on the trained model.)"""
    model = Dynamics(DynamicsConfig(hidden=16), rngs=nnx.Rngs(0))
    positions, mask = pile(jax.random.PRNGKey(7), n=12)
    mask = mask.at[-3:].set(False)
    config = PlannerConfig(samples=8, adam_steps=3, bound=BOUND)
    key = jax.random.PRNGKey(0)
    sampled = [plan(learned_dynamics(model, d)(0.01), centroid_cost, positions, mask, key, config, adam_steps=0).costs
               for d in ("float32", "bfloat16")]
    np.testing.assert_allclose(sampled[1], sampled[0], rtol=0.02)
    dynamics = learned_dynamics(model, "bfloat16")(0.01)
    best = np.asarray(plan(dynamics, centroid_cost, positions, mask, key, config).best)
    assert best.shape == (1, 4) and np.all(np.isfinite(best)) and np.all(np.abs(best) <= BOUND + 1e-6)
    assert np.all((lengths(best) >= MIN_LEN - 1e-6) & (lengths(best) <= MAX_LEN + 1e-6))
    garbage = positions.at[-3:].set(1e3)  # finite: centroid_cost weights by the mask (NaN: test_dynamics)
    np.testing.assert_array_equal(plan(dynamics, centroid_cost, garbage, mask, key, config).best, best)
    same = [jax.tree.structure(learned_dynamics(model, d)(r)) for d, r in (("bfloat16", 0.01), (jnp.bfloat16, 0.02))]
    assert same[0] == same[1] != jax.tree.structure(learned_dynamics(model)(0.01))
    with pytest.raises(ValueError, match="edge_dtype"):
        learned_dynamics(model, "float16")
    with pytest.raises(ValueError, match="Dynamics"):
        learned_dynamics(nnx.Linear(1, 1, rngs=nnx.Rngs(0)), "bfloat16")


def test_warm_start():
    key = jax.random.PRNGKey(1)
    positions, mask = pile(key)
    init = jnp.array([[-0.09, 0.0, 0.04, 0.0]])  # sweeps the whole pile to x = 0.05, onto the target
    result = plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG, init=init, adam_steps=0)
    np.testing.assert_allclose(result.best, project(init, BOUND, MIN_LEN, MAX_LEN), atol=1e-7)
    np.testing.assert_allclose(result.actions[0], init, atol=1e-7)
    refined = plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG, init=init)
    assert float(refined.best_cost) <= float(result.best_cost)
    with pytest.raises(ValueError, match="init"):
        plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG, init=jnp.zeros((2, 4)))


@pytest.mark.slow  # about 25-40 s on a 2-core CPU: CI's second tier
def test_traced_step_counts_equal_plans_of_that_many_steps():
    """Step counts traced and vmapped (one compiled plan of at most CFG.adam_steps) give exactly the plans whose config
    runs that many steps (each compiled alone); the history past the steps run is NaN."""
    positions, mask = pile(jax.random.PRNGKey(4))
    key = jax.random.PRNGKey(5)
    counts = jnp.array([7, 0, 40])  # a part of the steps, none, all
    batched = jax.vmap(lambda n: plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG, adam_steps=n))(counts)
    for i, n in enumerate(counts.tolist()):
        alone = plan(sweep_dynamics, centroid_cost, positions, mask, key, PlannerConfig(samples=16, adam_steps=n,
                                                                                        bound=BOUND))
        np.testing.assert_allclose(np.asarray(batched.best[i]), np.asarray(alone.best), atol=1e-6)
        np.testing.assert_allclose(float(batched.best_cost[i]), float(alone.best_cost), rtol=1e-6)
        np.testing.assert_allclose(np.asarray(batched.actions[i]), np.asarray(alone.actions), atol=1e-6)
        np.testing.assert_allclose(np.asarray(batched.history[i, :n]), np.asarray(alone.history[:n]), rtol=1e-6)
        assert np.all(np.isnan(np.asarray(batched.history[i, n:])))
    assert plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG, adam_steps=7).history.shape == (40,)
    with pytest.raises(ValueError, match="steps=41"):
        plan(sweep_dynamics, centroid_cost, positions, mask, key, CFG, adam_steps=41)


def test_config_errors():
    with pytest.raises(ValueError, match="samples"):
        PlannerConfig(samples=0)
    with pytest.raises(ValueError, match="horizon"):
        PlannerConfig(horizon=0)
    with pytest.raises(ValueError, match="min_length"):
        PlannerConfig(min_length=0.3, max_length=0.2)
    with pytest.raises(ValueError, match="max_length"):
        PlannerConfig(bound=0.1, max_length=0.25)
    with pytest.raises(ValueError, match="resamples"):
        PlannerConfig(resamples=0)
    positions, mask = pile(jax.random.PRNGKey(1), n=4)
    with pytest.raises(ValueError, match="resamples"):
        plan(sweep_dynamics, centroid_cost, positions, mask, None, PlannerConfig(samples=2, adam_steps=1, resamples=2))


def test_particles_no_plan_can_start_from_are_refused_by_name():
    """NaN or infinite valid positions, no valid particle, integer positions (millimetres?), a valid particle out of
    every push's reach (metres taken for another unit or frame) and a config that is not a PlannerConfig are one-line
    InputErrors before any work; a particle at the reach itself and garbage in masked slots stay allowed."""
    from dynres_jax.errors import InputError

    positions, mask = pile(jax.random.PRNGKey(2), n=6)
    small = PlannerConfig(samples=2, adam_steps=1, bound=BOUND)
    cases = {"NaN or infinite": np.asarray(positions).copy(), "no valid particle": positions,
             "floating-point metres": np.round(np.asarray(positions) * 1000).astype(np.int32),
             "beyond any push's reach": np.asarray(positions).copy()}
    cases["NaN or infinite"][0, 0] = np.nan
    reach = small.bound + small.max_length
    cases["beyond any push's reach"][0, 1] = reach + 0.001  # a particle a millimetre past the farthest push
    for match, p in cases.items():
        m = np.zeros_like(mask) if match == "no valid particle" else mask
        with pytest.raises(InputError, match=match):
            plan(sweep_dynamics, centroid_cost, p, m, None, small)
    with pytest.raises(InputError, match="must be a PlannerConfig"):
        plan(sweep_dynamics, centroid_cost, positions, mask, None, {"samples": 2})
    edge = np.asarray(positions).copy()
    edge[0, 1] = -reach
    assert np.isfinite(float(plan(sweep_dynamics, centroid_cost, edge, mask, None, small).best_cost))
    mask = np.asarray(mask).copy()
    mask[-2:] = False
    garbage = np.asarray(positions).copy()
    garbage[~mask] = 7.0  # masked slots are not checked (the learned model ignores them, even NaN)
    assert np.isfinite(float(plan(sweep_dynamics, centroid_cost, garbage, mask, None, small).best_cost))


def test_under_vmap_bad_particles_give_an_error_and_no_usable_push():
    """Traced through jit and vmap (where ``plan`` cannot refuse before work), a set with a NaN valid position or no
    valid particle comes back with its PlanResult.error bit and a NaN push and cost, never a finite push of cost 0;
    its neighbours in the batch plan exactly as alone, error 0."""
    from dynres_jax.control.planner import BAD_POSITIONS, NO_PARTICLES

    small = PlannerConfig(samples=4, adam_steps=3, bound=BOUND)
    positions, mask = pile(jax.random.PRNGKey(2), n=6)
    batch_p = jnp.stack([positions, positions.at[1, 0].set(jnp.nan), positions])
    batch_m = jnp.stack([mask, mask, jnp.zeros_like(mask)])
    keys = jax.random.split(jax.random.PRNGKey(5), 3)
    out = jax.jit(jax.vmap(lambda p, m, k: plan(sweep_dynamics, centroid_cost, p, m, k, small)))(batch_p, batch_m,
                                                                                                 keys)
    assert out.error.tolist() == [0, BAD_POSITIONS, NO_PARTICLES]
    assert np.all(np.isnan(np.asarray(out.best[1:]))) and np.all(np.isnan(np.asarray(out.best_cost[1:])))
    alone = plan(sweep_dynamics, centroid_cost, positions, mask, keys[0], small)
    assert int(alone.error) == 0 and np.isfinite(float(alone.best_cost))
    np.testing.assert_allclose(out.best[0], alone.best, atol=1e-6)
    np.testing.assert_allclose(out.best_cost[0], alone.best_cost, rtol=1e-5)


def test_a_bad_warm_start_or_step_count_is_refused_and_under_vmap_flagged():
    """A non-finite warm start, an Adam step count outside [0, N] and a non-positive learning rate are ValueErrors
    before work; traced (jit and vmap), the warm start and the step count come back as their own error bits with a
    NaN push, while a neighbour in the batch plans exactly as alone."""
    from dynres_jax.control.planner import BAD_START, BAD_STEPS

    for field in ("lr", "spread"):
        with pytest.raises(ValueError, match=field):
            PlannerConfig(**{field: -1.0})
    small = PlannerConfig(samples=4, adam_steps=3, bound=BOUND)
    positions, mask = pile(jax.random.PRNGKey(2), n=6)
    warm = jnp.array([[0.0, 0.05, 0.0, -0.05]])
    with pytest.raises(ValueError, match="warm start"):
        plan(sweep_dynamics, centroid_cost, positions, mask, None, small, init=warm.at[0, 1].set(jnp.nan))
    with pytest.raises(ValueError, match="adam_steps"):
        plan(sweep_dynamics, centroid_cost, positions, mask, None, small, adam_steps=4)
    inits = jnp.stack([warm, warm.at[0, 1].set(jnp.nan), warm])
    steps = jnp.array([3, 3, 7], jnp.int32)
    keys = jax.random.split(jax.random.PRNGKey(5), 3)
    out = jax.jit(jax.vmap(lambda i, s, k: plan(sweep_dynamics, centroid_cost, positions, mask, k, small, init=i,
                                                adam_steps=s)))(inits, steps, keys)
    assert out.error.tolist() == [0, BAD_START, BAD_STEPS]
    assert np.all(np.isnan(np.asarray(out.best[1:]))) and np.all(np.isnan(np.asarray(out.best_cost[1:])))
    alone = plan(sweep_dynamics, centroid_cost, positions, mask, keys[0], small, init=warm)
    np.testing.assert_allclose(out.best[0], alone.best, atol=1e-6)


def test_every_error_bit_is_one_cause():
    """Perception's, the planner's and the exported decision's error bits are distinct powers of two (the export's
    table once gave 'no table' and 'the plan is NaN' the same bit, and its sidecar lost one of the two texts)."""
    from dynres_jax import export, perception
    from dynres_jax.control import planner

    bits = {name: getattr(m, name) for m in (perception, planner, export)
            for name in ("NO_DEPTH", "EMPTY_FOREGROUND", "BAD_OMEGA", "TOO_FEW_POINTS", "GOAL_EMPTY", "GOAL_FULL",
                         "BAD_STEPS", "BAD_START", "NOT_A_TABLE", "NOT_FINITE", "NO_PARTICLES", "BAD_POSITIONS",
                         "GOAL_OUTSIDE")
            if hasattr(m, name)}
    assert len(bits) == 13 and len(set(bits.values())) == 13, bits
    assert all(b > 0 and b & (b - 1) == 0 for b in bits.values()), bits
    assert set(planner.PLAN_ERRORS) <= set(bits.values()) and len(planner.PLAN_ERRORS) == 5
    assert len(export.ERRORS) == 11 and set(export.ERRORS) <= set(bits.values())
