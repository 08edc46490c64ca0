"""Resolution buckets and the time budget: bucket choice, padding inert across buckets with the shipped model, common
random numbers across ω, the timing table (formula, refinement, round trip, errors) and a time-budgeted decision
returning within its budget plus one step."""

import json
import math

import jax
import numpy as np
import pytest

from dynres_jax.config import CameraConfig, PileConfig, PushConfig, SceneConfig, SimConfig
from dynres_jax.control import budget
from dynres_jax.control.budget import TimingTable, adam_steps, bucket_for, check_buckets
from dynres_jax.control.choosers import FixedOmega
from dynres_jax.control.decision import batch, perceive_and_decide
from dynres_jax.control.goals import disc_goal, make_goal
from dynres_jax.control.mpc import MPCConfig, measure_timing, run_episode
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics, sweep_dynamics
from dynres_jax.sim.env import PileEnv


@pytest.fixture(scope="module")
def scene():
    sim = SimConfig(scene=SceneConfig(pieces=(30,)), pile=PileConfig(layout="spread"),
                    push=PushConfig(max_length=0.1, settle_time=0.04), camera=CameraConfig(width=64, height=64))
    env = PileEnv(sim, backend="mujoco")
    mask = disc_goal(env.camera, np.array([0.02, -0.01]), 0.06)
    planner = PlannerConfig(samples=6, adam_steps=8, bound=env.action_bound, max_length=0.1)
    return env, env.reset(jax.random.PRNGKey(0)), mask, make_goal(mask, env.camera), planner


def test_bucket_choice():
    assert [bucket_for(w) for w in (1, 16, 17, 32, 33, 50, 51, 64, 75, 76, 100)] == [16, 16, 32, 32, 50, 50, 75, 75,
                                                                                     75, 100, 100]
    assert bucket_for(5, (4, 8)) == 8 and bucket_for(4, (4, 8)) == 4
    for bad in (0, -3, 2.5):
        with pytest.raises(ValueError, match="positive integer"):
            bucket_for(bad)
    with pytest.raises(ValueError, match="exceeds the largest resolution bucket 100"):
        bucket_for(101)
    for bad in ((), (16, 16), (32, 16), (0, 8), (4.0, 8)):
        with pytest.raises(ValueError, match="buckets"):
            check_buckets(bad)
    with pytest.raises(ValueError, match="exceeds the largest resolution bucket 32"):
        MPCConfig(buckets=(16, 32)).allot([40])


def _decide(state, goal, key, dynamics, cfg, camera, omega, bucket, steps=None):
    """One decision without a warm start: (Particles, c, PlanResult)."""
    return perceive_and_decide(state.obs, goal, key, None, False, omega, steps, spec=cfg.spec(bucket),
                               dynamics=dynamics, camera=camera)


@pytest.mark.slow
def test_padding_is_inert_across_buckets(scene):
    """A decision at ω = 10 in bucket 16 equals the same decision in bucket 32 (same key): the particles, c, the
    plan and its cost, with the shipped model."""
    env, state, _, goal, planner = scene
    dynamics, _, _ = load_dynamics("learned", SHIPPED_DYNAMICS, env.config.scene.plate_half_width)
    cfg = MPCConfig(buckets=(16, 32), max_points=512, planner=planner)
    key = jax.random.PRNGKey(3)
    small = _decide(state, goal, key, dynamics, cfg, env.camera, 10, 16)
    large = _decide(state, goal, key, dynamics, cfg, env.camera, 10, 32)
    assert small[0].positions.shape == (16, 3) and large[0].positions.shape == (32, 3)
    np.testing.assert_allclose(small[0].positions, large[0].positions[:16], atol=1e-6)
    assert not np.any(large[0].mask[16:]) and int(np.sum(small[0].mask)) == 10
    np.testing.assert_allclose(float(small[1]), float(large[1]), rtol=1e-5)
    np.testing.assert_allclose(small[2].best, large[2].best, atol=1e-4)
    np.testing.assert_allclose(float(small[2].best_cost), float(large[2].best_cost), rtol=1e-4)
    assert float(small[2].best_cost) < float(small[2].history[0])  # the plan moved (it is not a no-op comparison)


