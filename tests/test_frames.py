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
@pytest.mark.slow
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
    with pytest.raises(frames.FrameError, match="must be an 8-bit image, got uint16 \\(a depth frame\\?\\)"):
        frames.load_frame(paths["depth.png"], paths["depth.png"], paths["camera.json"])  # the depth as colour


def _exif_rotated(path, image, orientation=6):
    """Save ``image`` (grey or RGB uint8) as PNG or JPEG with an EXIF orientation tag (6: turn 90 degrees to show)."""
    from PIL import Image

    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(image).save(path, exif=exif.tobytes(), **({"quality": 100} if path.endswith(".jpg") else {}))
    assert cv2.imread(path, cv2.IMREAD_GRAYSCALE).shape[:2] == image.shape[:2][::-1]  # OpenCV would turn it
    return path


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_an_image_with_an_orientation_tag_is_refused_naming_it(saved, tmp_path, suffix):
    """A goal, a mask and a colour frame with an EXIF orientation tag other than "as stored" are refused, naming the
    tag: read as stored they lie turned against what a viewer showed; turned, against the depth frame (no tag). The
    same pixels without a tag (or tagged "as stored", 1) are read."""
    pytest.importorskip("PIL")
    env, state, paths = saved
    goal = disc_goal(env.camera, np.array([0.05, 0.02]), 0.06)
    tagged = _exif_rotated(str(tmp_path / f"goal{suffix}"), goal.astype(np.uint8) * 255)
    with pytest.raises(frames.FrameError, match="EXIF orientation tag \\(6"):
        frames.load_goal(tagged, env.camera)
    plain = str(tmp_path / f"plain{suffix}")
    from PIL import Image

    exif = Image.Exif()
    exif[0x0112] = 1
    Image.fromarray(goal.astype(np.uint8) * 255).save(plain, exif=exif.tobytes(),
                                                     **({"quality": 100} if suffix == ".jpg" else {}))
    np.testing.assert_array_equal(frames.load_goal(plain, env.camera), goal)
    if suffix == ".png":
        _exif_rotated(str(tmp_path / "rgb.png"), np.asarray(state.obs.rgb))
        with pytest.raises(frames.FrameError, match="colour file .* EXIF orientation"):
            frames.load_frame(paths["depth.png"], str(tmp_path / "rgb.png"), paths["camera.json"])


def test_goal_mask_with_an_orientation_tag_is_one_line(saved, tmp_path, capsys):
    pytest.importorskip("PIL")
    env, _, paths = saved
    big = cv2.resize(disc_goal(env.camera, np.array([0.08, 0.0]), 0.05).astype(np.uint8) * 255, (128, 128),
                     interpolation=cv2.INTER_NEAREST)
    tagged = _exif_rotated(str(tmp_path / "mask.png"), big, orientation=8)
    err = _one_line_error(["--mask", tagged, "--camera", paths["camera.json"], "--out", str(tmp_path / "g.png")],
                          capsys)
    assert "EXIF orientation tag (8" in err and not (tmp_path / "g.png").exists()


def _one_line_error(argv, capsys):
    from dynres_jax.commands import goal as goal_command

    with pytest.raises(SystemExit) as e:
        goal_command.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_a_fifo_a_device_or_a_folder_is_named_not_read(saved, tmp_path, capsys):
    """Where a file is expected, a FIFO (which would block the read forever), a device (/dev/null: no longer "does not
    exist") and a folder are refused in one line naming what they are, before anything opens them."""
    import os
    import threading

    _, _, paths = saved
    fifo = str(tmp_path / "pipe.png")
    os.mkfifo(fifo)
    found = {}

    def run():
        found["mask"] = _one_line_error(["--mask", fifo, "--camera", paths["camera.json"], "--out",
                                         str(tmp_path / "g.png")], capsys)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(30)
    if thread.is_alive():
        os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)  # unblock the reader before failing
        pytest.fail("goal --mask blocked on a FIFO")
    assert "FIFO" in found["mask"] and "--mask" in found["mask"]
    err = _one_line_error(["--disc", "0", "0", "0.05", "--camera", os.devnull, "--out", str(tmp_path / "g.png")],
                          capsys)
    assert "character device" in err and "does not exist" not in err
    err = _one_line_error(["--disc", "0", "0", "0.05", "--camera", str(tmp_path), "--out", str(tmp_path / "g.png")],
                          capsys)
    assert "is a folder" in err
    for path, says in ((fifo, "FIFO"), (os.devnull, "character device"), (str(tmp_path), "a folder")):
        with pytest.raises(frames.FrameError, match=says):
            frames.load_frame(path, paths["rgb.png"], paths["camera.json"])
        with pytest.raises(frames.FrameError, match=says):
            frames.load_goal(path, saved[0].camera)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        frames.load_camera(str(tmp_path / "none.json"))


