"""Closed loop: a tiny Gather episode with the sweep heuristic as the model (CPU)."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.config import CameraConfig, PileConfig, PushConfig, SceneConfig, SimConfig
from dynres_jax.control import tasks
from dynres_jax.control.budget import TimingTable
from dynres_jax.control.choosers import (
    AdaptiveOmega,
    BestOfK,
    Candidate,
    Chooser,
    FixedOmega,
    OracleOmega,
    Orders,
    ProbeOmega,
    SimulatorScored,
    climb,
    on_ladder,
)
from dynres_jax.control.decision import batch, decide_batch, fold, goal_cost
from dynres_jax.control.goals import disc_goal, make_goal
from dynres_jax.control.judge import JudgeScored
from dynres_jax.control.keep import scorer
from dynres_jax.control.mpc import MPCConfig, run, run_episode
from dynres_jax.control.objective import distribution_distance, seen_inside
from dynres_jax.control.planner import PlannerConfig, _plan_jit, plan
from dynres_jax.io.draw import PUSH_COLOUR, goal_frames, overlay
from dynres_jax.models.registry import sweep_dynamics
from dynres_jax.sim.camera import Camera
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import EnvWorlds, WorldPool


@pytest.fixture(scope="module")
def episode():
    sim = SimConfig(scene=SceneConfig(pieces=(8,)), pile=PileConfig(layout="spread"),
                    push=PushConfig(max_length=0.1, settle_time=0.04), camera=CameraConfig(width=64, height=64))
    env = PileEnv(sim, backend="mujoco")
    mask = disc_goal(env.camera, np.array([0.0, 0.0]), 0.06)
    goal = make_goal(mask, env.camera, n_samples=64)
    planner = PlannerConfig(samples=8, adam_steps=20, bound=env.action_bound, max_length=0.1)
    cfg = MPCConfig(mpc_steps=3, buckets=(4, 8), max_points=512, planner=planner)
    state = env.reset(jax.random.PRNGKey(0))
    lines, frames = [], goal_frames(mask, env.camera)
    final, records = run_episode(env, state, FixedOmega(batch(goal), 6), sweep_dynamics(0.04), cfg,
                                 jax.random.PRNGKey(1), log=lines.append, on_step=[frames])
    return env, state, goal, final, records, frames.finish(batch(final)), lines


def test_episode_records_every_step(episode):
    env, _, _, _, records, frames, lines = episode
    assert [r["step"] for r in records] == [0, 1, 2] and len(frames) == 4
    assert sum(line.startswith("step") for line in lines) == 3 and sum("compiling" in line for line in lines) <= 1
    for r in records:
        assert r["omega"] == 6 and 0.0 <= r["inside"] <= 1.0 and np.isfinite(r["distance"])
        assert r["bucket"] == 8 and r["adam_steps"] == 20 and r["planning_s"] > 0
        assert np.all(np.abs(r["action"]) <= env.action_bound + 1e-5)


def test_the_first_decision_of_a_bucket_says_it_compiles(episode):
    """One line before a bucket and batch size's first decision (it compiles); none when they come again."""
    env, start, goal, _, _, _, _ = episode
    planner = PlannerConfig(samples=3, adam_steps=2, bound=env.action_bound, max_length=0.1)  # a spec of its own
    cfg = MPCConfig(mpc_steps=2, buckets=(4, 8), max_points=512, planner=planner)
    runs = []
    for _ in range(2):
        lines = []
        run_episode(env, start, FixedOmega(batch(goal), 6), sweep_dynamics(0.04), cfg, jax.random.PRNGKey(1),
                    log=lines.append)
        runs.append([line for line in lines if "compiling" in line])
    assert runs[0] == ["compiling the decision at bucket 8 for 1 episode(s) (once per bucket; tens of seconds on a "
                       "CPU)"] and runs[1] == []