def test_common_random_numbers_across_omega(scene):
    """One key gives the same starting pushes at every ω (drawn through the perception cloud); another key differs."""
    env, state, _, goal, planner = scene
    cfg = MPCConfig(buckets=(16, 32), max_points=512, planner=planner)
    dyn = sweep_dynamics(env.config.scene.plate_half_width)

    def start(omega, key):  # zero Adam steps: the actions are the starting pushes
        return np.asarray(_decide(state, goal, key, dyn, cfg, env.camera, omega, bucket_for(omega), 0)[2].actions)

    key = jax.random.PRNGKey(7)
    np.testing.assert_array_equal(start(4, key), start(12, key))
    np.testing.assert_array_equal(start(4, key), start(30, key))
    assert not np.allclose(start(4, key), start(4, jax.random.PRNGKey(8)))


def test_timing_table_formula_refine_and_round_trip(tmp_path):
    table = TimingTable("cpu: test", 50, 1, fixed_s={16: 0.02, 100: 0.05}, step_s={16: 0.001, 100: 0.004})
    assert table.steps(16, 0.5, 1000) == math.floor((0.5 - 0.02) / 0.001) == 480
    assert table.steps(100, 0.5, 1000) == math.floor((0.5 - 0.05) / 0.004) == 112
    assert table.steps(100, 0.5, 50) == 50 and table.steps(100, 0.01, 50) == 0
    assert adam_steps(16, 200) == 200 and adam_steps(16, 200, 0.5, table) == 200 and adam_steps(100, 1000, 0.5,
                                                                                                table) == 112
    with pytest.raises(ValueError, match="needs a timing table"):
        adam_steps(16, 200, 0.5)
    with pytest.raises(ValueError, match="no bucket 32"):
        table.steps(32, 0.5, 10)
    table.refine(100, 10, 0.05 + 10 * 0.006)  # a decision slower than the table: step time moves halfway there
    assert table.step_s[100] == pytest.approx(0.005) and table.refined == {100: 1}
    path = str(tmp_path / "timing.json")
    table.save(path)
    loaded = TimingTable.load(path)
    assert loaded.frozen and loaded.to_json() == table.to_json()
    assert [loaded.steps(b, 0.3, 500) for b in (16, 100)] == [table.steps(b, 0.3, 500) for b in (16, 100)]
    loaded.refine(100, 10, 1.0)  # frozen: reproduces the run's step counts, never refined
    assert loaded.step_s[100] == table.step_s[100]
    with open(tmp_path / "other.json", "w") as f:
        json.dump({"samples": 3}, f)
    with pytest.raises(ValueError, match="not a timing table"):
        TimingTable.load(str(tmp_path / "other.json"))
    quoted = dict(json.load(open(path)), samples=str(table.samples))  # "50": the refusal named "50 x 1 against 50 x 1"
    with open(tmp_path / "quoted.json", "w") as f:
        json.dump(quoted, f)
    with pytest.raises(ValueError, match="samples must be an integer, got '"):
        TimingTable.load(str(tmp_path / "quoted.json"))
    with pytest.raises(ValueError, match="step_s > 0"):
        TimingTable("x", 1, 1, fixed_s={16: 0.0}, step_s={16: float("nan")})


@pytest.mark.slow
def test_time_budgeted_decisions_return_within_budget_plus_one_step(scene):
    """measure_timing on this CPU, then a budgeted episode: each decision runs the steps the table affords and
    returns within the budget plus one Adam step (the median decision, with an allowance for the host's jitter)."""
    env, state, mask, goal, _ = scene
    planner = PlannerConfig(samples=6, adam_steps=400, bound=env.action_bound, max_length=0.1)
    dyn = sweep_dynamics(env.config.scene.plate_half_width)
    cfg = MPCConfig(mpc_steps=3, buckets=(16, 32), max_points=512, planner=planner)
    lines = []
    table = measure_timing(state.obs, goal, dyn, cfg, env.camera, log=lines.append)
    assert set(table.step_s) == {16, 32} and all(s > 0 for s in table.step_s.values())
    assert [line.split(":")[1] for line in lines] == [" bucket 16 (1 of 2)", " bucket 32 (2 of 2)"]  # progress
    seconds = table.fixed_s[16] + 40 * table.step_s[16]  # a budget of about 40 steps: it binds below 400
    cfg = MPCConfig(mpc_steps=5, buckets=(16, 32), max_points=512, planner=planner, time_budget=seconds)
    _, records = run_episode(env, state, FixedOmega(batch(goal), 12), dyn, cfg, jax.random.PRNGKey(1),
                             log=lambda s: None, timing=table)
    for r in records:
        assert r["bucket"] == 16 and 0 < r["adam_steps"] < 400
    # the median decision, with 50 ms for a busy host's jitter (decisions here take milliseconds)
    median = float(np.median([r["planning_s"] for r in records]))
    assert median <= seconds + table.step_s[16] + 0.05, ([r["planning_s"] for r in records], seconds)
    assert budget.BUCKETS[-1] == 100


