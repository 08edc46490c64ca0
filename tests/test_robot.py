"""The robot loop (control.robot, experiments.robot): a whole tiny Gather episode on the simulator as camera and arm,
its recorded frames replayed as a dry run, the workspace check before any push, a stop at the goal (CPU)."""

import json
import os

import imageio.v3 as iio
import jax
import numpy as np
import pytest

from dynres_jax.commands import robot
from dynres_jax.config import CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control.choosers import FixedOmega, OracleOmega, ProbeOmega
from dynres_jax.control.goals import disc_goal
from dynres_jax.control.mpc import MPCConfig
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.control.robot import DryRun, SimulatedRobot, UnsafePush, Workspace, run_robot
from dynres_jax.errors import InputError
from dynres_jax.models.registry import sweep_dynamics
from dynres_jax.sim.env import PileEnv

pytestmark = pytest.mark.slow  # end to end: CI's second tier (python -m pytest -m slow)

TINY = ["--steps", "2", "--samples", "4", "--adam-steps", "3", "--dynamics", "sweep", "--pieces", "30"]
REPLAY = TINY[:-2]  # a replay's frames are as recorded: the simulator's --pieces is refused beside --replay


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("robot"))
    return out, robot.main([*TINY, "--sensor", "realsense", "--calibrate", "--out", out])


def test_a_simulated_episode_pushes_and_records_every_frame(episode):
    out, summary = episode
    steps = summary["steps"]
    assert summary["pushes"] == 2 and not summary["dry_run"] and [s["step"] for s in steps] == [0, 1, 2]
    assert all(len(s["action"]) == 4 for s in steps[:2]) and "action" not in steps[2]
    assert sorted(os.listdir(os.path.join(out, "frames"))) == ["000", "001", "002"]
    assert set(os.listdir(os.path.join(out, "frames", "000"))) == {"depth.png", "rgb.png", "camera.json"}
    assert open(os.path.join(out, "episode.gif"), "rb").read(3) == b"GIF"
    assert steps[2]["distance"] != steps[0]["distance"] and 0 <= summary["true_inside"] <= 1  # the pushes moved it
    assert summary["succeeded"] == (summary["true_inside"] >= 0.9 - 1e-6)  # Gather's rule on the true state
    with open(os.path.join(out, "metrics.json")) as f:
        assert json.load(f)["steps"] == steps


def test_the_recorded_frames_replay_as_a_dry_run(episode, tmp_path):
    """The frames the simulator's episode saved, read back: the robot plans a push for each but sends none, and
    each frame's d is what the episode saw (depth kept to a millimetre)."""
    out, summary = episode
    replay = robot.main([*REPLAY, "--replay", os.path.join(out, "frames"), "--calibrate", "--out", str(tmp_path)])
    assert replay["dry_run"] and replay["pushes"] == 2 and "true_inside" not in replay
    assert replay["sensor"] is None and summary["sensor"] == "realsense"  # a replay is as recorded, no profile
    longer = robot.main([*REPLAY, "--steps", "5", "--replay", os.path.join(out, "frames"), "--out",
                         str(tmp_path / "longer")])  # more steps than frames: the replay ends with its last frame
    assert longer["pushes"] == 3 and os.path.isfile(tmp_path / "longer" / "metrics.json")
    for seen, live in zip(replay["steps"], summary["steps"], strict=True):
        assert seen["distance"] == pytest.approx(live["distance"], rel=0.05)


