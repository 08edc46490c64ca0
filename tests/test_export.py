"""Exported decision: the file, read back where only jax and flatbuffers are installed, turns a depth frame and a goal
mask into the push the library's closed loop chooses, bit for bit on the CPU."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from dynres_jax import export as ex
from dynres_jax.commands import export as export_cli
from dynres_jax.commands import plan as plan_cli
from dynres_jax.config import CameraConfig, SceneConfig
from dynres_jax.control.decision import DecisionSpec
from dynres_jax.control.goals import disc_goal, make_goal
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.io import ckpt, frames
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig
from dynres_jax.models.registry import load_dynamics
from dynres_jax.perception import BAD_OMEGA, NO_DEPTH
from dynres_jax.sim.camera import Camera, Observation
from dynres_jax.sim.pushes import wall_reach
from dynres_jax.sim.sensor import NO_READING
from studies import export_check

N_MAX, STEP, Q, FRAMES = 16, 7, 16, 20
CAMERA = Camera.top_down(CameraConfig(width=32, height=32))  # 1 m above the table, 1.4 cm a pixel
SPEC = DecisionSpec(16, PlannerConfig(samples=4, adam_steps=3, horizon=2), max_points=256, real_depth=True)


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    """A randomly initialised tiny Dynamics model saved as a checkpoint (the card as train.py writes it)."""
    cfg = DynamicsConfig(hidden=16, propagation_steps=1, push_frame=True, residual=True, world_edges=False,
                         bin_position=False)
    directory = tmp_path_factory.mktemp("ckpt")
    ckpt.save_module(directory, STEP, Dynamics(cfg, rngs=nnx.Rngs(3)),
                     {"dynamics": dataclasses.asdict(cfg), "train": {"n_max": N_MAX}, "step": STEP})
    return str(directory)


def frame(seed):
    """A robot's frame of a pile: blobs of 3 x 3 pixels 1 cm high on the table, a few missing readings."""
    rng = np.random.default_rng(seed)
    height = np.zeros((32, 32), np.float32)
    for u, v in rng.integers(8, 22, size=(int(rng.integers(4, 9)), 2)):
        height[v - 1:v + 2, u - 1:u + 2] = 0.01
    depth = 1.0 - height  # top-down, camera 1 m up: z-depth is 1 - z
    depth[tuple(rng.integers(0, 32, size=(2, 6)))] = NO_READING
    unknown = np.full((32, 32), -1, np.int32)
    return Observation(jnp.asarray(depth), unknown, unknown, np.zeros((32, 32, 3), np.uint8))


def inputs(i):
    """Frame i's call: (depth, goal_mask, key, omega, adam_steps, init, warm)."""
    rng = np.random.default_rng(100 + i)
    mask = disc_goal(CAMERA, rng.uniform(-0.08, 0.08, 2), rng.uniform(0.04, 0.08))
    init = rng.uniform(-0.1, 0.1, (SPEC.planner.horizon, 4)).astype(np.float32)
    return (np.asarray(frame(i).depth), mask, np.asarray(jax.random.PRNGKey(i)), np.int32(3 + i % 14),
            np.int32(i % 4), init, np.bool_(i % 2))


def library_decision(dynamics, depth, goal_mask, key, omega, steps, init, warm):
    """What the robot loop decides on this frame (``control.robot.run_robot``'s call)."""
    obs = frame(0)._replace(depth=jnp.asarray(depth))
    return export_check.library_decision(obs, make_goal(goal_mask, CAMERA, n_samples=Q), key, omega, steps, init,
                                         warm, spec=SPEC, dynamics=dynamics, camera=CAMERA)


@pytest.fixture(scope="module")
def exported_file(tiny_ckpt, tmp_path_factory):
    exported, info = ex.export_checkpoint(tiny_ckpt, SPEC, CAMERA, goal_samples=Q, platforms=("cpu",))
    path = str(tmp_path_factory.mktemp("export") / "decision.jaxexport")
    assert ex.save(exported, path, info) > 0
    return path


@pytest.fixture(scope="module")
def reloaded(exported_file):
    """The file read back with the library's loader; one object, so it compiles once."""
    return ex.load(exported_file)