def test_the_gif_draws_each_push_and_captions_the_end(episode):
    """Each step's frame draws its push as an arrow (the midpoint of the push is the arrow's colour); the final frame
    draws none and is captioned with the final d (it differs from the uncaptioned frame only in the caption's rows)."""
    env, _, goal, final, records, frames, _ = episode
    mask = disc_goal(env.camera, np.array([0.0, 0.0]), 0.06)  # the fixture's goal
    for frame, record in zip(frames[:-1], records, strict=True):
        push = np.asarray(record["action"], np.float64)
        middle = np.array([[(push[0] + push[2]) / 2, (push[1] + push[3]) / 2, 0.0]])
        u, v = (np.asarray(env.camera.world_to_pixel(middle)[0][0]) * frame.shape[0] / env.camera.height).astype(int)
        assert np.any(np.all(frame[v - 2:v + 3, u - 2:u + 3] == PUSH_COLOUR, axis=-1)), record["step"]
    assert not np.any(np.all(frames[-1] == PUSH_COLOUR, axis=-1))
    bare = overlay(np.asarray(final.obs.rgb), mask, None, env.camera)
    assert np.array_equal(frames[-1][24:], bare[24:]) and not np.array_equal(frames[-1][:24], bare[:24])


def test_a_held_step_draws_no_push(episode):
    """A step whose episode held (the stop rule: a NaN action) is drawn without an arrow, not refused."""
    env, state, _, _, records, _, _ = episode
    mask = disc_goal(env.camera, np.array([0.0, 0.0]), 0.06)
    frames = goal_frames(mask, env.camera)
    held = {k: v if k == "step" else [v] for k, v in records[0].items()} | {"action": [[np.nan] * 4]}
    particles = np.asarray(state.pos)[:3]
    frame = frames.draw(np.asarray(state.obs.rgb), particles, held)
    assert not np.any(np.all(frame == PUSH_COLOUR, axis=-1))


def test_episode_brings_the_pile_nearer_the_goal(episode):
    env, start, goal, _, records, _, _ = episode
    before = float(distribution_distance(start.obs, goal, env.camera))
    assert records[-1]["distance"] < before, "three planned pushes should lower the distribution distance d"


def test_the_judge_pushes_the_candidate_it_rates_best(episode):
    """A closed loop whose keep rule is a second model (``judge.JudgeScored``, the sweep heuristic as judge): each
    step pushes one of the refined candidates, and the record's predicted c is the judge's c of the pushed plan,
    recomputed here from the step's particles."""
    env, start, goal, _, _, _, _ = episode
    judge = sweep_dynamics(0.04)
    planner = PlannerConfig(samples=8, adam_steps=20, bound=env.action_bound, max_length=0.1)
    cfg = MPCConfig(mpc_steps=2, buckets=(4, 8), max_points=512, planner=planner, warm_start=False)
    seen = []
    _, records = run_episode(env, start, JudgeScored(FixedOmega(batch(goal), 6), judge), sweep_dynamics(0.04), cfg,
                             jax.random.PRNGKey(1), log=lambda s: None,
                             on_step=[lambda t, states, particles, record: seen.append(particles)])
    for particles, record in zip(seen, records, strict=True):
        p = jax.tree.map(lambda x: x[0], particles)  # the callback's particles are the batch's [B = 1]
        push = jnp.asarray(record["action"], jnp.float32).reshape(1, 4)
        final = judge(p.radius)(p.positions, p.mask, push)[-1]
        c = float(goal_cost(goal, env.camera, p.positions.shape[0])(final, p.mask))
        assert np.isclose(float(np.ravel(record["predicted_objective"])[0]), c, rtol=1e-5)
        assert np.isfinite(np.ravel(record["distance"])[0])


def test_omega_out_of_range_is_named():
    for omega in (0, 1, 101, 2.5):
        with pytest.raises(ValueError, match="omega must be an integer in"):
            FixedOmega(None, omega)
    with pytest.raises(ValueError, match="mpc_steps"):
        MPCConfig(mpc_steps=0)