def test_a_table_of_another_batch_and_bad_perception_are_named(scene):
    env, state, mask, goal, planner = scene
    cfg = MPCConfig(mpc_steps=1, buckets=(16, 32), planner=planner, time_budget=0.1)
    other = TimingTable("x", planner.samples + 1, 1, fixed_s={16: 0.0, 32: 0.0}, step_s={16: 1e-3, 32: 1e-3})
    with pytest.raises(ValueError, match="measured for 7 samples"):
        cfg.adam_steps(16, other)
    dyn = sweep_dynamics(env.config.scene.plate_half_width)
    empty = state.obs._replace(depth=np.full_like(np.asarray(state.obs.depth), np.nan))
    with pytest.raises(ValueError, match="NaN"):
        run_episode(env, state._replace(obs=empty), FixedOmega(batch(goal), 12), dyn,
                    MPCConfig(mpc_steps=1, buckets=(16, 32), planner=planner), jax.random.PRNGKey(0),
                    log=lambda s: None)


def test_the_reference_pricing_by_hand():
    """The reference's fitted step time, (2969.3971 - 69.923244 ω + 1.8509846 ω²) / 200 ms in whole ms, and the Adam
    steps it affords: at ω = 100, 1 s buys 13 (PAPER.md: 'only 13 steps') and 2 s 27."""
    from dynres_jax.control import budget

    assert [budget.reference_step_s(w) for w in (25, 50, 75, 100)] == [0.011, 0.02, 0.04, 0.072]
    table = budget.reference_table((25, 50, 75, 100), samples=50, horizon=1)
    assert table.frozen and table.by_omega and set(table.fixed_s) == set(range(1, 101))
    assert set(table.fixed_s.values()) == {0.0}
    assert table.steps(100, 1.0, 200) == 13 and table.steps(100, 2.0, 200) == 27
    assert table.steps(25, 2.0, 200) == 181 and table.steps(25, 3.0, 200) == 200
    assert table.steps(25, 1e308, 200) == 200  # no OverflowError from floor(huge / step)
    table.refine(100, 10, 5.0)  # frozen: a run's own times do not move it
    assert table.step_s[100] == 0.072


def test_the_reference_prices_each_omega_by_its_own_step_time_not_its_bucket():
    """The reference has no buckets: a decision at ω = 34 runs in bucket 50 but is priced at t(34) = int((2969.3971 -
    69.923244 · 34 + 1.8509846 · 34²) / 200) = 13 ms, so 1 s buys 76 Adam steps, not bucket 50's 50; a measured table
    prices the same decision by its bucket."""
    from dynres_jax.control import budget
    from dynres_jax.control.mpc import MPCConfig
    from dynres_jax.control.planner import PlannerConfig

    cfg = MPCConfig(planner=PlannerConfig(samples=50, adam_steps=200), buckets=(25, 50, 75, 100), time_budget=1.0)
    t34 = int((2969.3971 - 69.923244 * 34 + 1.8509846 * 34**2) / 200) / 1000
    assert t34 == 0.013 and budget.reference_step_s(34) == t34
    reference = budget.reference_table(cfg.buckets, 50, 1)
    buckets, steps = cfg.allot([34, 50, 10, 100], reference)
    assert buckets.tolist() == [50, 50, 25, 100]
    assert steps.tolist() == [int(1.0 / t34), 50, int(1.0 / budget.reference_step_s(10)), 13] == [76, 50, 83, 13]
    measured = budget.TimingTable("x", 50, 1, {b: 0.0 for b in cfg.buckets}, {b: 0.02 for b in cfg.buckets})
    assert cfg.allot([34, 50], measured)[1].tolist() == [50, 50]