@pytest.mark.slow
def test_the_file_decides_like_the_library_where_only_jax_and_flatbuffers_are(tiny_ckpt, exported_file, tmp_path):
    calls = [inputs(i) for i in range(FRAMES)]
    np.savez(tmp_path / "frames.npz", **{n: np.stack([c[k] for c in calls]) for k, n in enumerate(ex.INPUT_NAMES)})
    # this Python, isolated, in a site of links to jax and flatbuffers only
    robot = export_check.run_robot_side(exported_file, str(tmp_path / "frames.npz"), str(tmp_path / "out.npz"), None,
                                        str(tmp_path))
    installed = sorted(os.listdir(tmp_path / "site"))
    assert not any(n.startswith(("dynres", "flax", "mujoco", "cv2", "opencv")) for n in installed), installed
    assert "flatbuffers" in installed and "jaxlib" in installed
    assert not robot["error"].any() and robot["seconds"].shape == (FRAMES,)
    dynamics, n_max, _ = load_dynamics("learned", tiny_ckpt, 0.04)
    assert n_max == N_MAX
    pushes = set()
    for i, call in enumerate(calls):
        live = library_decision(dynamics, *call)
        for k, v in live.items():
            np.testing.assert_array_equal(robot[k][i], np.asarray(v), err_msg=f"frame {i}: {k}")
        assert int(robot["mask"][i].sum()) == call[3]  # ω particles
        pushes.add(tuple(np.round(robot["push"][i], 4)))
    assert len(pushes) == FRAMES  # every frame its own push: the inputs matter


def test_a_missing_reading_may_be_written_as_zero(reloaded):
    """0, NaN and ±inf are no reading, as NO_READING is (``sim.sensor.is_reading``, the library's rule too)."""
    depth, *rest = inputs(3)
    assert (depth == NO_READING).any()
    a = reloaded.call(depth, *rest)
    for hole in (0.0, np.nan, np.inf, -np.inf):
        b = reloaded.call(np.where(depth == NO_READING, hole, depth).astype(np.float32), *rest)
        for k in ex.OUTPUT_NAMES:
            np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]), err_msg=f"{hole}: {k}")


def test_bad_input_is_flagged_and_gives_no_push(reloaded):
    depth, goal_mask, key, omega, steps, init, warm = inputs(5)
    cases = {
        "empty goal": ((depth, np.zeros_like(goal_mask), key, omega, steps, init, warm), ex.GOAL_EMPTY),
        "whole-image goal": ((depth, np.ones_like(goal_mask), key, omega, steps, init, warm), ex.GOAL_FULL),
        "inverted goal": ((depth, ~goal_mask, key, omega, steps, init, warm), ex.GOAL_OUTSIDE),
        "a goal pixel in the image's corner": ((depth, goal_mask | (np.arange(goal_mask.size).reshape(goal_mask.shape)
                                                                    == 0), key, omega, steps, init, warm),
                                               ex.GOAL_OUTSIDE),
        "no depth reading": ((np.full_like(depth, np.nan), goal_mask, key, omega, steps, init, warm), NO_DEPTH),
        "omega 0": ((depth, goal_mask, key, np.int32(0), steps, init, warm), BAD_OMEGA),
        "omega above capacity": ((depth, goal_mask, key, np.int32(SPEC.capacity + 1), steps, init, warm), BAD_OMEGA),
        "too many Adam steps": ((depth, goal_mask, key, omega, np.int32(SPEC.planner.adam_steps + 1), init, warm),
                                ex.BAD_STEPS),
        "NaN warm start": ((depth, goal_mask, key, omega, steps, np.full_like(init, np.nan), np.bool_(True)),
                           ex.BAD_START),
        "a frame 1 m deeper": ((np.where(depth < NO_READING, depth + 1.0, depth), goal_mask, key, omega, steps, init,
                                warm), ex.NOT_A_TABLE),
        "depth x 1.1": ((np.where(depth < NO_READING, depth * 1.1, depth), goal_mask, key, omega, steps, init, warm),
                        ex.NOT_A_TABLE),
    }
    for what, (args, bit) in cases.items():
        out = reloaded.call(*args)
        error = int(out["error"])
        assert error & bit, what
        assert np.isnan(np.asarray(out["push"])).all(), what
        assert ex.ERRORS[bit] in ex.describe_error(error), what
    assert int(reloaded.call(*inputs(5))["error"]) == 0 and ex.describe_error(0) == ""
    with pytest.raises(ValueError, match="shape"):
        reloaded.call(depth[:5], goal_mask, key, omega, steps, init, warm)