def test_batched_episodes_equal_one_at_a_time():
    """run over EnvWorlds (a batch of episodes; C MuJoCo here, so that no MJX compile is paid: MJX's batch equals its
    worlds in test_pool) makes the same first decision as run_episode on each episode."""
    sim = SimConfig(scene=SceneConfig(pieces=(6,)), pile=PileConfig(layout="spread"),
                    push=PushConfig(max_length=0.1, settle_time=0.04), camera=CameraConfig(width=48, height=48))
    env = PileEnv(sim, backend="mujoco")
    masks = [disc_goal(env.camera, np.array(c), 0.06) for c in ([0.0, 0.0], [0.05, -0.03])]
    goals = [make_goal(m, env.camera, n_samples=32) for m in masks]
    planner = PlannerConfig(samples=4, adam_steps=5, bound=env.action_bound, max_length=0.1)
    cfg = MPCConfig(mpc_steps=1, buckets=(6,), max_points=256, planner=planner)
    keys = jax.random.split(jax.random.PRNGKey(2), 2)
    worlds = EnvWorlds(env)
    starts = worlds.reset(jax.random.split(jax.random.PRNGKey(3), 2))
    batched_goals = jax.tree.map(lambda *x: np.stack(x), *goals)
    _, records = run(worlds, starts, FixedOmega(batched_goals, 5), sweep_dynamics(0.04), cfg, keys, log=lambda s: None)
    for b in range(2):
        start = jax.tree.map(lambda x, b=b: x[b], starts)
        _, one = run_episode(env, start, FixedOmega(batch(goals[b]), 5), sweep_dynamics(0.04), cfg, keys[b],
                             log=lambda s: None)
        np.testing.assert_allclose(records[0]["objective"][b], one[0]["objective"], rtol=1e-4)
        np.testing.assert_allclose(records[0]["predicted_objective"][b], one[0]["predicted_objective"], rtol=1e-3)
        np.testing.assert_allclose(records[0]["inside"][b], one[0]["inside"], atol=1 / 6 + 1e-6)


@pytest.mark.slow
def test_pool_episodes_with_per_episode_omega_and_budget_equal_one_at_a_time():
    """run on a WorldPool with ω chosen per episode (adaptive) in different buckets and a time budget makes the same
    decisions as run_episode at each episode's ω in its own bucket: every episode runs the Adam steps its bucket
    affords (from the same frozen timing table), and the batch's larger bucket pads inertly."""
    sim = SimConfig(scene=SceneConfig(pieces=(6,)), pile=PileConfig(layout="spread"),
                    push=PushConfig(max_length=0.1, settle_time=0.04), camera=CameraConfig(width=48, height=48))
    pool, env = WorldPool(sim), PileEnv(sim, backend="mujoco")
    masks = [disc_goal(env.camera, np.array(c), 0.06) for c in ([0.0, 0.0], [0.05, -0.03])]
    goals = [make_goal(m, env.camera, n_samples=32) for m in masks]
    planner = PlannerConfig(samples=4, adam_steps=6, bound=env.action_bound, max_length=0.1)
    cfg = MPCConfig(mpc_steps=2, buckets=(2, 6), max_points=256, planner=planner, time_budget=0.016)
    timing = TimingTable("test", 4, 1, fixed_s={2: 0.01, 6: 0.01}, step_s={2: 0.0015, 6: 0.003}, frozen=True)
    keys = jax.random.split(jax.random.PRNGKey(2), 2)
    starts = pool.reset(jax.random.split(jax.random.PRNGKey(3), 2))
    omegas = np.array([2, 6])
    chooser = AdaptiveOmega(jax.tree.map(lambda *x: np.stack(x), *goals), lambda obs, goals: omegas)
    _, records = run(pool, starts, chooser, sweep_dynamics(0.04), cfg, keys, log=lambda s: None, timing=timing)
    assert [r["omega"].tolist() for r in records] == [[2, 6], [2, 6]]
    assert [r["bucket"].tolist() for r in records] == [[2, 6], [2, 6]]
    assert [r["adam_steps"].tolist() for r in records] == [[4, 2], [4, 2]]  # floor(6 ms / 1.5 ms), floor(6 / 3)
    np.testing.assert_allclose(records[0]["planning_s"], [0.016, 0.016])
    for b in range(2):
        start = jax.tree.map(lambda x, b=b: x[b], starts)
        _, one = run_episode(env, start, FixedOmega(batch(goals[b]), int(omegas[b])), sweep_dynamics(0.04), cfg,
                             keys[b], log=lambda s: None, timing=timing)
        for t in range(2):
            assert one[t]["bucket"] == omegas[b] and one[t]["adam_steps"] == records[t]["adam_steps"][b]
            np.testing.assert_allclose(records[t]["predicted_objective"][b], one[t]["predicted_objective"], rtol=1e-3)
            np.testing.assert_allclose(records[t]["inside"][b], one[t]["inside"], atol=1e-6)


