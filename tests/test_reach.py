"""Pushes that reach every piece (sim.pushes): the action space with starts outside the walls, by hand and at random;
random wall pushes; the env's checks; and a piece resting against a wall brought to the centre by planned pushes,
which the action space without a reach cannot do."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.config import CameraConfig, PushConfig, SceneConfig, SimConfig
from dynres_jax.control.choosers import FixedOmega
from dynres_jax.control.decision import batch
from dynres_jax.control.goals import disc_goal, make_goal
from dynres_jax.control.mpc import MPCConfig, run_episode
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.models.registry import sweep_dynamics
from dynres_jax.sim import pushes
from dynres_jax.sim.env import PileEnv

B, R, MIN, MAX = 0.181, 0.207, 0.01, 0.25


def lengths(a):
    return np.hypot(a[..., 2] - a[..., 0], a[..., 3] - a[..., 1])


def in_action_space(a, tol=1e-5):
    """NumPy: every start coordinate within ±B or at ±R, every end within ±B, every length in [MIN, MAX]."""
    start = np.abs(a[..., :2])
    starts = np.all((start <= B + tol) | (np.abs(start - R) <= tol), axis=-1)
    ends = np.all(np.abs(a[..., 2:]) <= B + tol, axis=-1)
    return starts & ends & (lengths(a) >= MIN - tol) & (lengths(a) <= MAX + tol)


def test_projection_lands_in_the_action_space_and_is_idempotent():
    raw = jax.random.uniform(jax.random.PRNGKey(0), (4000, 4), minval=-0.3, maxval=0.3)
    out = np.asarray(pushes.project(raw, B, MIN, MAX, R))
    assert in_action_space(out).all()
    outside = np.any(np.abs(out[:, :2]) > B + 1e-6, axis=1)
    assert 0.2 < outside.mean() < 0.9  # both kinds of push are reached from random actions
    np.testing.assert_allclose(pushes.project(out, B, MIN, MAX, R), out, atol=1e-6)
    grad = jax.grad(lambda a: jnp.sum(jnp.square(pushes.project(a, B, MIN, MAX, R))))(raw[:200])
    assert np.all(np.isfinite(grad))
    # Without a reach nothing starts outside: the old action space.
    assert np.all(np.abs(np.asarray(pushes.project(raw, B, MIN, MAX))) <= B + 1e-6)


@pytest.mark.parametrize("action, expected", [
    ((R, 0.05, 0.1, 0.05), (R, 0.05, 0.1, 0.05)),  # from outside, valid: unchanged
    ((0.19, 0.0, 0.0, 0.0), (B, 0.0, B - 0.19, 0.0)),  # a start between bound and wall, nearer the bound
    ((0.2, 0.0, 0.1, 0.0), (R, 0.0, R - 0.1, 0.0)),  # ... nearer the wall: outside (direction, length kept)
    ((R, 0.0, R + 0.05, 0.0), (R, 0.0, R - 0.05, 0.0)),  # pointing out: turned to the inward normal, length kept
    ((R, 0.0, -0.3, 0.0), (R, 0.0, R - MAX, 0.0)),  # too long: cut to max_length along its direction
    ((-R, -R, -0.2, -0.2), (-R, -R, -B, -B)),  # from outside a corner, too short to get in: lengthened
])
def test_projection_by_hand(action, expected):
    np.testing.assert_allclose(pushes.project(jnp.array(action), B, MIN, MAX, R), expected, atol=1e-6)


def test_reach_must_leave_room():
    pushes.check_reach(B, R, MIN, MAX)
    with pytest.raises(ValueError, match="reach"):
        pushes.check_reach(B, B + 0.005, MIN, MAX)  # closer than a shortest push
    with pytest.raises(ValueError, match="reach"):
        PlannerConfig(bound=B, reach=B + 0.2)


def test_wall_points_favour_pieces_at_the_walls():
    """pile_points with a reach draws point i with weight exp(-(R - max|p_i|) / WALL_SCALE): frequencies match."""
    points = jnp.array([[0.0, 0.0, 0], [0.19, 0.0, 0], [0.0, -0.17, 0], [0.1, 0.1, 0], [0.195, 0.195, 0]])
    valid = jnp.array([True, True, True, True, False])
    drawn = np.asarray(pushes.pile_points(jax.random.PRNGKey(1), points, valid, (20000,), R))
    index = np.argmin(np.linalg.norm(drawn[:, None] - np.asarray(points)[None, :, :2], axis=-1), axis=1)
    w = np.exp((np.max(np.abs(np.asarray(points)[:, :2]), axis=1) - R) / pushes.WALL_SCALE) * np.asarray(valid)
    np.testing.assert_allclose(np.bincount(index, minlength=5) / len(index), w / w.sum(), atol=0.015)
    uniform = np.asarray(pushes.pile_points(jax.random.PRNGKey(1), points, valid, (20000,)))
    assert np.all(np.abs(uniform).max(axis=1) < 0.195)  # the masked point never comes


def test_a_share_of_sampled_pushes_come_from_outside_through_the_wall_points():
    m = 4000
    wall_xy = jnp.broadcast_to(jnp.array([0.17, 0.02]), (m, 1, 2))
    actions = np.asarray(pushes.sample_actions(jax.random.PRNGKey(2), m, 1, B, MIN, MAX, jnp.zeros(2), 0.03, R,
                                               wall_xy))[:, 0]
    assert in_action_space(actions).all()
    outside = np.abs(actions[:, 0] - R) < 1e-6  # from outside the +x wall, the one nearest to (0.17, 0.02)
    share = outside.mean()
    assert abs(share - pushes.WALL_SHARE) < 4 * np.sqrt(pushes.WALL_SHARE * (1 - pushes.WALL_SHARE) / m)
    a = actions[outside]
    d = a[:, 2:] - a[:, :2]
    s = np.clip(np.sum((np.array([0.17, 0.02]) - a[:, :2]) * d, -1) / np.sum(d * d, -1), 0, 1)
    miss = np.linalg.norm(a[:, :2] + s[:, None] * d - [0.17, 0.02], axis=1)
    assert np.mean(miss < 1e-4) > 0.95  # through the wall point (a few are bent by the projection)
    assert np.all(d[:, 0] < 0)  # inward
    none = np.asarray(pushes.sample_actions(jax.random.PRNGKey(2), m, 1, B, MIN, MAX, jnp.zeros(2), 0.03))
    assert np.all(np.abs(none) <= B + 1e-6)


SIM = SimConfig(scene=SceneConfig(pieces=(3,)), push=PushConfig(settle_time=0.04),
                camera=CameraConfig(width=64, height=64))


@pytest.fixture(scope="module")
def env():
    return PileEnv(SIM, backend="mujoco")


def test_env_checks_the_action_space(env):
    b, r = env.action_bound, env.reach
    assert r > SIM.scene.bin_half_width + SIM.scene.plate_thickness / 2  # the plate lowers wholly outside the wall
    env.check_action([r, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="between the workspace and the walls"):
        env.check_action([(b + SIM.scene.bin_half_width) / 2, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="ends outside"):
        env.check_action([0.0, 0.0, r, 0.0])
    traced, bad = jax.jit(env._sanitise)(jnp.array([b + 0.001, 0.0, 0.0, 0.0]))
    env.check_action(np.asarray(traced))
    assert not bool(bad)


def wall_episode(env, reach):
    """Three coffee beans against the +x wall, a disc goal of 6 cm at the centre, three planned pushes (sweep
    heuristic as the model) -> the pieces' final distances from the centre (m)."""
    foot = float(env.scene.footprint.max())
    x = SIM.scene.bin_half_width - foot - 0.0005
    state = env.place(np.array([[x, -0.02], [x, 0.0], [x, 0.02]]))
    mask = disc_goal(env.camera, np.zeros(2), 0.06)
    planner = PlannerConfig(samples=24, adam_steps=20, bound=env.action_bound, reach=reach)
    cfg = MPCConfig(mpc_steps=3, buckets=(4,), max_points=512, planner=planner)
    final, _ = run_episode(env, state, FixedOmega(batch(make_goal(mask, env.camera, n_samples=64)), 3),
                           sweep_dynamics(SIM.scene.plate_half_width), cfg, jax.random.PRNGKey(0), log=lambda _: None)
    return np.linalg.norm(np.asarray(final.pos)[:, :2], axis=1)


@pytest.mark.slow
def test_a_piece_at_a_wall_is_brought_to_the_centre(env):
    assert np.all(wall_episode(env, env.reach) < 0.06)
    assert np.sum(wall_episode(env, None) < 0.06) < 3  # pushes that start inside cannot get behind them