def test_reference_planner_flags_resolve_to_the_authors_options_and_a_flag_beside_wins(capsys):
    """--reference-planner fills every option as the reference's code (starts fixed, 30 re-samplings with a vote, no
    warm start, lr 0.005 of the action range, buckets 25 50 75 100, its pricing); a flag given beside it wins; without
    it, ours; bad combinations are one-line errors before any work."""
    import argparse
    from types import SimpleNamespace

    from dynres_jax.commands.planner_args import add_planner_args, mpc_config, resolve_planner_args
    from dynres_jax.config import PushConfig

    def parsed(*flags):
        parser = argparse.ArgumentParser()
        add_planner_args(parser)
        parser.add_argument("--quick", action="store_true")
        args = parser.parse_args(list(flags))
        resolve_planner_args(parser, args)
        return args

    env = SimpleNamespace(action_bound=0.181, reach=0.2, config=SimpleNamespace(push=PushConfig()))
    cfg = mpc_config(env, parsed("--reference-planner"))
    p = cfg.planner
    assert (p.starts, p.resamples, p.vote, cfg.warm_start, cfg.buckets) == ("fixed", 30, True, False, (25, 50, 75, 100))
    assert abs(p.lr - 0.005 * 2 * 0.181) < 1e-12
    assert parsed("--reference-planner").pricing == "reference"
    cfg = mpc_config(env, parsed("--reference-planner", "--warm-start", "--resamples", "1", "--no-vote"))
    assert cfg.warm_start and cfg.planner.resamples == 1 and not cfg.planner.vote and cfg.planner.starts == "fixed"
    one = mpc_config(env, parsed("--reference-planner", "--resamples", "1"))  # the preset's vote over one: no vote
    assert one.planner.resamples == 1 and not one.planner.vote and one.planner.starts == "fixed"
    ours = mpc_config(env, parsed())
    assert (ours.planner.starts, ours.planner.resamples, ours.planner.vote, ours.warm_start) == ("pile", 1, False, True)
    assert ours.planner.lr == 0.02 and ours.buckets == (16, 32, 50, 75, 100) and parsed().pricing == "measured"
    for bad, says in ((["--vote"], "--vote needs --resamples"), (["--lr", "-1"], "--lr"),
                      (["--reference-planner", "--resamples", "1", "--vote"], "--vote needs --resamples"),
                      (["--buckets", "50", "25"], "--buckets"),
                      (["--pricing", "reference", "--time-budget", "1", "--timing", "t.json"], "--timing and"),
                      (["--pricing", "reference"], "prices the Adam steps of a --time-budget")):
        with pytest.raises(SystemExit):
            parsed(*bad)
        assert says in capsys.readouterr().err