@pytest.fixture(scope="module")
def three():
    """Three tiny Gather scenes in a WorldPool: (pool, goals [3], planner, cfg of one MPC step, keys, starts)."""
    sim = SimConfig(scene=SceneConfig(pieces=(6,)), pile=PileConfig(layout="spread"),
                    push=PushConfig(max_length=0.1, settle_time=0.04), camera=CameraConfig(width=48, height=48))
    pool = WorldPool(sim)
    masks = [disc_goal(pool.camera, np.array(c), 0.06) for c in ([0.0, 0.0], [0.05, -0.03], [-0.04, 0.04])]
    goals = jax.tree.map(lambda *x: np.stack(x), *[make_goal(m, pool.camera, n_samples=32) for m in masks])
    planner = PlannerConfig(samples=4, adam_steps=3, bound=pool.env.action_bound, max_length=0.1)
    cfg = MPCConfig(mpc_steps=1, buckets=(2, 6), max_points=256, planner=planner)
    keys = jax.random.split(jax.random.PRNGKey(2), 3)
    return pool, goals, planner, cfg, keys, pool.reset(jax.random.split(jax.random.PRNGKey(3), 3))


@pytest.mark.slow
def test_oracle_keeps_the_best_candidate_per_episode(three):
    """The oracle over (2, 6): each episode keeps the ω whose push left the lower d, and its record equals that of the
    run at that fixed ω (same keys); an ω beyond the pile's points is named, not planned on empty particles."""
    pool, goals, planner, cfg, keys, starts = three
    runs = {}
    for omega in (2, 6):
        runs[omega] = run(pool, starts, FixedOmega(goals, omega), sweep_dynamics(0.04), cfg, keys,
                          log=lambda s: None).records[0]
    _, records = run(pool, starts, OracleOmega(goals, (2, 6)), sweep_dynamics(0.04), cfg, keys, log=lambda s: None)
    best = np.where(runs[6]["distance"] < runs[2]["distance"], 6, 2)
    assert records[0]["omega"].tolist() == best.tolist()
    for b, w in enumerate(best):
        np.testing.assert_allclose(records[0]["distance"][b], runs[w]["distance"][b], rtol=1e-6)
    np.testing.assert_allclose(records[0]["distance"], np.minimum(runs[2]["distance"], runs[6]["distance"]), rtol=1e-6)
    with pytest.raises(ValueError, match="perception failed in episodes"):
        run(pool, starts, FixedOmega(goals, 100), sweep_dynamics(0.04),
            MPCConfig(mpc_steps=1, buckets=(100,), max_points=256, planner=planner), keys, log=lambda s: None)


def test_probe_keeps_the_plan_the_model_rates_best_per_second(three):
    """The probe over (2, 6) under a budget: each candidate plans on half of it (bucket 6 affords 1 Adam step, not
    the 3 of the whole budget), and each episode keeps the candidate with the larger predicted fall of c per second of
    the table's price, computed here by hand from fixed-ω runs on half the budget; only that push is executed."""
    pool, goals, planner, cfg, keys, starts = three
    table = TimingTable("test", 4, 1, fixed_s={2: 2**-10, 6: 2**-9}, step_s={2: 2**-10, 6: 2**-8}, frozen=True)
    whole, half = (dataclasses.replace(cfg, time_budget=b) for b in (2**-6, 2**-7))
    assert whole.allot([6], table)[1].tolist() == [3] and whole.allot([6], table, share=0.5)[1].tolist() == [1]
    runs = {w: run(pool, starts, FixedOmega(goals, w), sweep_dynamics(0.04), half, keys, timing=table,
                   log=lambda s: None).records[0] for w in (2, 6)}
    rate = {w: (r["objective"] - r["predicted_objective"]) / np.array(
        [table.seconds(int(b), int(s)) for b, s in zip(r["bucket"], r["adam_steps"], strict=True)])
        for w, r in runs.items()}
    best = np.where(rate[6] > rate[2], 6, 2)
    assert set(best.tolist()) == {2, 6}  # chosen per episode: both candidates are kept somewhere
    _, records = run(pool, starts, ProbeOmega(goals, (2, 6)), sweep_dynamics(0.04), whole, keys, timing=table,
                     log=lambda s: None)
    assert records[0]["omega"].tolist() == best.tolist()
    assert records[0]["adam_steps"].tolist() == [3 if w == 2 else 1 for w in best]
    for b, w in enumerate(best):
        for key in ("distance", "predicted_objective", "action"):
            np.testing.assert_allclose(records[0][key][b], runs[w][key][b], rtol=1e-6, err_msg=key)
    with pytest.raises(ValueError, match="at least two"):
        ProbeOmega(goals, (50,))


