"""Perception h: point cloud, FPS (against a brute-force NumPy FPS), re-centring, sample_particles, bad input."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax import perception
from dynres_jax.config import KINDS, CameraConfig, SceneConfig, SimConfig
from dynres_jax.perception import fps, point_cloud, random_start, recentre, sample_particles
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.sensor import NO_READING, is_reading, readings

N_MAX = 16


def brute_force_fps(points, valid, n, start):
    """FPS from scratch at every pick: the valid point whose distance to its nearest chosen point is largest
    (lowest index on ties); radius[i] that distance, radius[0] = inf."""
    points = np.asarray(points, np.float32)
    chosen, radius = [int(start)], [np.inf]
    for _ in range(1, n):
        best, best_d2 = -1, -np.inf
        for k in range(len(points)):
            if not valid[k]:
                continue
            d2 = np.min(np.sum(np.square(points[k] - points[chosen]), axis=-1))
            if d2 > best_d2:
                best, best_d2 = k, d2
        chosen.append(best)
        radius.append(np.sqrt(max(best_d2, 0.0)))
    return np.array(chosen), np.array(radius, np.float32)


def random_cloud(seed, p=120, invalid_fraction=0.3):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.2, 0.2, (p, 3)).astype(np.float32)
    valid = rng.uniform(size=p) > invalid_fraction
    start = int(rng.choice(np.flatnonzero(valid)))
    return points, valid, start


# ----------------------------------------------------------------------------------------------------------------
# FPS
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fps_matches_brute_force(seed):
    points, valid, start = random_cloud(seed)
    n = 30
    indices, radius = fps(points, valid, n, start)
    ref_indices, ref_radius = brute_force_fps(points, valid, n, start)
    np.testing.assert_array_equal(np.asarray(indices), ref_indices)
    np.testing.assert_allclose(np.asarray(radius), ref_radius, rtol=1e-5)
    assert np.all(valid[np.asarray(indices)])


def test_fps_past_the_valid_count_repeats_valid_points():
    points, valid, start = random_cloud(3, p=40, invalid_fraction=0.5)
    n = int(valid.sum()) + 5
    indices, radius = fps(points, valid, n, start)
    ref_indices, ref_radius = brute_force_fps(points, valid, n, start)
    np.testing.assert_array_equal(np.asarray(indices), ref_indices)
    np.testing.assert_allclose(np.asarray(radius), ref_radius, rtol=1e-5)
    k = int(valid.sum())
    assert sorted(np.asarray(indices)[:k].tolist()) == np.flatnonzero(valid).tolist()
    assert np.all(np.asarray(radius)[k:] == 0) and np.all(valid[np.asarray(indices)])


def test_fps_prefix_and_radius_mask():
    points, valid, start = random_cloud(4, p=200)
    indices, radius = (np.asarray(a) for a in fps(points, valid, 40, start))
    assert radius[0] == np.inf and np.all(np.diff(radius[1:]) <= 0)
    for k in (1, 2, 7, 25):
        np.testing.assert_array_equal(np.asarray(fps(points, valid, k, start)[0]), indices[:k])
    # a covering-radius resolution is a prefix mask: the kept prefix covers the valid cloud within r
    r = float(radius[20] + radius[21]) / 2
    kept = indices[radius > r]
    assert len(kept) == 21
    np.testing.assert_array_equal(kept, indices[: len(kept)])
    d = np.linalg.norm(points[valid][:, None] - points[kept][None], axis=-1).min(1)
    assert d.max() <= r + 1e-6 and d.max() == pytest.approx(radius[len(kept)], rel=1e-5)


def test_fps_padding_inert():
    points, valid, start = random_cloud(5)
    garbage = np.where(valid[:, None], points, np.float32(1e6) * np.sign(points + 1e-3)).astype(np.float32)
    a, b = fps(points, valid, 30, start), fps(garbage, valid, 30, start)
    np.testing.assert_array_equal(np.asarray(a[0]), np.asarray(b[0]))
    np.testing.assert_array_equal(np.asarray(a[1]), np.asarray(b[1]))


def test_random_start_is_valid_and_varies():
    valid = jnp.asarray(np.random.default_rng(6).uniform(size=500) > 0.8)
    starts = np.asarray(jax.vmap(random_start, (0, None))(jax.random.split(jax.random.PRNGKey(0), 64), valid))
    assert np.all(np.asarray(valid)[starts]) and len(set(starts.tolist())) > 20
    assert int(random_start(jax.random.PRNGKey(0), jnp.zeros(10, bool))) == 0


def test_recentre_moves_to_mean_of_points_in_reach():
    points = jnp.array([[0.0, 0, 0], [0.01, 0, 0], [0.002, 0.004, 0], [0.5, 0, 0], [0.003, 0, 0]])
    valid = jnp.array([True, True, True, True, False])  # the last is masked: never counted
    out = np.asarray(recentre(points[:1], points, valid, 0.005))
    np.testing.assert_allclose(out[0], [0.001, 0.002, 0.0], atol=1e-7)
    np.testing.assert_allclose(np.asarray(recentre(points[:1], points, valid, 0.0)), points[:1])


# ----------------------------------------------------------------------------------------------------------------
# Observations from a rendered pile
# ----------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def env():
    return PileEnv(SimConfig(scene=SceneConfig(kinds=("coffee", "candy"), pieces=(6, 4)),
                             camera=CameraConfig(width=64, height=64)), backend="mujoco")


@pytest.fixture(scope="module")
def states(env):
    return [env.reset(jax.random.PRNGKey(i)) for i in range(2)]


def xy_distance_to_pieces(points, state):
    """[M, N] xy distance (m) from each point to each true piece centre."""
    return np.linalg.norm(np.asarray(points)[:, None, :2] - np.asarray(state.pos)[None, :, :2], axis=-1)


def test_point_cloud_lies_on_pieces(env, states):
    state = states[0]
    points, valid = (np.asarray(a) for a in point_cloud(state.obs, env.camera))
    assert points.shape == (64 * 64, 3) and valid.sum() > 20
    d = xy_distance_to_pieces(points[valid], state)
    assert np.all(np.min(d - env.scene.footprint[None], axis=1) < 1e-4)  # inside some piece's footprint
    assert np.all(np.asarray(state.obs.piece).reshape(-1)[valid] >= 0)
    assert np.all(points[valid, 2] > perception.FOREGROUND_MARGIN) and np.all(points[~valid] == 0)
    # every piece shows up
    assert np.all(d.min(0) < env.scene.footprint)


def test_point_cloud_kind_and_colour_restriction(env, states):
    obs = states[0].obs
    kind = np.asarray(obs.kind).reshape(-1)
    _, all_valid = point_cloud(obs, env.camera)
    for k, name in enumerate(("coffee", "candy")):
        _, by_kind = point_cloud(obs, env.camera, kind=k)
        _, by_colour = point_cloud(obs, env.camera, colour=KINDS[name].rgb)
        by_kind, by_colour = np.asarray(by_kind), np.asarray(by_colour)
        assert by_kind.sum() > 0 and np.all(kind[by_kind] == k)
        np.testing.assert_array_equal(by_kind, np.asarray(all_valid) & (kind == k))
        np.testing.assert_array_equal(by_colour, by_kind)


def test_point_cloud_max_points(env, states):
    obs = states[0].obs
    points, valid = (np.asarray(a) for a in point_cloud(obs, env.camera))
    count = int(valid.sum())
    packed, kept = (np.asarray(a) for a in point_cloud(obs, env.camera, max_points=count + 7))
    assert kept.sum() == count and np.all(packed[~kept] == 0)
    assert sorted(map(tuple, packed[kept].tolist())) == sorted(map(tuple, points[valid].tolist()))
    few, kept_few = (np.asarray(a) for a in point_cloud(obs, env.camera, max_points=count // 2))
    assert kept_few.all()
    assert set(map(tuple, few.tolist())) <= set(map(tuple, points[valid].tolist()))


def test_sampled_particles_sit_on_pieces(env, states):
    for i, state in enumerate(states):
        out = sample_particles(state.obs, env.camera, 10, jax.random.PRNGKey(i), N_MAX)
        pos, mask = np.asarray(out.positions), np.asarray(out.mask)
        assert mask.tolist() == [True] * 10 + [False] * (N_MAX - 10) and np.all(pos[~mask] == 0)
        d = xy_distance_to_pieces(pos[mask], state)
        assert np.all(np.min(d - env.scene.footprint[None], axis=1) < 0)
        assert 0 < float(out.radius) < 0.2 and int(out.error) == 0


def test_recentring_pulls_particles_towards_piece_centres(env, states):
    state = states[0]
    key = jax.random.PRNGKey(3)
    raw = sample_particles(state.obs, env.camera, 10, key, N_MAX, r_center=0.0)
    centred = sample_particles(state.obs, env.camera, 10, key, N_MAX)
    d_raw = xy_distance_to_pieces(np.asarray(raw.positions)[:10], state).min(1)
    d_centred = xy_distance_to_pieces(np.asarray(centred.positions)[:10], state).min(1)
    assert d_centred.mean() < d_raw.mean()


def test_vmap_over_omega_equals_per_omega_calls(env, states):
    obs, key = states[0].obs, jax.random.PRNGKey(7)
    omegas = jnp.arange(1, N_MAX + 1)
    batched = jax.vmap(lambda w: sample_particles(obs, env.camera, w, key, N_MAX))(omegas)
    for i, w in enumerate(omegas.tolist()):
        single = sample_particles(obs, env.camera, w, key, N_MAX)
        for a, b in zip(single, batched, strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b)[i], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(np.asarray(batched.mask).sum(1), np.asarray(omegas))
    # the prefix property: at a fixed re-centring radius, resolution ω's particles are the first ω of any larger one's
    fixed = jax.vmap(lambda w: sample_particles(obs, env.camera, w, key, N_MAX, r_center=0.005))(omegas)
    full = np.asarray(fixed.positions[-1])
    for i, w in enumerate(omegas.tolist()):
        np.testing.assert_array_equal(np.asarray(fixed.positions[i])[:w], full[:w])


def test_vmap_over_observations_equals_loop(env, states):
    obs = jax.tree.map(lambda *x: jnp.stack(x), *[s.obs for s in states])
    keys = jax.random.split(jax.random.PRNGKey(8), len(states))
    batched = jax.vmap(lambda o, k: sample_particles(o, env.camera, 9, k, N_MAX))(obs, keys)
    for i, state in enumerate(states):
        single = sample_particles(state.obs, env.camera, 9, keys[i], N_MAX)
        for a, b in zip(single, batched, strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b)[i], rtol=1e-6, atol=1e-7)


def test_a_frame_given_as_nested_lists_is_the_same_frame(env, states):
    """Depth and colour as Python lists (JSON, a notebook) sample the particles their arrays do (a list ended in a
    TracerArrayConversionError inside the sensor's code)."""
    obs, key = states[0].obs, jax.random.PRNGKey(3)
    listed = obs._replace(depth=np.asarray(obs.depth).tolist(), rgb=np.asarray(obs.rgb).tolist())
    for a, b in zip(sample_particles(obs, env.camera, 9, key, N_MAX), sample_particles(listed, env.camera, 9, key,
                                                                                         N_MAX), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_sample_particles_padding_inert(env, states):
    """Pixels outside the requested kind never matter: scrambling their depth and colour changes nothing."""
    obs = states[0].obs
    other = np.asarray(obs.kind) == 1
    rng = np.random.default_rng(9)
    scrambled = obs._replace(
        depth=jnp.where(other, jnp.asarray(rng.uniform(0.9, 1.0, other.shape), jnp.float32), obs.depth),
        rgb=jnp.where(other[..., None], jnp.asarray(rng.integers(0, 256, obs.rgb.shape), jnp.uint8), obs.rgb))
    key = jax.random.PRNGKey(10)
    a = sample_particles(obs, env.camera, 5, key, N_MAX, kind=0)
    b = sample_particles(scrambled, env.camera, 5, key, N_MAX, kind=0)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# ----------------------------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------------------------
def test_bad_input_raises_naming_the_problem(env, states):
    obs, cam, key = states[0].obs, env.camera, jax.random.PRNGKey(0)
    n_points = int(sample_particles(obs, cam, 1, key, N_MAX).n_points)
    with pytest.raises(ValueError, match="empty foreground"):
        sample_particles(obs._replace(depth=jnp.full_like(obs.depth, cam.centre[2])), cam, 3, key, N_MAX)
    with pytest.raises(ValueError, match=r"omega=0 is outside \[1, capacity=16\]"):
        sample_particles(obs, cam, 0, key, N_MAX)
    with pytest.raises(ValueError, match="whole number of particles, got 2.7"):
        sample_particles(obs, cam, 2.7, key, N_MAX)  # was read as 2
    with pytest.raises(TypeError, match="integer"):
        jax.jit(lambda w: sample_particles(obs, cam, w, key, N_MAX))(jnp.float32(3.0))
    with pytest.raises(ValueError, match=r"omega=17 is outside \[1, capacity=16\]"):
        sample_particles(obs, cam, N_MAX + 1, key, N_MAX)
    with pytest.raises(ValueError, match=f"too few foreground points: {n_points} points for omega=100"):
        sample_particles(obs, cam, 100, key, 128)
    with pytest.raises(ValueError, match="no reading"):
        sample_particles(obs._replace(depth=jnp.full_like(obs.depth, jnp.nan)), cam, 3, key, N_MAX)
    with pytest.raises(ValueError, match="shape"):
        sample_particles(obs._replace(depth=obs.depth[:32]), cam, 3, key, N_MAX)
    with pytest.raises(ValueError, match="capacity"):
        sample_particles(obs, cam, 3, key, 0)


def test_bad_input_traced_returns_the_flag(env, states):
    obs, cam, key = states[0].obs, env.camera, jax.random.PRNGKey(0)
    run = jax.jit(lambda o, w: sample_particles(o, cam, w, key, N_MAX))
    no_reading = perception.NO_DEPTH | perception.EMPTY_FOREGROUND
    cases = [(obs, 5, 0), (obs, 0, perception.BAD_OMEGA), (obs, N_MAX + 1, perception.BAD_OMEGA),
             (obs._replace(depth=obs.depth.at[3, 5].set(jnp.nan)), 5, 0),  # a hole, as a 0 is
             (obs._replace(depth=jnp.full_like(obs.depth, jnp.nan)), 5, no_reading),
             (obs._replace(depth=jnp.zeros_like(obs.depth)), 5, no_reading),
             (obs._replace(depth=jnp.full_like(obs.depth, cam.centre[2])), 5, perception.EMPTY_FOREGROUND)]
    for o, w, flag in cases:
        out = run(o, w)
        assert int(out.error) == flag and bool(out.ok) == (flag == 0)
        assert np.all(np.isfinite(np.asarray(out.positions))) and np.isfinite(float(out.radius))
        if flag:
            assert not np.asarray(out.mask).any() and np.all(np.asarray(out.positions) == 0)
    few = jax.jit(lambda w: sample_particles(obs, cam, w, key, 128))(100)
    assert int(few.error) == perception.TOO_FEW_POINTS
    errors = jax.vmap(lambda w: sample_particles(obs, cam, w, key, N_MAX).error)(jnp.array([0, 3, N_MAX + 1]))
    assert errors.tolist() == [perception.BAD_OMEGA, 0, perception.BAD_OMEGA]


def _patch(depth, r, c, value, size=20):
    return jnp.asarray(depth).at[r:r + size, c:c + size].set(value)


@pytest.mark.parametrize("real_depth", [False, True])
def test_no_reading_is_never_a_point(env, states, real_depth):
    """Depth 0 (a camera's "no reading"), NaN, ±inf and NO_READING are one thing (``sim.sensor.is_reading``): a 20 x
    20 patch of any of them on the table gives the particles of the frame without it (exactly, with exact depth); on
    the pile, no particle lies in the patch or off the table (0 once put every patch pixel at the camera: a pile
    widened to the camera's centre), and every kind of hole gives the same particles."""
    obs, cam, key = states[0].obs, env.camera, jax.random.PRNGKey(3)
    sample = functools.partial(sample_particles, camera=cam, omega=4, key=key, capacity=N_MAX, real_depth=real_depth)
    _, valid = point_cloud(obs, cam)
    valid = np.asarray(valid).reshape(cam.height, cam.width)
    free = next((r, c) for r in range(8, cam.height - 28) for c in range(8, cam.width - 28)
                if not valid[r:r + 20, c:c + 20].any())
    rows, cols = np.nonzero(valid)
    on_pile = (rows.min() - 12, cols.min() - 12)  # the pile's corner
    whole = sample(obs)
    for (r, c), pile in ((free, False), (on_pile, True)):
        outs = [sample(obs._replace(depth=_patch(obs.depth, r, c, v)))
                for v in (0.0, jnp.nan, jnp.inf, -jnp.inf, NO_READING, -0.5)]
        for out in outs[1:]:
            np.testing.assert_array_equal(np.asarray(out.positions), np.asarray(outs[0].positions))
        out = outs[0]
        assert bool(out.ok) and int(out.mask.sum()) == 4 and (int(out.n_points) < int(whole.n_points)) == pile
        positions = np.asarray(out.positions)[np.asarray(out.mask)]
        assert np.all(positions[:, 2] < 0.1), positions  # nothing at the camera (1 m up)
        uv, _ = cam.world_to_pixel(positions)
        inside = np.all((uv >= [c + 1, r + 1]) & (uv <= [c + 19, r + 19]), axis=1)
        assert not inside.any(), uv[inside]
        if not pile and not real_depth:
            np.testing.assert_array_equal(np.asarray(out.positions), np.asarray(whole.positions))


@pytest.mark.parametrize("real_depth", [False, True])
def test_a_reading_far_above_the_table_is_no_pile(env, states, real_depth):
    """A patch read 5 cm below the camera (an arm, a hand, a reading next to the lens: about 1 m above the table)
    is not foreground: the cloud is the frame's without it, and no particle lies above PILE_CEILING (it became a
    particle 1 m up); a patch 5 cm above the table (under the ceiling) on free table is foreground."""
    obs, cam = states[0].obs, env.camera
    valid = np.asarray(point_cloud(obs, cam, real_depth=real_depth)[1]).reshape(cam.height, cam.width)
    free = next((r, c) for r in range(8, cam.height - 28) for c in range(8, cam.width - 28)
                if not valid[r:r + 20, c:c + 20].any())
    table = float(np.median(np.asarray(obs.depth)))
    near_lens = obs._replace(depth=_patch(obs.depth, *free, 0.05))
    got = np.asarray(point_cloud(near_lens, cam, real_depth=real_depth)[1]).reshape(valid.shape)
    np.testing.assert_array_equal(got, valid)
    out = sample_particles(near_lens, cam, omega=8, key=jax.random.PRNGKey(0), capacity=N_MAX, real_depth=real_depth)
    assert bool(out.ok) and np.all(np.asarray(out.positions)[:, 2] <= perception.PILE_CEILING)
    raised = np.asarray(point_cloud(obs._replace(depth=_patch(obs.depth, *free, table - 0.05)), cam,
                                    real_depth=real_depth)[1]).reshape(valid.shape)
    assert raised[free[0] + 5:free[0] + 15, free[1] + 5:free[1] + 15].all()


def test_a_depth_in_millimetres_is_named(env, states):
    """A frame in millimetres (every reading beyond NO_READING m) is no reading, and the error says millimetres."""
    obs, cam = states[0].obs, env.camera
    with pytest.raises(ValueError, match="no reading .* a depth in millimetres reads as none; give metres"):
        sample_particles(obs._replace(depth=obs.depth * 1000), cam, omega=8, key=jax.random.PRNGKey(0),
                         capacity=N_MAX)


def test_is_reading_is_the_one_rule():
    depth = np.array([0.0, np.nan, np.inf, -np.inf, -0.2, NO_READING, 2 * NO_READING, 0.5, 1.2], np.float32)
    want = [False] * 7 + [True, True]
    assert is_reading(depth).tolist() == want and np.asarray(is_reading(jnp.asarray(depth))).tolist() == want
    np.testing.assert_array_equal(readings(depth), np.where(want, depth, NO_READING).astype(np.float32))


def test_perceive_is_the_cloud_the_particles_and_the_kinds_of_one_frame():
    """``perceive`` computes the foreground once and gives what ``point_cloud``, ``sample_particles`` and
    ``particle_kinds`` give one by one (the same key), for every piece and for one kind."""
    sim = SimConfig(scene=SceneConfig(kinds=("coffee", "candy"), pieces=(8, 6)), camera=CameraConfig(width=48,
                                                                                                  height=48))
    env = PileEnv(sim, backend="mujoco")
    obs = env.reset(jax.random.PRNGKey(5)).obs
    key = jax.random.PRNGKey(6)
    for kind, omega in ((None, 12), (1, 5)):
        seen = perception.perceive(obs, env.camera, omega, key, 16, max_points=256, kind=kind, with_kinds=True)
        points, valid = point_cloud(obs, env.camera, max_points=256, kind=kind)
        particles = sample_particles(obs, env.camera, omega, key, 16, max_points=256, kind=kind)
        np.testing.assert_array_equal(seen.points, points)
        np.testing.assert_array_equal(seen.valid, valid)
        for got, want in zip(seen.particles, particles, strict=True):
            np.testing.assert_allclose(got, want, atol=1e-6)
        assert int(np.sum(seen.particles.mask)) == omega
        if kind is None:
            kinds = perception.particle_kinds(obs, env.camera, particles)
            np.testing.assert_array_equal(seen.kinds, kinds)
            assert set(np.asarray(seen.kinds)[np.asarray(seen.particles.mask)]) == {0, 1}
    assert perception.perceive(obs, env.camera, 12, key, 16, max_points=256).kinds is None
