"""Recorded frames: the simulator's frames saved as a depth camera would, read back, and planned on."""

import json

import cv2
import jax
import numpy as np
import pytest

from dynres_jax.commands import plan
from dynres_jax.config import CameraConfig, SceneConfig, SimConfig
from dynres_jax.control.goals import disc_goal
from dynres_jax.io import frames
from dynres_jax.sim.env import PileEnv


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    env = PileEnv(SimConfig(scene=SceneConfig(pieces=(8,)), camera=CameraConfig(width=64, height=64)),
                  backend="mujoco")
    state = env.reset(jax.random.PRNGKey(0))
    folder = tmp_path_factory.mktemp("frame")
    paths = frames.save_frame(str(folder), state.obs, env.camera)
    goal = disc_goal(env.camera, np.array([0.0, 0.0]), 0.06)
    paths["goal.png"] = str(folder / "goal.png")
    cv2.imwrite(paths["goal.png"], goal.astype(np.uint8) * 255)
    return env, state, paths


def test_round_trip_keeps_depth_to_a_millimetre(saved):
    env, state, paths = saved
    obs, camera = frames.load_frame(paths["depth.png"], paths["rgb.png"], paths["camera.json"])
    assert camera == env.camera
    np.testing.assert_allclose(obs.depth, np.asarray(state.obs.depth), atol=0.0005 + 1e-6)
    np.testing.assert_array_equal(obs.rgb, np.asarray(state.obs.rgb))


@pytest.mark.parametrize("camera_flags", [[], ["--no-real-depth"], ["--sensor", "realsense"],
                                          ["--sensor", "realsense", "--calibrate"]])
def test_plan_command_prints_a_push_of_the_action_space(saved, tmp_path, capsys, camera_flags):
    _, _, paths = saved
    out = plan.main(["--depth", paths["depth.png"], "--rgb", paths["rgb.png"], "--camera", paths["camera.json"],
                     "--goal", paths["goal.png"], "--resolution", "6", "--samples", "4", "--adam-steps", "5",
                     "--dynamics", "sweep", "--out", str(tmp_path / "push.png"), *camera_flags])
    said = capsys.readouterr()
    printed = json.loads(said.out.strip())  # stdout is the JSON alone; the wait is announced on stderr
    assert "planning at ω = 6" in said.err
    # a push ends within the bound and starts there or outside a wall (the closed loop's action space, sim.pushes)
    assert printed["push"] == out["push"] and np.all(np.abs(out["push"][2:]) <= 0.18 + 1e-6)
    assert np.all(np.abs(out["push"][:2]) <= 0.2 + 0.005 + 0.002 + 1e-6)
    assert cv2.imread(str(tmp_path / "push.png")) is not None


def test_bad_files_are_named(saved, tmp_path):
    _, _, paths = saved
    with pytest.raises(FileNotFoundError, match="depth file"):
        frames.load_frame(str(tmp_path / "none.png"), paths["rgb.png"], paths["camera.json"])
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match="not a readable image"):
        frames.load_frame(str(tmp_path / "junk.png"), paths["rgb.png"], paths["camera.json"])
    with pytest.raises(ValueError, match="16-bit"):
        frames.load_frame(paths["rgb.png"], paths["rgb.png"], paths["camera.json"])
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(ValueError, match="goal file"):
        frames.load_goal(str(tmp_path / "small.png"), frames.load_frame(
            paths["depth.png"], paths["rgb.png"], paths["camera.json"])[1])


def test_goal_command_writes_what_load_goal_reads(saved, tmp_path, capsys):
    """``dynres goal``: a disc and a letter drawn through a saved camera equal the library's masks as ``load_goal``
    reads them back; a mask drawn at twice the camera's size comes back at its size; the default camera is the
    simulator's."""
    from dynres_jax.commands import goal
    from dynres_jax.control.goals import text_goal
    from dynres_jax.sim.camera import Camera

    env, _, paths = saved
    disc, letter, mask = (str(tmp_path / f"{n}.png") for n in ("disc", "letter", "mask"))
    goal.main(["--disc", "0.02", "-0.03", "0.06", "--camera", paths["camera.json"], "--out", disc])
    np.testing.assert_array_equal(frames.load_goal(disc, env.camera), disc_goal(env.camera, [0.02, -0.03], 0.06))
    goal.main(["--letter", "U", "--height", "0.12", "--centre", "0.01", "0", "--camera", paths["camera.json"],
               "--out", letter])
    want = text_goal(env.camera, "U", [0.01, 0.0], 0.12)
    np.testing.assert_array_equal(frames.load_goal(letter, env.camera), want)
    big = str(tmp_path / "big.png")
    cv2.imwrite(big, cv2.resize(want.astype(np.uint8) * 255, (128, 128), interpolation=cv2.INTER_NEAREST))
    goal.main(["--mask", big, "--camera", paths["camera.json"], "--out", mask])
    np.testing.assert_array_equal(frames.load_goal(mask, env.camera), want)
    default = goal.main(["--disc", "0", "0", "0.08", "--out", str(tmp_path / "default.png")])
    assert (default["width"], default["height"]) == (Camera.top_down(CameraConfig()).width, CameraConfig().height)
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["pixels"] == default["pixels"] > 0


def test_a_missing_reading_round_trips_as_missing(saved, tmp_path):
    """A depth camera's missing readings (``NO_READING`` m) are saved as 0 mm and read back as missing, not as the
    65.535 m a clipped uint16 would say."""
    from dynres_jax.sim.sensor import NO_READING

    env, state, _ = saved
    depth = np.asarray(state.obs.depth).copy()
    depth[:5, :5] = NO_READING
    paths = frames.save_frame(str(tmp_path), state.obs._replace(depth=depth), env.camera)
    back, _ = frames.load_frame(paths["depth.png"], paths["rgb.png"], paths["camera.json"])
    assert np.all(np.asarray(back.depth)[:5, :5] == NO_READING)
    np.testing.assert_allclose(np.asarray(back.depth)[5:], depth[5:], atol=6e-4)


def test_implausible_frames_are_refused_before_planning(saved, tmp_path):
    """A frame must show a table where its camera says the table is: a depth scaled by 2, uniform noise around the
    table's depth, or a camera file whose pose sits 1 mm above the table are each refused naming the files; the true
    frame and a frame 1 cm off (a calibration error) are read."""
    env, _, paths = saved
    depth = cv2.imread(paths["depth.png"], cv2.IMREAD_UNCHANGED)
    camera = json.load(open(paths["camera.json"]))

    def load(depth_mm=depth, **camera_changes):
        cv2.imwrite(str(tmp_path / "d.png"), np.asarray(depth_mm, np.uint16))
        json.dump(dict(camera, **camera_changes), open(tmp_path / "c.json", "w"))
        return frames.load_frame(str(tmp_path / "d.png"), paths["rgb.png"], str(tmp_path / "c.json"))

    load()
    load(depth + 10)  # 1 cm further: a calibration error, not a wrong frame
    table = np.median(depth[depth > 0])
    noise = np.random.default_rng(0).uniform(table - 300, table + 300, depth.shape)  # around the table, not on it
    low = dict(centre=[*camera["centre"][:2], 0.001])
    for depth_mm, changes, says in ((depth * 2, {}, "median point lies"), (noise, {}, "of the readings lie within"),
                                    (depth, low, "median point lies")):
        with pytest.raises(frames.FrameError, match=says):
            load(depth_mm, **changes)