def test_best_of_k_keeps_the_best_of_independent_plans(three):
    """BestOfK(ω, 2): draw 0 is FixedOmega's plan (same keys), draw 1 a plan of its own keys that pushes elsewhere;
    each episode keeps the one whose push left the lower d."""
    pool, goals, _, cfg, keys, starts = three

    class Draw(Chooser):  # one candidate: plan draw d alone
        def __init__(self, d):
            self.d = d

        def __call__(self, t, obs):
            return Orders(goals, (Candidate(np.full(3, 6, np.int32), draw=self.d),))

    one = {d: run(pool, starts, Draw(d), sweep_dynamics(0.04), cfg, keys, log=lambda s: None).records[0]
           for d in (0, 1)}
    fixed = run(pool, starts, FixedOmega(goals, 6), sweep_dynamics(0.04), cfg, keys, log=lambda s: None).records[0]
    np.testing.assert_array_equal(one[0]["action"], fixed["action"])
    assert not np.allclose(one[0]["action"], one[1]["action"])  # independent keys: other pushes
    best = run(pool, starts, BestOfK(FixedOmega(goals, 6), 2), sweep_dynamics(0.04), cfg, keys,
               log=lambda s: None).records[0]
    np.testing.assert_allclose(best["distance"], np.minimum(one[0]["distance"], one[1]["distance"]), rtol=1e-6)
    with pytest.raises(ValueError, match="K >= 1"):
        BestOfK(FixedOmega(goals, 6), 0)
    with pytest.raises(ValueError, match="one plan per step, got 5 candidates$"):  # the oracle already chooses
        BestOfK(OracleOmega(goals), 2)(0, starts.obs)
    with pytest.raises(ValueError, match="one plan per step, got 2 candidates, drawn$"):
        SimulatorScored(BestOfK(FixedOmega(goals, 6), 2))(0, starts.obs)
    assert isinstance(climb(FixedOmega(goals, 6), "best3"), BestOfK) and climb(FixedOmega(goals, 6), "best3").k == 3
    assert climb(FixedOmega(goals, 6), "rerank").refine and not climb(FixedOmega(goals, 6), "sim").refine
    assert not on_ladder("oracle") and not on_ladder("best0") and on_ladder("best12")
    with pytest.raises(ValueError, match="not a rung of the ladder: 'oracle'"):
        climb(FixedOmega(goals, 6), "oracle")


def test_simulator_scored_keeps_the_sample_with_the_lowest_true_d(three):
    """The sim ceiling: the planner's M = 4 first samples of the step (as ``decide_batch`` draws them with no Adam
    step), each pushed in the pool; every episode keeps the one that left the lowest d. The method pushes all four in
    one call of 4 x 3 worlds; the reference pushes one candidate a call, in the same shape (four copies), because the
    renderer's edge pixels move with the batch's shape (float rounding: one pixel of a 48 x 48 frame moved d by 9 %)."""
    pool, goals, planner, cfg, keys, starts = three
    record = run(pool, starts, SimulatorScored(FixedOmega(goals, 6)), sweep_dynamics(0.04), cfg, keys,
                 log=lambda s: None).records[0]
    omega, zero = np.full(3, 6, np.int32), np.zeros(3, np.int32)
    _, _, result = decide_batch(starts.obs, goals, fold(keys, 0), jnp.zeros((3, 1, 4)), False, omega, zero,
                                spec=cfg.spec(6), dynamics=sweep_dynamics(0.04), camera=pool.camera)
    samples = np.asarray(result.actions)[:, :, 0]  # [B, M, 4]
    score = scorer(pool.camera, tuple(np.asarray(pool.scene.kind).tolist()))
    four = lambda x: jnp.concatenate([jnp.asarray(x)] * 4)  # noqa: E731
    d = np.stack([np.asarray(score(pool.push(jax.tree.map(four, starts), four(samples[:, m])),
                                   jax.tree.map(four, goals))["distance"])[:3] for m in range(4)], 1)
    np.testing.assert_allclose(record["distance"], d.min(axis=1), rtol=1e-6)
    np.testing.assert_allclose(record["action"], samples[np.arange(3), d.argmin(axis=1)], atol=1e-7)
    assert np.all(record["adam_steps"] == 0) and np.all(np.isnan(record["predicted_objective"]))
    assert len(set(map(tuple, samples[0]))) == 4 and np.all(d.argmin(axis=1) != 0)  # a real choice, not sample 0