def test_an_interrupted_robot_episode_resumes_after_its_last_push(tmp_path, capsys, monkeypatch):
    """Ctrl-C once push 1 of 2 is saved keeps the episode's progress; the same command then reads the frame after that
    push (the simulator's world as it was left, its sensor's next frame) and ends where the uninterrupted episode
    ends: the same pushes, the same true share inside, a GIF of every frame."""

    whole = robot.main([*TINY, "--out", str(tmp_path / "whole")])
    from dynres_jax.commands import guard

    kept = guard.kept

    def interrupted(what):  # the user's Ctrl-C arrives once push 1 is saved ("": none yet)
        kept(what)
        if what:
            raise KeyboardInterrupt

    monkeypatch.setattr(guard, "kept", interrupted)
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        robot.main([*TINY, "--out", str(tmp_path / "cut")])
    assert e.value.code == 130
    assert "(the episode's push 1 of 2); rerun the same command to resume" in capsys.readouterr().err
    assert (tmp_path / "cut" / "progress.npz").exists() and not (tmp_path / "cut" / "metrics.json").exists()
    monkeypatch.setattr(guard, "kept", kept)
    again = robot.main([*TINY, "--out", str(tmp_path / "cut")])
    assert "resuming the interrupted episode after push 1 of 2" in capsys.readouterr().out
    assert [s.get("action") for s in again["steps"]] == [s.get("action") for s in whole["steps"]]
    assert again["true_inside"] == whole["true_inside"] and again["pushes"] == 2
    assert not (tmp_path / "cut" / "progress.npz").exists()
    assert len(iio.imread(tmp_path / "cut" / "episode.gif", index=None)) == 3  # two pushes and the end


def test_the_workspace_check_refuses_pushes_outside_and_a_dry_run_moves_nothing():
    sim = SimConfig(scene=SceneConfig(pieces=(12,)), pile=PileConfig(layout="spread"),
                    camera=CameraConfig(width=64, height=64))
    env = PileEnv(sim, backend="mujoco")
    workspace = Workspace.of(env)
    with pytest.raises(UnsafePush, match="leaves the workspace"):
        workspace.check([0.0, 0.0, env.action_bound + 0.01, 0.0])  # ends beyond the bound
    with pytest.raises(UnsafePush, match="finite"):
        workspace.check([0.0, np.nan, 0.05, 0.0])
    inside = np.array([0.0, 0.0, 0.05, 0.0], np.float32)
    np.testing.assert_array_equal(workspace.check(inside), inside)
    world, pusher = SimulatedRobot(env, jax.random.PRNGKey(1)), DryRun()
    start = np.asarray(world.state.pos).copy()
    planner = PlannerConfig(samples=4, adam_steps=3, bound=env.action_bound, reach=env.reach,
                            max_length=sim.push.max_length)
    cfg = MPCConfig(mpc_steps=2, buckets=(16,), max_points=1024, planner=planner)
    steps = run_robot(world, pusher, disc_goal(env.camera, np.zeros(2), 0.08), sweep_dynamics(0.04), cfg, 12,
                      jax.random.PRNGKey(2), workspace=workspace, log=lambda s: None)
    assert len(pusher.pushes) == 2 and np.array_equal(np.asarray(world.state.pos), start)
    assert steps[0]["distance"] == steps[2]["distance"]  # nothing moved: the same frame every time
    done = run_robot(SimulatedRobot(env, jax.random.PRNGKey(1)), DryRun(), np.ones((64, 64), bool) & ~np.eye(
        64, dtype=bool), sweep_dynamics(0.04), cfg, 12, jax.random.PRNGKey(2), workspace=workspace, success=0.5,
        log=lambda s: None)
    assert len(done) == 1 and "action" not in done[0]  # already at the goal: stops before any push


