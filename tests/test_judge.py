"""The judge (``control.judge``): a second model's c of each candidate, against a loop over episodes and candidates;
the candidate it rates best is the one pushed, and only it; bad judgements and unsupported orders refused."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from dynres_jax.config import CameraConfig
from dynres_jax.control.choosers import BestOfK, FixedOmega
from dynres_jax.control.goals import KindGoals, disc_goal, make_goals
from dynres_jax.control.judge import JudgeKeep, JudgeScored, judged_costs
from dynres_jax.control.mpc import Situation
from dynres_jax.control.objective import objective
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig
from dynres_jax.models.registry import learned_dynamics, sweep_dynamics
from dynres_jax.perception import Particles
from dynres_jax.sim.camera import Camera

B, K, T, N = 3, 5, 2, 16


@pytest.fixture(scope="module")
def scene():
    camera = Camera.top_down(CameraConfig(width=64, height=64))
    rng = np.random.default_rng(0)
    masks = [disc_goal(camera, c, 0.06) for c in ([0.05, 0.0], [-0.05, 0.05], [0.0, -0.06])]
    goals = make_goals(np.stack(masks), camera, n_samples=64)  # 64 <= 5 N: c uses every sample
    positions = np.c_[rng.uniform(-0.08, 0.08, (B * N, 2)), np.full(B * N, 0.005)].reshape(B, N, 3)
    mask = np.arange(N)[None] < np.array([[16], [12], [9]])
    particles = Particles(jnp.asarray(np.where(mask[..., None], positions, 0.0), jnp.float32), jnp.asarray(mask),
                          jnp.full(B, 0.02), jnp.full(B, 100), jnp.zeros(B, jnp.int32))
    proposals = np.c_[rng.uniform(-0.1, 0.1, (B * K * T, 2)), rng.uniform(-0.1, 0.1, (B * K * T, 2))]
    return camera, goals, particles, proposals.reshape(B, K, T, 4).astype(np.float32)


def loop_costs(judge, camera, goals, particles, proposals):
    """c of each (episode, candidate) one by one: the judge's rollout, then the task objective on its last state."""
    out = np.zeros(proposals.shape[:2])
    for b in range(B):
        goal = jax.tree.map(lambda x, b=b: x[b], goals)
        model = judge(particles.radius[b])
        for k in range(K):
            final = model(particles.positions[b], particles.mask[b], jnp.asarray(proposals[b, k]))[-1]
            out[b, k] = float(objective(final, particles.mask[b], goal, camera))
    return out


@pytest.mark.parametrize("which", ["sweep", "learned"])
def test_judged_costs_equal_a_loop(scene, which):
    camera, goals, particles, proposals = scene
    judge = sweep_dynamics(0.04) if which == "sweep" else learned_dynamics(
        Dynamics(DynamicsConfig(hidden=16, processor="gns", propagation_steps=2), rngs=nnx.Rngs(0)))
    ours = np.asarray(judged_costs(particles, goals, jnp.asarray(proposals), dynamics=judge, camera=camera))
    reference = loop_costs(judge, camera, goals, particles, proposals)
    np.testing.assert_allclose(ours, reference, rtol=1e-5, atol=1e-5)
    assert np.ptp(reference, axis=1).min() > 0  # the candidates differ, so the choice is not a tie


class Pushes:
    """Worlds whose push records its actions and moves nothing."""

    def __init__(self):
        self.actions = []

    def push(self, states, actions):
        self.actions.append(np.asarray(actions))
        return states


def keep(scene, judge, proposals=None):
    camera, goals, particles, given = scene
    proposals = given if proposals is None else proposals
    worlds, states = Pushes(), SimpleNamespace(broken=np.zeros(B, bool))
    now = Situation(states, None, camera, goals, None, jnp.zeros((B, 2), jnp.uint32), None, False)
    plan = dict(omega=np.full(B, 16), particles=particles, proposals=proposals,
                predicted_objective=np.full(B, np.nan, np.float32))
    scored = lambda after, g: dict(distance=np.zeros(B), inside=np.zeros(B))  # noqa: E731
    return worlds, JudgeKeep(judge)(worlds, now, [plan], scored)