def test_time_budget_needs_a_table():
    cfg = MPCConfig(mpc_steps=1, buckets=(6,), time_budget=0.1)
    with pytest.raises(ValueError, match="timing table"):
        run(None, None, FixedOmega(None, 5), None, cfg, None)


def test_a_new_goal_reuses_the_compiled_plan(episode):
    """Each MPC step builds its cost for a new goal; the planner must not compile again for it."""
    env, state, goal, *_ = episode
    other = make_goal(disc_goal(env.camera, np.array([0.05, -0.03]), 0.05), env.camera, n_samples=64)
    config = PlannerConfig(samples=4, adam_steps=3, bound=env.action_bound, max_length=0.1)
    positions, mask = state.pos[:6], np.ones(6, bool)
    dynamics = sweep_dynamics(0.04)(0.01)
    plan(dynamics, goal_cost(goal, env.camera), positions, mask, jax.random.PRNGKey(0), config)
    compiled = _plan_jit._cache_size()
    result = plan(dynamics, goal_cost(other, env.camera), positions, mask, jax.random.PRNGKey(1), config)
    assert _plan_jit._cache_size() == compiled
    assert np.isfinite(float(result.best_cost))


def test_a_chooser_that_repeats_the_goals_changes_nothing(episode):
    """A chooser of its own that orders the fixed goal and ω every step decides exactly as FixedOmega, and adds its
    record fields and scores to every record."""
    env, state, goal, _, records, _, _ = episode
    cfg = MPCConfig(mpc_steps=3, buckets=(4, 8), max_points=512,
                    planner=PlannerConfig(samples=8, adam_steps=20, bound=env.action_bound, max_length=0.1))

    class Repeat(Chooser):
        def __call__(self, t, obs):
            return Orders(batch(goal), (Candidate(np.array([6])),), None, {"order": [t]})

        def score(self, states):
            return {"pieces_x": [float(np.mean(np.asarray(states.pos[0])[:, 0]))]}

    _, repeated = run_episode(env, state, Repeat(), sweep_dynamics(0.04), cfg, jax.random.PRNGKey(1),
                              log=lambda s: None)
    for r, p in zip(records, repeated, strict=True):
        np.testing.assert_array_equal(p["action"], r["action"])
        assert p["distance"] == r["distance"] and p["order"] == r["step"]
    assert np.isfinite(repeated[-1]["pieces_x"])


@pytest.mark.slow
def test_evaluate_climbs_the_ladder_on_episodes_that_do_not_depend_on_the_count(tmp_path):
    """``evaluate --methods 50 best2 sim rerank``, one MPC step: best-of-2 (draw 0 is ω = 50's plan) and rerank (the
    model's plans, its own best among them, chosen by the simulator) leave no episode worse than ω = 50; sim runs no
    Adam step, rerank the model's. A run of one episode repeats episode 0 of the run of two (keys from (seed, i)
    alone), so the ceiling on a subset is paired with the full run."""
    from dynres_jax.commands import evaluate

    tiny = ["--quick", "--dynamics", "sweep", "--workers", "2", "--mpc-steps", "1", "--samples", "4",
            "--adam-steps", "2", "--pieces", "20", "--seed", "3"]
    evaluate.main([*tiny, "--episodes", "2", "--methods", "50", "best2", "sim", "rerank", "--out",
                   str(tmp_path / "two")])
    evaluate.main([*tiny, "--episodes", "1", "--methods", "sim", "--out", str(tmp_path / "one")])
    runs = {m: json.loads((tmp_path / "two" / f"{m}.json").read_text()) for m in ("50", "best2", "sim", "rerank")}
    one = json.loads((tmp_path / "one" / "sim.json").read_text())
    for method in ("best2", "rerank"):
        assert np.all(np.array(runs[method]["final_distance"]) <= np.array(runs["50"]["final_distance"]) + 1e-6)
    assert np.all(np.array(runs["sim"]["adam_steps"]) == 0)
    assert np.all(np.array(runs["50"]["adam_steps"]) == 2) and np.all(np.array(runs["rerank"]["adam_steps"]) == 2)
    assert one["final_distance"][0] == pytest.approx(runs["sim"]["final_distance"][0], rel=1e-6)
    np.testing.assert_allclose(one["final_pieces"][0], runs["sim"]["final_pieces"][0], atol=1e-4)
    assert not np.allclose(runs["sim"]["final_pieces"][0], runs["sim"]["start_pieces"][0], atol=1e-3)  # it pushed