def test_the_file_refuses_the_frames_plan_refuses(reloaded):
    """The table check (``io.frames.table_fit``) flags a frame in the file exactly where ``check_table``, plan's
    rule, raises: scaled and shifted depths, and noise, but not the frames of a table."""
    depth, *rest = inputs(9)
    seen = depth < NO_READING
    rng = np.random.default_rng(0)
    variants = {"as is": depth, "x 1.02": depth * 1.02, "x 1.05": depth * 1.05, "+ 2 cm": depth + 0.02,
                "+ 5 cm": depth + 0.05, "noise": rng.uniform(0.5, 1.5, depth.shape), "x 0.5": depth * 0.5}
    verdicts = {}
    for what, d in variants.items():
        d = np.where(seen, d, NO_READING).astype(np.float32)
        try:
            frames.check_table(d, CAMERA, what)
            refused = False
        except frames.FrameError:
            refused = True
        flagged = bool(int(reloaded.call(d, *rest)["error"]) & ex.NOT_A_TABLE)
        verdicts[what] = (refused, flagged)
    assert all(refused == flagged for refused, flagged in verdicts.values()), verdicts
    assert verdicts["as is"] == (False, False) and verdicts["x 0.5"] == (True, True), verdicts


def test_a_damaged_file_is_refused_by_its_sidecars_checksum(exported_file, tmp_path):
    data = bytearray(open(exported_file, "rb").read())
    info = json.loads(open(exported_file + ".json").read())
    assert info["sha256"] and ex.load(exported_file) is not None
    data[len(data) // 2] ^= 1
    damaged = tmp_path / "decision.jaxexport"
    damaged.write_bytes(bytes(data))
    (tmp_path / "decision.jaxexport.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="SHA-256"):
        ex.load(str(damaged))
    for sidecar in (json.dumps(info)[:12], "[1, 2]", "{}"):  # a damaged sidecar no longer skips the check
        (tmp_path / "decision.jaxexport.json").write_text(sidecar)
        with pytest.raises(ValueError, match="sidecar .* is damaged"):
            ex.load(str(damaged))
    truncated = tmp_path / "cut.jaxexport"  # no sidecar to check: jax.export's own reading fails
    truncated.write_bytes(bytes(data[: len(data) // 3]))
    with pytest.raises(ValueError, match="not a whole exported decision"):
        ex.load(str(truncated))


def test_convenience_call_and_key_types(reloaded):
    depth, goal_mask, key, omega, _, init, _ = inputs(7)
    full = reloaded.call(depth, goal_mask, key, omega, np.int32(SPEC.planner.adam_steps), init, np.bool_(True))
    again = ex.call(reloaded, depth, goal_mask, jax.random.wrap_key_data(jnp.asarray(key)), int(omega), init=init)
    np.testing.assert_array_equal(np.asarray(full["push"]), np.asarray(again["push"]))
    for bad in ({"omega": int(omega) + 0.7}, {"omega": int(omega), "adam_steps": 2.5}):  # truncated to int before
        with pytest.raises(ValueError, match="must be a whole number"):
            ex.call(reloaded, depth, goal_mask, key, **bad)


def test_one_file_for_cpu_and_cuda(tiny_ckpt):
    """jax.export lowers the decision for both platforms at once, on a machine without a GPU, and the file reads back
    with both."""
    exported, info = ex.export_checkpoint(tiny_ckpt, SPEC, CAMERA, goal_samples=Q, platforms=("cpu", "cuda"))
    assert tuple(exported.platforms) == ("cpu", "cuda") and info["platforms"] == ["cpu", "cuda"]
    again = jax.export.deserialize(exported.serialize())
    assert tuple(again.platforms) == ("cpu", "cuda") and again.in_avals == exported.in_avals


def test_cli_writes_the_file_and_its_sidecar(tiny_ckpt, tmp_path, capsys):
    camera_json = tmp_path / "camera.json"
    camera_json.write_text(CAMERA.to_json())
    out = tmp_path / "robot" / "decision.jaxexport"
    summary = export_cli.main(["--ckpt", tiny_ckpt, "--out", str(out), "--samples", "4", "--adam-steps", "3",
                               "--horizon", "2", "--resolution", "12", "--camera", str(camera_json),
                               "--goal-samples", str(Q), "--platforms", "cpu"])
    assert out.stat().st_size == summary["bytes"] > 0
    assert "signature: (depth: float32[32, 32], goal_mask: bool[32, 32]" in capsys.readouterr().out
    info = json.loads((tmp_path / "robot" / "decision.jaxexport.json").read_text())
    assert [i["name"] for i in info["inputs"]] == list(ex.INPUT_NAMES)
    shapes = {i["name"]: (i["shape"], i["dtype"]) for i in info["inputs"]}
    assert shapes["depth"] == ([32, 32], "float32") and shapes["goal_mask"] == ([32, 32], "bool")
    assert shapes["key"] == ([2], "uint32") and shapes["omega"] == ([], "int32")
    assert shapes["init"] == ([2, 4], "float32") and shapes["warm"] == ([], "bool")
    outputs = {o["name"]: o["shape"] for o in info["outputs"]}
    assert list(outputs) == list(ex.OUTPUT_NAMES) and outputs["positions"] == [16, 3]  # ω 12's bucket: 16 slots
    assert info["capacity"] == 16 and info["perception"]["real_depth"] is True
    assert info["planner"]["samples"] == 4 and info["planner"]["adam_steps"] == 3 and info["planner"]["horizon"] == 2
    assert info["planner"]["reach"] == pytest.approx(0.2 + 0.005 + 0.002)  # pushes may start outside a wall
    assert info["checkpoint"]["step"] == STEP and info["platforms"] == ["cpu"] and "flatbuffers" in info["needs"]
    assert set(info["errors"]) == {str(b) for b in ex.ERRORS}
    exported = ex.load(str(out))
    assert [list(a.shape) for a in exported.in_avals] == [i["shape"] for i in info["inputs"]]
    assert not any(p.name.startswith(".tmp-") for p in out.parent.iterdir())  # atomic writes left nothing behind


def test_cli_refuses_before_work(tiny_ckpt, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        export_cli.main(["--ckpt", str(tmp_path / "nowhere"), "--out", str(tmp_path / "p.jaxexport")])
    assert exit_info.value.code == 2 and "no checkpoint" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:  # the tiny model holds 16 particles: ω 20's bucket is 32
        export_cli.main(["--ckpt", tiny_ckpt, "--resolution", "20", "--out", str(tmp_path / "p.jaxexport")])
    assert exit_info.value.code == 2 and "n_max = 16" in capsys.readouterr().err
    assert not (tmp_path / "p.jaxexport").exists()
    (tmp_path / "p.jaxexport.json").write_text('{"mine": 1}')  # a user's file where the sidecar would go
    with pytest.raises(SystemExit) as exit_info:
        export_cli.main(["--ckpt", tiny_ckpt, "--resolution", "12", "--out", str(tmp_path / "p.jaxexport")])
    assert exit_info.value.code == 2 and "is not an export's description" in capsys.readouterr().err
    assert (tmp_path / "p.jaxexport.json").read_text() == '{"mine": 1}' and not (tmp_path / "p.jaxexport").exists()
    with pytest.raises(SystemExit) as exit_info:
        export_cli.main(["--help"])
    assert exit_info.value.code == 0 and "pip install jax flatbuffers" in capsys.readouterr().out


@pytest.mark.slow
def test_plan_gives_the_exported_files_push(tiny_ckpt, tmp_path, capsys):
    """``dynres plan`` on a saved frame and the exported decision on the same frame, goal, key, ω and Adam steps: the
    same push (both decide through ``decision.perceive_and_decide``; the planner's defaults the export's)."""
    paths = frames.save_frame(str(tmp_path), frame(3), CAMERA)
    mask = disc_goal(CAMERA, np.array([0.03, -0.02]), 0.06)
    goal = frames.save_goal(str(tmp_path / "goal.png"), mask)
    shown = plan_cli.main(["--depth", paths["depth.png"], "--rgb", paths["rgb.png"], "--camera", paths["camera.json"],
                           "--goal", goal, "--ckpt", tiny_ckpt, "--dynamics", "learned", "--resolution", "12",
                           "--samples", "4", "--adam-steps", "3", "--seed", "5", "--out", str(tmp_path / "push.png")])
    capsys.readouterr()
    spec = DecisionSpec(16, PlannerConfig(samples=4, adam_steps=3, reach=wall_reach(SceneConfig.bin_half_width,
                                                                                    SceneConfig.plate_thickness)),
                        real_depth=True)
    exported, _ = ex.export_checkpoint(tiny_ckpt, spec, CAMERA, platforms=("cpu",))
    obs, _ = frames.load_frame(paths["depth.png"], paths["rgb.png"], paths["camera.json"])
    filed = ex.call(exported, obs.depth, frames.load_goal(goal, CAMERA), jax.random.PRNGKey(5), 12, 3)
    assert int(filed["error"]) == 0
    np.testing.assert_array_equal(np.asarray(filed["push"], np.float64), shown["push"])


@pytest.mark.slow
def test_a_file_with_a_judge_pushes_the_candidate_the_judge_rates_best(tiny_ckpt, reloaded, tmp_path):
    """export --judge: both models in one file; its push is, among the planner's M refined candidates and its best,
    the one whose rollout by the judge ends with the lowest c (a loop over the candidates, from the library's own
    decision on the same frame); the sidecar names the judge; a judge other than the planner's model changes pushes."""
    from dynres_jax.control.decision import goal_cost, perceive_and_decide

    cfg = DynamicsConfig(hidden=16, propagation_steps=1, bin_position=False, residual=False)  # residual: the sweep,
    judge_dir = tmp_path / "judge"  # as the planner's untrained residual model is
    ckpt.save_module(judge_dir, 3, Dynamics(cfg, rngs=nnx.Rngs(5)),
                     {"dynamics": dataclasses.asdict(cfg), "train": {"n_max": N_MAX}, "step": 3})
    exported, info = ex.export_checkpoint(tiny_ckpt, SPEC, CAMERA, goal_samples=Q, platforms=("cpu",),
                                          judge_dir=str(judge_dir))
    assert info["judge"]["step"] == 3 and info["checkpoint"]["step"] == STEP
    path = str(tmp_path / "judged.jaxexport")
    ex.save(exported, path, info)
    judged_file = ex.load(path)
    dynamics, _, _ = load_dynamics("learned", tiny_ckpt, 0.04)
    judge, _, _ = load_dynamics("learned", str(judge_dir), 0.04)
    changed = 0
    for i in range(6):
        call = inputs(i)
        depth, goal_mask, key, omega, steps, init, warm = call
        out = judged_file.call(*call)
        goal = make_goal(goal_mask, CAMERA, n_samples=Q)
        obs = frame(0)._replace(depth=jnp.asarray(depth))
        particles, _, result = perceive_and_decide(obs, goal, jnp.asarray(key), jnp.asarray(init), jnp.asarray(warm),
                                                   jnp.int32(omega), jnp.int32(steps), spec=SPEC, dynamics=dynamics,
                                                   camera=CAMERA)
        cost = goal_cost(goal, CAMERA, SPEC.capacity)
        model = judge(particles.radius)
        candidates = [*np.asarray(result.actions), np.asarray(result.best)]
        costs = [float(cost(model(particles.positions, particles.mask, jnp.asarray(c))[-1], particles.mask))
                 for c in candidates]
        pick = int(np.argmin(costs))
        np.testing.assert_allclose(np.asarray(out["best"]), candidates[pick], atol=1e-6, err_msg=f"frame {i}")
        assert float(out["best_cost"]) == pytest.approx(costs[pick], rel=1e-5, abs=1e-5)
        changed += not np.allclose(np.asarray(out["push"]), np.asarray(reloaded.call(*call)["push"]))
    assert changed > 0  # the judge's choice is not the planner's best on every frame
