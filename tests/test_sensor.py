"""The depth-camera profile (sim.sensor) and perception's answer to it (perception.foreground(real_depth=True))."""

import json

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.config import DEFAULT_PIECES, CameraConfig, SceneConfig, SimConfig
from dynres_jax.perception import calibrate, foreground, median_depth, sample_particles, table_height
from dynres_jax.sim.camera import Camera, Observation
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.sensor import NO_READING, DepthSensor


def _flat(depth_m, size=64):
    z = jnp.full((size, size), depth_m, jnp.float32)
    zeros = jnp.zeros((size, size), jnp.int32)
    return Observation(z, zeros - 1, zeros - 1, jnp.zeros((size, size, 3), jnp.uint8))


def test_noise_grows_with_distance_squared_and_readings_are_whole_millimetres():
    sensor = DepthSensor(quantum=1e-6, dropout=0.0)
    sd = [float(jnp.std(sensor.observe(_flat(z), jax.random.PRNGKey(0)).depth)) for z in (1.0, 2.0)]
    for z, s in zip((1.0, 2.0), sd, strict=True):
        assert s == pytest.approx(sensor.noise_per_m2 * z**2, rel=0.05)
    depth = np.asarray(DepthSensor().observe(_flat(1.0), jax.random.PRNGKey(1)).depth)
    readings = depth[depth < NO_READING]
    np.testing.assert_allclose(readings * 1000, np.round(readings * 1000), atol=1e-3)
    assert 0 < np.mean(depth == NO_READING) < 0.02  # dropout only: a flat table has no edges


def test_edges_lose_readings_or_fly_and_flat_regions_do_not():
    """A step of 1 cm: the two pixel columns at the step are edges; about edge_drop of them are missing and about
    flying of them sit between the two levels; away from the step, only dropout removes readings."""
    z = np.full((64, 64), 1.0, np.float32)
    z[:, 32:] = 0.99
    obs = _flat(1.0)._replace(depth=jnp.asarray(z))
    sensor = DepthSensor(noise_per_m2=0.0, dropout=0.0, quantum=1e-6)
    depth = np.asarray(sensor.observe(obs, jax.random.PRNGKey(2)).depth)
    edge = depth[:, 31:33]
    assert np.mean(edge == NO_READING) == pytest.approx(sensor.edge_drop * (1 - sensor.flying), abs=0.1)
    between = (edge > 0.9901) & (edge < 0.9999)
    assert np.mean(between) == pytest.approx(sensor.flying, abs=0.1)
    np.testing.assert_array_equal(np.delete(depth, [31, 32], axis=1), np.delete(z, [31, 32], axis=1))


def test_the_believed_camera_is_off_by_the_calibration_error():
    camera = Camera.top_down(CameraConfig())
    sensor = DepthSensor()
    seen = sensor.believed_camera(camera, seed=3)
    np.testing.assert_allclose(seen.rotation @ seen.rotation.T, np.eye(3), atol=1e-12)
    cos = (np.trace(seen.rotation @ camera.rotation.T) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) == pytest.approx(sensor.tilt_deg, rel=1e-6)
    assert np.linalg.norm(seen.centre - camera.centre) == pytest.approx(sensor.shift_m)
    assert seen == sensor.believed_camera(camera, seed=3) != camera


def test_median_and_table_plane_by_hand():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 1.0, size=(6, 7)).astype(np.float32)  # readings: finite, > 0 (sensor.is_reading)
    out = np.asarray(median_depth(jnp.asarray(depth)))
    padded = np.pad(depth, 1, mode="edge")
    expect = np.array([[np.median(padded[i:i + 3, j:j + 3]) for j in range(7)] for i in range(6)])
    np.testing.assert_allclose(out, expect)
    holes = depth.copy()
    holes[rng.random(depth.shape) < 0.3] = NO_READING
    holes[:3, :3] = NO_READING  # a pixel whose nine readings are all missing stays missing
    padded = np.pad(holes, 1, mode="edge")
    given = [[padded[i:i + 3, j:j + 3][padded[i:i + 3, j:j + 3] < NO_READING] for j in range(7)] for i in range(6)]
    expect = np.array([[np.median(g) if g.size else NO_READING for g in row] for row in given])
    np.testing.assert_allclose(np.asarray(median_depth(jnp.asarray(holes))), expect)
    xy = rng.uniform(-0.2, 0.2, (400, 2))
    z = 0.004 * xy[:, 0] - 0.002 * xy[:, 1] + 0.0015
    z[:60] += 0.02  # a pile on a tilted, lifted table: the plane fit ignores it
    points = jnp.asarray(np.c_[xy, z], jnp.float32)
    fit = np.asarray(table_height(points, jnp.ones(400, bool)))
    np.testing.assert_allclose(fit, 0.004 * xy[:, 0] - 0.002 * xy[:, 1] + 0.0015, atol=1e-5)