@pytest.mark.slow
def test_evaluate_quick_is_quick(tmp_path):
    """``evaluate --quick`` alone runs 4 episodes of 3 MPC steps of 8 samples x 10 Adam steps; a flag given beside it
    wins. --stop-share reaches the loop: from the first frame that met it, an episode's scores stand still."""
    from dynres_jax.commands import evaluate

    summary = evaluate.main(["--quick", "--methods", "50", "--dynamics", "sweep", "--workers", "2", "--pieces", "20",
                             "--samples", "4", "--stop-share", "0.01", "--out", str(tmp_path)])
    run = json.loads((tmp_path / "50.json").read_text())
    assert summary["methods"]["50"]["episodes"] == 4 and len(run["mean_distance"]) == 3
    assert summary["mpc_steps"] == 3 and summary["samples"] == 4 and np.all(np.array(run["adam_steps"])[0] == 10)
    seen, inside = np.array(run["seen_inside"]), np.array(run["inside"])
    first = [int(np.argmax(seen[:, e] >= 0.01)) if np.any(seen[:, e] >= 0.01) else 3 for e in range(4)]
    assert min(first) < 2  # some episode held before its last push
    for e, t in enumerate(first):
        assert np.all(inside[max(t - 1, 0):, e] == inside[max(t - 1, 0), e]) if t < 3 else True


def test_warm_start_off_plans_every_step_from_fresh_samples(episode, monkeypatch):
    """MPCConfig.warm_start: the decisions after the first get the previous plan (warm) by default, and never with
    warm_start=False (the reference's planner); the first never does."""
    from dynres_jax.control import mpc

    env, state, goal, *_ = episode
    planner = PlannerConfig(samples=8, adam_steps=20, bound=env.action_bound, max_length=0.1)
    seen = []

    def spy(*args, **kwargs):
        seen.append(bool(np.asarray(args[4]).all()))
        return decide_batch(*args, **kwargs)

    monkeypatch.setattr(mpc, "decide_batch", spy)
    for warm_start, want in ((True, [False, True, True]), (False, [False, False, False])):
        seen.clear()
        cfg = MPCConfig(mpc_steps=3, buckets=(8,), max_points=512, planner=planner, warm_start=warm_start)
        run_episode(env, state, FixedOmega(batch(goal), 6), sweep_dynamics(0.04), cfg, jax.random.PRNGKey(1),
                    log=lambda s: None)
        assert seen == want, (warm_start, seen)


def test_a_decision_on_resamplings_plans_on_the_clouds_other_fps_starts(episode):
    """With PlannerConfig.resamples R, the decision scores each push on R re-samplings of one cloud: the first is the
    particles it reports, the others FPS from other starts (keys folded from the perception key); the plan equals the
    planner run by hand on those R sets."""
    from dynres_jax.control.decision import perceive_and_decide
    from dynres_jax.control.planner import sample_pushes
    from dynres_jax.perception import cloud_particles, perceive

    env, state, goal, *_ = episode
    planner = PlannerConfig(samples=6, adam_steps=4, bound=env.action_bound, max_length=0.1, resamples=3)
    spec = MPCConfig(buckets=(8,), max_points=512, planner=planner).spec(8)
    key, init = jax.random.PRNGKey(3), jnp.zeros((1, 4))
    particles, _, result = perceive_and_decide(state.obs, goal, key, init, False, 6, 4, spec=spec,
                                               dynamics=sweep_dynamics(0.04), camera=env.camera)
    k_h, k_plan = jax.random.split(key)
    seen = perceive(state.obs, env.camera, 6, k_h, 8, max_points=512)
    sets = [seen.particles] + [cloud_particles(seen.points, seen.valid, state.obs.depth, 6, k, 8)
                               for k in jax.random.split(jax.random.fold_in(k_h, 1), 2)]
    assert not np.allclose(sets[0].positions, sets[1].positions)  # other starts, other particles
    by_hand = plan(sweep_dynamics(0.04)(seen.particles.radius), goal_cost(goal, env.camera, 8),
                   jnp.stack([s.positions for s in sets]), jnp.stack([s.mask for s in sets]), k_plan, planner,
                   init=sample_pushes(k_plan, seen.points, seen.valid, planner)[0], adam_steps=4,
                   initial=sample_pushes(k_plan, seen.points, seen.valid, planner))
    np.testing.assert_allclose(np.asarray(particles.positions), np.asarray(sets[0].positions))
    np.testing.assert_allclose(np.asarray(result.best), np.asarray(by_hand.best), atol=1e-6)
    np.testing.assert_allclose(np.asarray(result.costs), np.asarray(by_hand.costs), rtol=1e-5)