def test_the_lowest_judged_candidate_is_pushed_and_nothing_else(scene):
    camera, goals, particles, proposals = scene
    judge = sweep_dynamics(0.04)
    worlds, kept = keep(scene, judge)
    reference = loop_costs(judge, camera, goals, particles, proposals)
    pick = np.argmin(reference, axis=1)
    assert len(worlds.actions) == 1  # one push per episode: the judge's candidate, no simulated copies
    np.testing.assert_array_equal(worlds.actions[0], proposals[np.arange(B), pick, 0])
    np.testing.assert_array_equal(kept["best"], proposals[np.arange(B), pick])
    np.testing.assert_allclose(kept["predicted_objective"], reference[np.arange(B), pick], rtol=1e-5)
    assert not np.all(pick == K - 1)  # not merely the last candidate (the planner's best)


def test_a_candidate_the_judge_cannot_score_is_never_chosen(scene):
    _, _, _, proposals = scene
    bad = proposals.copy()
    bad[:, 0] = np.nan  # the judge's c is NaN for candidate 0 of every episode
    worlds, kept = keep(scene, sweep_dynamics(0.04), bad)
    assert np.all(np.isfinite(kept["best"])) and np.all(np.isfinite(kept["predicted_objective"]))
    bad[1] = np.nan
    with pytest.raises(ValueError, match=r"episodes \[1\]"):
        keep(scene, sweep_dynamics(0.04), bad)


def test_the_judge_asks_for_the_refined_candidates_of_one_plan(scene):
    _, goals, _, _ = scene
    obs = SimpleNamespace(depth=np.zeros((B, 4, 4)))
    orders = JudgeScored(FixedOmega(goals, 50), sweep_dynamics(0.04))(0, obs)
    (candidate,) = orders.candidates
    assert candidate.proposals == "plans" and np.all(candidate.omega == 50) and isinstance(orders.keep, JudgeKeep)
    with pytest.raises(ValueError, match="one plan per step"):
        JudgeScored(BestOfK(FixedOmega(goals, 50), 3), sweep_dynamics(0.04))(0, obs)
    pair = jax.tree.map(lambda x: jnp.stack([x, x], 1), goals)
    kinds = KindGoals(pair, jnp.zeros((B, 2), bool), pair.distance, jnp.zeros(B))
    with pytest.raises(ValueError, match="Sort"):
        JudgeScored(FixedOmega(kinds, 50), sweep_dynamics(0.04))(0, obs)


def test_the_judge_recipe_is_the_issues_learned_simulator():
    """``train_dynamics --recipe judge``: GNS with at least 10 message-passing steps of their own weights at width
    128 or more, input noise, and at least 10 M push samples seen (steps x windows x pushes)."""
    from dynres_jax.learn.train import RECIPES

    recipe = RECIPES["judge"]
    model = Dynamics(recipe.model, rngs=nnx.Rngs(0))
    steps = [m for _, m in nnx.iter_graph(model) if type(m).__name__ == "GNSStep"]
    assert recipe.model.processor == "gns" and len(steps) >= 10 and recipe.model.hidden >= 128
    assert len({id(s.edge_in.kernel) for s in steps}) == len(steps)  # unshared: a kernel each
    assert recipe.noise > 0 and recipe.steps * recipe.batch * recipe.horizon >= 10_000_000


@pytest.mark.slow
def test_evaluate_runs_the_judge_beside_the_model(tmp_path):
    """evaluate --methods 10 judge --judge CKPT: both on the same episodes, paired; the judge's name in the summary;
    method and checkpoint go together, else one line before any work."""
    import json

    from dynres_jax.commands import evaluate
    from dynres_jax.models.registry import SHIPPED_DYNAMICS

    tiny = ["--quick", "--episodes", "2", "--mpc-steps", "1", "--pieces", "40", "--samples", "4", "--adam-steps", "2",
            "--dynamics", "sweep", "--best-omega", "10", "--workers", "1"]
    summary = evaluate.main([*tiny, "--methods", "10", "judge", "--judge", SHIPPED_DYNAMICS, "--out", str(tmp_path)])
    assert set(summary["methods"]) == {"10", "judge"} and "step" in summary["judge"]
    judged = json.loads((tmp_path / "judge.json").read_text())
    assert len(judged["final_distance"]) == 2 and np.all(np.array(judged["omega"]) == 10)
    for bad in (["--methods", "judge"], ["--methods", "10", "--judge", SHIPPED_DYNAMICS]):
        with pytest.raises(SystemExit):
            evaluate.main([*tiny, *bad, "--out", str(tmp_path / "bad")])