@pytest.fixture(scope="module")
def pile():
    env = PileEnv(SimConfig(scene=SceneConfig(pieces=(100,))), backend="mujoco")
    return env, env.reset(jax.random.PRNGKey(0)).obs


@pytest.mark.parametrize("seed", range(3))
def test_calibration_from_the_bin_takes_out_the_extrinsic_error(pile, seed):
    """Every pixel of the bin's floor and pile, put into the world through the true depth: through the believed camera
    it lands millimetres off (the tilt moves the table sideways), through the camera refined from a noisy frame
    within half a millimetre. The true camera on an exact frame is left as it is."""
    env, obs = pile
    sensor, scene = DepthSensor(), env.config.scene
    uv, depth = env.camera.pixel_centres().reshape(-1, 2), np.asarray(obs.depth).reshape(-1)
    truth = np.asarray(env.camera.pixel_to_world(uv, depth))
    floor = np.all(np.abs(truth[:, :2]) < scene.bin_half_width - 0.01, axis=1)
    believed = sensor.believed_camera(env.camera, seed)
    refined = calibrate(sensor.observe(obs, jax.random.PRNGKey(seed)), believed,
                        bin_half_width=scene.bin_half_width, wall_height=scene.wall_height)
    error = [np.linalg.norm(np.asarray(c.pixel_to_world(uv, depth))[floor] - truth[floor], axis=1).mean()
             for c in (believed, refined)]
    assert error[0] > 0.003 and error[1] < 0.0005, error
    same = calibrate(obs, env.camera, bin_half_width=scene.bin_half_width, wall_height=scene.wall_height)
    np.testing.assert_allclose(same.rotation, env.camera.rotation, atol=1e-9)
    np.testing.assert_allclose(same.centre, env.camera.centre, atol=1e-6)


def test_calibration_names_walls_out_of_view():
    env = PileEnv(SimConfig(scene=SceneConfig(pieces=(20,)), camera=CameraConfig(view_half_width=0.15)),
                  backend="mujoco")
    with pytest.raises(ValueError, match="bin walls across x in view"):
        calibrate(env.reset(jax.random.PRNGKey(0)).obs, env.camera, bin_half_width=0.2, wall_height=0.04)


@pytest.mark.parametrize("kind", ["coffee", "rice"])
def test_perception_through_the_profile_sees_the_pile_it_sees_without(kind):
    """Noise, holes, flying pixels and the calibration error: without real_depth, hundreds of pixels far from the pile
    become foreground; with it (and the camera calibrated from the frame), at most a few, and most of the pile's own
    pixels are found, rice's thin grains included; the particles' covering radius stays within 15 %."""
    env = PileEnv(SimConfig(scene=SceneConfig(kinds=(kind,), pieces=(DEFAULT_PIECES[kind],))), backend="mujoco")
    obs, scene = env.reset(jax.random.PRNGKey(1)).obs, env.config.scene
    sensor = DepthSensor()
    noisy = sensor.observe(obs, jax.random.PRNGKey(1))
    camera = calibrate(noisy, sensor.believed_camera(env.camera), bin_half_width=scene.bin_half_width,
                       wall_height=scene.wall_height)
    pile = np.asarray(foreground(obs, env.camera)[1]).reshape(env.camera.height, env.camera.width)
    near = cv2.dilate(pile.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # the pile and two pixels around it
    naive, robust = (np.asarray(foreground(noisy, camera, real_depth=r)[1]).reshape(pile.shape) for r in (False, True))
    assert np.sum(naive & ~near) > 200 and np.sum(robust & ~near) <= 5, (np.sum(naive & ~near), np.sum(robust & ~near))
    assert np.sum(robust & pile) / np.sum(pile) > (0.6 if kind == "rice" else 0.9)
    r_clean = float(sample_particles(obs, env.camera, 50, jax.random.PRNGKey(2), 64).radius)
    r_robust = float(sample_particles(noisy, camera, 50, jax.random.PRNGKey(2), 64, real_depth=True).radius)
    assert abs(r_robust / r_clean - 1) < 0.15, (r_clean, r_robust)


@pytest.mark.slow
def test_evaluate_runs_through_the_sensor(tmp_path):
    """``evaluate --sensor realsense`` plans on the camera's depth and records it; d is measured on the true state."""
    from dynres_jax.commands import evaluate

    summary = evaluate.main(["--quick", "--dynamics", "sweep", "--workers", "2", "--episodes", "2", "--mpc-steps", "1",
                             "--methods", "50", "--samples", "4", "--adam-steps", "2", "--sensor", "realsense",
                             "--out", str(tmp_path)])
    assert summary["sensor"] == "realsense" and np.isfinite(summary["methods"]["50"]["final_distance"])
    with open(tmp_path / "50.json") as f:
        run = json.load(f)
    start, final = np.array(run["start_pieces"]), np.array(run["final_pieces"])  # where every piece began and ended
    assert start.shape == final.shape == (2, summary["pieces"], 2) and np.all(np.abs(final) < 0.2)
    assert np.any(np.abs(final - start) > 1e-3)  # the push moved pieces