def test_seen_inside_is_the_share_of_foreground_pixels_on_the_goal():
    """objective.seen_inside of a hand-made foreground: 4 pixels, one on the goal -> 1/4; none -> 0."""
    camera = Camera.top_down(CameraConfig(width=16, height=16))
    goal_mask = np.zeros((16, 16), bool)
    goal_mask[2:4, 2:4] = True
    goal, current = make_goal(goal_mask, camera, n_samples=4), np.zeros((16, 16), bool)
    current[3, 3] = current[10, 10] = current[10, 11] = current[12, 5] = True
    assert float(seen_inside(current, goal, camera)) == 0.25
    assert float(seen_inside(np.zeros((16, 16), bool), goal, camera)) == 0.0


@pytest.fixture(scope="module")
def free(three):
    """The three scenes over 4 MPC steps without the stop rule: (pool, goals, cfg, keys, starts, records, the pieces
    before each push)."""
    pool, goals, _, cfg, keys, starts = three
    cfg, before = dataclasses.replace(cfg, mpc_steps=4), []
    _, records = run(pool, starts, FixedOmega(goals, 6), sweep_dynamics(0.04), cfg, keys, log=lambda s: None,
                     on_step=[lambda t, states, particles, record: before.append(np.asarray(states.pos))])
    return pool, goals, cfg, keys, starts, records, before


@pytest.mark.parametrize("stop", ["some", "all"])
def test_the_stop_rule_holds_an_episode_from_the_frame_that_met_it(free, stop):
    """MPCConfig.stop_share: a run that stops equals, episode by episode, the same run without the rule up to the
    first frame whose seen share met it (t*), and from t* on it pushes nothing: its pieces stay where they were
    before push t* and its d and share inside are those after push t* - 1 ("all": every episode holds, and the steps
    where all do are not planned)."""
    pool, goals, cfg, keys, starts, free, before = free
    seen = np.array([r["seen_inside"] for r in free])  # [T, B]
    share = 1e-6 if stop == "all" else float(np.max(seen[1:])) * 0.9  # met by some episode after a push
    first = np.array([np.argmax(seen[:, b] >= share) if np.any(seen[:, b] >= share) else 4 for b in range(3)])
    assert np.all(first >= 1) and (np.all(first < 4) if stop == "all" else np.any(first == 4))
    lines = []
    final, held = run(pool, starts, FixedOmega(goals, 6), sweep_dynamics(0.04),
                      dataclasses.replace(cfg, stop_share=share), keys, log=lines.append)
    assert len(held) == 4
    for b in range(3):
        for t in range(4):
            assert held[t]["held"][b] == (t >= first[b])
            source = free[min(t, first[b] - 1)]  # held from t*: the scores after push t* - 1
            for k in ("distance", "inside", "seen_inside"):
                np.testing.assert_allclose(held[t][k][b], source[k][b] if k != "seen_inside" else free[t][k][b]
                                           if t <= first[b] else held[first[b]][k][b], atol=1e-6)
            assert np.all(np.isnan(held[t]["action"][b])) == (t >= first[b])
        if first[b] < 4:
            np.testing.assert_allclose(np.asarray(final.pos)[b], before[first[b]][b], atol=1e-6)
    for t in range(1, 4):  # a step where every episode holds plans nothing
        assert np.all(held[t]["adam_steps"] == 0) == np.all(t >= first)
    assert (stop == "all") == any(np.all(t >= first) for t in range(1, 4))
    steps = lambda records, k: np.stack([r[k] for r in records]).tolist()  # noqa: E731  (evaluate's [T][E])
    replayed = tasks.stopped({k: steps(free, k) for k in ("inside", "distance", "seen_inside")}, share)
    assert replayed["stopped_at"] == first.tolist()
    for k in ("inside", "distance"):
        np.testing.assert_allclose(replayed[k], steps(held, k), atol=1e-6)
        np.testing.assert_allclose(replayed[f"final_{k}"], held[-1][k], atol=1e-6)