def test_the_robot_loop_takes_any_chooser_that_keeps_by_the_model():
    """A chooser as a function of the goal: FixedOmega the same pushes as the int ω; the probe plans at each of its
    ω and pushes the one it keeps; the oracle (copies of the world) is refused before any push."""
    sim = SimConfig(scene=SceneConfig(pieces=(30,)), camera=CameraConfig(width=64, height=64))
    env = PileEnv(sim, backend="mujoco")
    planner = PlannerConfig(samples=4, adam_steps=3, bound=env.action_bound, reach=env.reach,
                            max_length=sim.push.max_length)
    cfg = MPCConfig(mpc_steps=2, buckets=(16, 32), max_points=1024, planner=planner)
    goal = disc_goal(env.camera, np.zeros(2), 0.08)

    def episode(chooser):
        pusher = DryRun()
        steps = run_robot(SimulatedRobot(env, jax.random.PRNGKey(1)), pusher, goal, sweep_dynamics(0.04), cfg,
                          chooser, jax.random.PRNGKey(2), workspace=Workspace.of(env), log=lambda s: None)
        return [{k: v for k, v in s.items() if k != "planning_s"} for s in steps], pusher.pushes

    fixed, pushed = episode(12)
    assert episode(lambda g: FixedOmega(g, 12)) == (fixed, pushed) and [s["omega"] for s in fixed[:2]] == [12, 12]
    probe, pushed = episode(lambda g: ProbeOmega(g, (12, 25)))
    assert len(pushed) == 2 and {s["omega"] for s in probe[:2]} <= {12, 25}
    with pytest.raises(InputError, match="a robot has one world"):
        episode(lambda g: OracleOmega(g, (12, 25)))


def test_the_robot_pushes_the_judges_choice():
    """JudgeScored in the robot loop: each push is the candidate the judge's keep rule chose among the planner's
    refined candidates (no world copied), its judged c the record's predicted_objective; a judge other than the
    planner's model changes what is pushed."""
    from flax import nnx

    from dynres_jax.control.judge import JudgeScored
    from dynres_jax.models.dynamics import Dynamics, DynamicsConfig
    from dynres_jax.models.registry import learned_dynamics

    sim = SimConfig(scene=SceneConfig(pieces=(30,)), camera=CameraConfig(width=64, height=64))
    env = PileEnv(sim, backend="mujoco")
    planner = PlannerConfig(samples=6, adam_steps=3, bound=env.action_bound, reach=env.reach,
                            max_length=sim.push.max_length)
    cfg = MPCConfig(mpc_steps=2, buckets=(16,), max_points=1024, planner=planner)
    goal = disc_goal(env.camera, np.zeros(2), 0.08)
    judge = learned_dynamics(Dynamics(DynamicsConfig(hidden=8, residual=False), rngs=nnx.Rngs(3)))
    chosen = []

    class Recorded:  # the judge's keep rule, its choices kept
        def __init__(self, keep):
            self.keep = keep

        def choose(self, plan, now):
            chosen.append(self.keep.choose(plan, now))
            return chosen[-1]

    def factory(g):
        scored = JudgeScored(FixedOmega(g, 12), judge)
        scored.keep = Recorded(scored.keep)
        return scored

    def episode(chooser):
        pusher = DryRun()
        steps = run_robot(SimulatedRobot(env, jax.random.PRNGKey(1)), pusher, goal, sweep_dynamics(0.04), cfg,
                          chooser, jax.random.PRNGKey(2), workspace=Workspace.of(env), log=lambda s: None)
        return steps, pusher.pushes

    steps, pushed = episode(factory)
    assert len(chosen) == len(pushed) == 2
    for step, push, pick in zip(steps, pushed, chosen, strict=False):
        np.testing.assert_array_equal(push, np.asarray(pick["proposals"])[0, 0, 0])
        assert step["predicted_objective"] == pytest.approx(float(pick["predicted_objective"][0]))
    _, own = episode(12)
    assert not np.array_equal(np.asarray(pushed[0]), np.asarray(own[0]))  # the judge chose another push


def test_robot_takes_a_judge_checkpoint(tmp_path):
    """robot --judge CKPT: the episode runs with the judge's choice, its name in the start line and metrics.json."""
    from dynres_jax.models.registry import SHIPPED_DYNAMICS

    summary = robot.main([*TINY, "--sensor", "none", "--judge", SHIPPED_DYNAMICS, "--out", str(tmp_path)])
    assert summary["judge"] and summary["pushes"] >= 1
    assert json.loads((tmp_path / "metrics.json").read_text())["judge"] == summary["judge"]