@pytest.mark.parametrize("text, says", [
    ("[1, 2, 3]", "must be an object"), ('"camera"', "must be an object"), ("null", "must be an object"),
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"), ('{"K": ' + "[" * 5000 + "]" * 5000 + "}", "nested"),
    ("{WIDTH9}", "width must be a finite number"), ("{CENTRE}", "centre"), ("{K_STRINGS}", "K must be"),
    ("{NO_HEIGHT}", "lacks"), ("{HUGE}", "image size"), ("{BOOL}", "width must be"),
    ("{DISTORTED}", "lens distortion is not modelled"),
])
def test_bad_camera_json_is_one_line(saved, tmp_path, capsys, text, says):
    """Camera JSON that is not an object, nested deeply, with a 400-digit number, a camera 10^300 m away, strings,
    a missing field, an absurd size or a boolean is refused in one line naming the file, never a traceback."""
    good = json.load(open(saved[2]["camera.json"]))
    text = {"{WIDTH9}": json.dumps(good).replace(f'"width": {good["width"]}', '"width": ' + "9" * 400),
            "{CENTRE}": json.dumps({**good, "centre": [0, 0, 1e300]}),
            "{K_STRINGS}": json.dumps({**good, "K": [["1", "0", "0"]] * 3}),
            "{NO_HEIGHT}": json.dumps({k: v for k, v in good.items() if k != "height"}),
            "{HUGE}": json.dumps({**good, "width": 10**12}),
            "{BOOL}": json.dumps({**good, "width": True}),
            "{DISTORTED}": json.dumps({**good, "coeffs": [0.1, -0.05, 0, 0, 0]})}.get(text, text)
    path = tmp_path / "cam.json"
    path.write_text(text)
    with pytest.raises(frames.FrameError, match=says):
        frames.load_camera(str(path))
    err = _one_line_error(["--disc", "0", "0", "0.05", "--camera", str(path), "--out", str(tmp_path / "g.png")],
                          capsys)
    assert "camera file" in err and len(err) < 400, err


def test_goal_masks_read_as_gray_levels_in_every_layout_and_odd_ones_refused(saved, tmp_path, capsys):
    """The same disc saved as 8-bit gray, BGR, opaque BGRA and opaque gray + alpha reads as the same mask (by
    ``load_goal`` and by ``goal --mask``), as does 16-bit white on black; a 16-bit 0 / 1 mask (OpenCV would scale it
    to 0: "no goal pixel") and a shape drawn in transparency (white everywhere, the disc in alpha: "outside the
    workspace") are refused, naming why."""
    env, _, paths = saved
    goal = disc_goal(env.camera, np.array([0.02, -0.01]), 0.05)
    gray = goal.astype(np.uint8) * 255
    opaque = np.full_like(gray, 255)
    layouts = {"gray": gray, "bgr": np.dstack([gray] * 3), "bgra": np.dstack([gray] * 3 + [opaque]),
               "gray_alpha": np.dstack([gray, opaque])}
    for name, image in layouts.items():
        path = str(tmp_path / f"{name}.png")
        if name == "gray_alpha":  # OpenCV writes no two-channel PNG: Pillow's LA mode
            from PIL import Image
            Image.fromarray(image, "LA").save(path)
            assert cv2.imread(path, cv2.IMREAD_UNCHANGED).shape[-1] in (2, 4)
        else:
            cv2.imwrite(path, image)
        np.testing.assert_array_equal(frames.load_goal(path, env.camera), goal, err_msg=name)
    wide = str(tmp_path / "sixteen.png")
    cv2.imwrite(wide, goal.astype(np.uint16))  # 0 / 1 in 16 bits
    with pytest.raises(frames.FrameError, match="16-bit image with levels 0-1"):
        frames.load_goal(wide, env.camera)
    cv2.imwrite(wide, goal.astype(np.uint16) * 65535)  # white on black in 16 bits: the mask (as OpenCV read it)
    np.testing.assert_array_equal(frames.load_goal(wide, env.camera), goal)
    drawn = str(tmp_path / "alpha.png")
    cv2.imwrite(drawn, np.dstack([opaque] * 3 + [gray]))  # white, the disc opaque, the rest transparent
    with pytest.raises(frames.FrameError, match="transparent pixels"):
        frames.load_goal(drawn, env.camera)
    err = _one_line_error(["--mask", drawn, "--camera", paths["camera.json"], "--out", str(tmp_path / "g.png")],
                          capsys)
    assert "transparent pixels" in err and not (tmp_path / "g.png").exists()