def test_a_run_spending_a_saved_table_plans_at_its_buckets(tmp_path, capsys):
    """--timing FILE of a table measured at other buckets (16 32 64 100, before buckets 50 and 75): the run plans at
    the table's buckets, so it reproduces the runs that table priced; --buckets beside it must be the table's; without
    --timing the default buckets."""
    import argparse

    from dynres_jax.commands.planner_args import (
        add_budget_args,
        add_reference_planner_args,
        check_budget,
        load_timing,
        resolve_planner_args,
    )
    from dynres_jax.errors import InputError

    old = (16, 32, 64, 100)
    path = str(tmp_path / "timing.json")
    TimingTable("cpu", 50, 1, {b: 0.01 for b in old}, {b: 0.02 for b in old}).save(path)

    def loaded(*flags):
        parser = argparse.ArgumentParser()
        add_budget_args(parser)
        add_reference_planner_args(parser)
        args = parser.parse_args(list(flags))
        resolve_planner_args(parser, args)
        load_timing(parser, args)
        return args

    assert loaded("--time-budget", "1", "--timing", path).buckets == old
    assert loaded("--time-budget", "1", "--timing", path, "--buckets", "16", "32", "64", "100").buckets == old
    assert loaded("--time-budget", "1").buckets == budget.BUCKETS == (16, 32, 50, 75, 100)
    with pytest.raises(SystemExit):
        loaded("--time-budget", "1", "--timing", path, "--buckets", "16", "32", "50", "100")
    assert "prices buckets 16 32 64 100; give those" in capsys.readouterr().err
    # a fixed-ω run's table (its one bucket) keeps the run's buckets, and a run that may plan where it has no price
    # is told so before any step (it failed mid-episode: "omega=75 exceeds the largest resolution bucket 50")
    partial = str(tmp_path / "partial.json")
    TimingTable("cpu", 50, 1, {50: 0.01}, {50: 0.02}).save(partial)
    assert loaded("--time-budget", "1", "--timing", partial).buckets == budget.BUCKETS
    cfg = MPCConfig(planner=PlannerConfig(samples=50, adam_steps=10), time_budget=1.0)
    table = TimingTable.load(partial)
    check_budget(cfg, table, [50])  # a fixed ω = 50 finds its price
    with pytest.raises(InputError, match="prices buckets 50; this run plans at ω 10-100, in buckets 16 32 50 75 100"):
        check_budget(cfg, table, [10], finest=100)  # adaptive
    per_omega = str(tmp_path / "per_omega.json")  # a table priced by ω (the reference's): the preset's buckets stay
    budget.reference_table((25, 50, 75, 100), 50, 1).save(per_omega)
    assert loaded("--time-budget", "1", "--timing", per_omega, "--reference-planner", "--pricing",
                  "measured").buckets == (25, 50, 75, 100)


@pytest.mark.slow
def test_a_fixed_omega_times_only_its_bucket(scene, monkeypatch, tmp_path):
    """measure_timing for the ω a run decides at times their buckets alone; a task command at a fixed ω asks for
    its ω only (was: every bucket, 43 of a 60 s run)."""
    env, state, _, goal, planner = scene
    cfg = MPCConfig(buckets=(16, 32), max_points=512, planner=planner)
    lines = []
    table = measure_timing(state.obs, goal, sweep_dynamics(env.config.scene.plate_half_width), cfg, env.camera,
                           log=lines.append, omegas=[12], repeats=1)
    assert set(table.step_s) == {16} and [line.split(":")[1] for line in lines] == [" bucket 16 (1 of 1)"]

    from dynres_jax.commands import gather, task

    asked = []

    def measured(*args, omegas=None, **kwargs):
        asked.append(omegas)
        raise KeyboardInterrupt  # enough: the command stops here, as Ctrl-C stops it

    monkeypatch.setattr(task, "measure_timing", measured)
    with pytest.raises(SystemExit):
        gather.main(["--time-budget", "1", "--resolution", "25", "--dynamics", "sweep", "--pieces", "20",
                     "--mpc-steps", "1", "--samples", "4", "--out", str(tmp_path / "gather")])
    assert asked == [[25]]


def test_a_budget_says_what_it_affords_before_the_episode(capsys):
    """A run under --time-budget says, before its first step, how many Adam steps a decision gets at each ω by the
    table (by hand: (budget - fixed) / step), so a budget that leaves one step is not silent; none is refused."""
    from dynres_jax.commands.planner_args import check_budget
    from dynres_jax.errors import InputError

    table = TimingTable("cpu", 50, 1, {b: 0.2 for b in budget.BUCKETS}, {b: 0.04 for b in budget.BUCKETS})
    cfg = MPCConfig(planner=PlannerConfig(samples=50, adam_steps=100), time_budget=0.25)
    expected = adam_steps(table.key(50, cfg.buckets), 100, 0.25, table)
    check_budget(cfg, table, [50])
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"--time-budget 0.25 s on cpu affords {expected} Adam step(s) at ω = 50 a decision"), line
    assert 1 <= expected <= 2 and "without a budget: 100" in line
    with pytest.raises(InputError, match="affords no Adam step"):
        check_budget(MPCConfig(planner=PlannerConfig(samples=50, adam_steps=100), time_budget=0.1), table, [50])
