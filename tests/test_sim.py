"""Simulator: scenes, pushes, backends, vmap, camera and renderer, bad input. Small scenes, compiled once a module."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from dynres_jax.config import KINDS, CameraConfig, PileConfig, PushConfig, SceneConfig, SimConfig
from dynres_jax.sim.camera import Camera
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.physics.mjx_step import traced_template
from dynres_jax.sim.scene import GROUP_PIECES, build_scene

SMALL_PUSH = PushConfig(max_length=0.1, settle_time=0.06)
CAM = CameraConfig(width=48, height=48)
# One piece in the plate's path, two far from it.
XY = np.array([[-0.05, 0.0], [0.12, 0.14], [-0.13, -0.12]])
ACTION = np.array([-0.1, 0.0, 0.0, 0.0], np.float32)


def small_config(joints="planar", kinds=("coffee",), pieces=(3,)):
    return SimConfig(scene=SceneConfig(kinds=kinds, pieces=pieces, joints=joints), push=SMALL_PUSH, camera=CAM)


@pytest.fixture(scope="module")
def envs():
    cfg = small_config()
    return {b: PileEnv(cfg, backend=b) for b in ("mujoco", "mjx")}


@pytest.fixture(scope="module")
def pushed(envs):
    """Each backend: the hand-placed world, and the world after ACTION."""
    out = {}
    for b, env in envs.items():
        s0 = env.place(XY)
        out[b] = (s0, env.push(s0, ACTION))
    return out


@pytest.mark.parametrize("joints", ["planar", "free"])
@pytest.mark.parametrize("kind", sorted(KINDS))
def test_scene_builds_every_kind(kind, joints):
    scene = build_scene(SceneConfig(kinds=(kind,), pieces=(4,), joints=joints))
    assert scene.n_pieces == 4 and scene.model.nbody == 2 + 4  # world, pusher, pieces
    planar_dofs = 2 if KINDS[kind].geom == "sphere" else 3  # spheres have no yaw joint by default
    assert scene.model.nv == 4 * (planar_dofs if joints == "planar" else 6)
    assert np.all(scene.rest_height > 0) and np.all(scene.footprint >= scene.rest_height - 1e-9)
    assert np.all(scene.model.geom_group[scene.geom_id] == GROUP_PIECES)


def test_two_kind_scene_for_sort():
    scene = build_scene(SceneConfig(kinds=("coffee", "candy"), pieces=(3, 2)))
    assert scene.kind.tolist() == [0, 0, 0, 1, 1]
    assert not np.allclose(scene.rgb[0], scene.rgb[-1])
    assert scene.geom_type.tolist() == [0, 0, 0, 2, 2]


def test_granola_sizes_are_mixed():
    scene = build_scene(SceneConfig(kinds=("granola",), pieces=(20,)))
    assert scene.size[:, 0].std() > 0.001


@pytest.mark.parametrize("bad, message", [
    (dict(kinds=("pebble",), pieces=(3,)), "unknown piece kind 'pebble'"),
    (dict(pieces=(0,)), "between 1 and 10000 pieces"), (dict(pieces=(10_001,)), "between 1 and 10000 pieces"),
    (dict(kinds=("coffee", "candy"), pieces=(3,)), "equal length"),
    (dict(joints="hinged"), "joints must be"),
])
def test_bad_scene_config_names_the_problem(bad, message):
    with pytest.raises(ValueError, match=message):
        SceneConfig(**bad)


def test_too_many_pieces_for_the_bin():
    """Refused from the config, before MuJoCo compiles anything."""
    with pytest.raises(ValueError, match=r"500 candy pieces cover 238% of the bin's floor \(at most 50%"):
        PileEnv(SimConfig(scene=SceneConfig(kinds=("candy",), pieces=(500,))), backend="mujoco", render=False)


@pytest.mark.parametrize("backend", ["mujoco", "mjx"])
def test_push_moves_what_it_should(pushed, envs, backend):
    s0, s1 = pushed[backend]
    env = envs[backend]
    front = ACTION[2] + env.config.scene.plate_thickness / 2 + env.scene.footprint[0]
    assert np.allclose(np.asarray(s0.pos[:, :2]), XY, atol=1e-3), "placing pieces moved them"
    assert float(s1.pos[0, 0]) > front - 0.004, "the piece in the plate's path did not travel with it"
    assert abs(float(s1.pos[0, 1])) < 0.01, "the pushed piece left the push line"
    moved = np.linalg.norm(np.asarray(s1.pos - s0.pos), axis=1)
    assert np.all(moved[1:] < 0.001), f"pieces far from the plate moved {moved[1:]}"
    assert not bool(s1.broken)


def test_backends_agree(pushed):
    """C MuJoCo (float64) and MJX (float32) leave the pushed piece within 3 mm of each other."""
    a, b = np.asarray(pushed["mujoco"][1].pos), np.asarray(pushed["mjx"][1].pos)
    assert np.max(np.linalg.norm(a - b, axis=1)) < 0.003


def test_reset_is_reproducible_and_settled(envs):
    env = envs["mujoco"]
    a, b = env.reset(jax.random.PRNGKey(7)), env.reset(jax.random.PRNGKey(7))
    np.testing.assert_array_equal(np.asarray(a.qpos), np.asarray(b.qpos))
    assert not np.allclose(np.asarray(env.reset(jax.random.PRNGKey(8)).qpos), np.asarray(a.qpos))
    assert np.all(np.abs(np.asarray(a.pos[:, :2])) < env.config.scene.bin_half_width)


def test_free_pieces_rest_on_the_table():
    env = PileEnv(small_config(joints="free", kinds=("coffee", "almond", "candy"), pieces=(2, 2, 2)),
                  backend="mujoco", render=False)
    s = env.push(env.reset(jax.random.PRNGKey(0)), env.sample_push(jax.random.PRNGKey(1), env.reset(
        jax.random.PRNGKey(0)).pos))
    sink = env.scene.rest_height - np.asarray(s.pos[:, 2])
    assert np.all(sink < 0.0015), f"pieces sank {sink * 1000} mm"
    assert not bool(s.broken)


@pytest.mark.parametrize("action, message", [
    ([0.0, 0.0, np.nan, 0.0], "NaN"),
    ([0.0, 0.0, 0.3, 0.0], "outside the workspace"),
    ([0.0, 0.0, 0.0, 0.0], "push length"),
    ([-0.1, 0.0, 0.1, 0.0], "push length"),
    ([0.0, 0.0, 0.05], "shape"),
])
def test_bad_action_names_the_problem(envs, action, message):
    state = None  # checked before the state is touched
    with pytest.raises(ValueError, match=message):
        envs["mujoco"].push(state, action)


def test_actions_on_the_length_bounds_in_float32_pass_the_check(envs):
    """The planner projects lengths onto [min_length, max_length] in float32; such pushes must be accepted."""
    env = envs["mujoco"]
    p = env.config.push
    for length in (p.min_length, p.max_length):
        a = np.array([0.0, 0.0, np.float32(length) * np.float32(1 - 3e-7), 0.0], np.float32)
        env.check_action(a)


def test_traced_nan_action_flags_the_world_broken(envs, pushed):
    env = envs["mjx"]
    s = jax.jit(env.push)(pushed["mjx"][0], jnp.array([0.0, 0.0, jnp.nan, 0.0]))
    assert bool(s.broken)
    assert np.all(np.isfinite(np.asarray(s.pos)))


def test_traced_template_rebuilds_zeros_inside_the_trace_not_as_constants():
    data0 = {"contacts": jnp.zeros((4096, 8)), "qpos0": jnp.arange(3.0), "mixed": jnp.array([0.0, 1.0])}
    template = traced_template(data0)
    jax.tree.map(np.testing.assert_array_equal, jax.jit(template)(), data0)  # equal values
    captured = jax.make_jaxpr(lambda: data0)().consts  # the plain closure: every array is a constant
    rebuilt = jax.make_jaxpr(template)().consts
    assert max(c.size for c in captured) == 4096 * 8
    assert max((np.size(c) for c in rebuilt), default=0) == 3  # only the non-zero arrays stay constants


def test_unknown_backend():
    with pytest.raises(ValueError, match="backend"):
        PileEnv(small_config(), backend="flex")


def test_projection_round_trip():
    cam = Camera.top_down(CameraConfig(width=64, height=48))
    pts = np.random.default_rng(0).uniform([-0.2, -0.2, 0.0], [0.2, 0.2, 0.05], size=(50, 3))
    uv, z = cam.world_to_pixel(pts)
    np.testing.assert_allclose(np.asarray(cam.pixel_to_world(uv, z)), pts, atol=1e-6)  # float32: a micrometre
    # the bin's +x, +y corner appears right and up in the image
    uv_c, _ = cam.world_to_pixel(np.array([0.2, 0.2, 0.0]))
    assert uv_c[0] > cam.width / 2 and uv_c[1] < cam.height / 2


def test_camera_json_round_trip():
    cam = Camera.top_down(CameraConfig())
    back = Camera.from_json(cam.to_json())
    np.testing.assert_array_equal(back.K, cam.K)
    assert back == cam and hash(back) == hash(cam)  # so jit reuses what it compiled for an equal camera
    assert back != Camera.top_down(CameraConfig(width=64))
    with pytest.raises(ValueError, match="lacks"):
        Camera.from_json('{"K": [[1,0,0],[0,1,0],[0,0,1]]}')


@pytest.mark.parametrize("joints", ["planar", "free"])
def test_rendered_depth_matches_mujoco_ray_casts(joints):
    """Every pixel a piece covers: our depth equals mj_ray's distance within 1 mm, and the same piece is hit."""
    cfg = SimConfig(scene=SceneConfig(kinds=("coffee", "almond", "candy"), pieces=(4, 4, 4), joints=joints),
                    camera=CameraConfig(width=96, height=96), pile=PileConfig(layout="spread"))
    env = PileEnv(cfg, backend="mujoco")
    state = env.reset(jax.random.PRNGKey(2))
    m, d = env.scene.model, mujoco.MjData(env.scene.model)
    d.qpos[:] = np.asarray(state.qpos, np.float64)
    mujoco.mj_forward(m, d)
    cam, obs = env.camera, state.obs
    piece_of_geom = {g: i for i, g in enumerate(env.scene.geom_id)}
    rows, cols = np.nonzero(np.asarray(obs.piece) >= 0)
    assert len(rows) > 100
    dirs = np.asarray(cam.ray_directions(np.stack([cols + 0.5, rows + 0.5], -1)), np.float64)
    groups = np.zeros(6, np.uint8)
    groups[GROUP_PIECES] = 1
    geomid = np.zeros(1, np.int32)
    for r, c, vec in zip(rows, cols, dirs, strict=True):
        t = mujoco.mj_ray(m, d, cam.centre, vec, groups, 1, -1, geomid)
        assert t > 0, f"mj_ray missed pixel {(r, c)} that we render as piece {obs.piece[r, c]}"
        assert abs(t - float(obs.depth[r, c])) < 1e-3
        assert piece_of_geom[int(geomid[0])] == int(obs.piece[r, c])
    assert np.all(np.asarray(obs.kind)[rows, cols] == env.scene.kind[np.asarray(obs.piece)[rows, cols]])


def test_place_refuses_pieces_outside_the_bin_or_not_finite(envs):
    """Hand-placed pieces beyond the bin's walls or at NaN: a ValueError naming it (MuJoCo put them somewhere else, or
    reset the world to its default pose, and said nothing)."""
    env = next(iter(envs.values()))
    for xy, says in ((np.full((len(XY), 2), 0.5), "outside the bin"), (np.full((len(XY), 2), np.nan), "finite xy")):
        with pytest.raises(ValueError, match=says):
            env.place(xy)
    with pytest.raises(ValueError, match="finite xy and yaw"):
        env.place(XY, yaw=np.array([0.0, np.inf, 0.0]))
