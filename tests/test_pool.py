"""WorldPool: C MuJoCo worlds in worker processes behave as PileEnv's C backend world by world."""

import jax
import numpy as np
import pytest

from dynres_jax.config import PushConfig, SceneConfig, SimConfig
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import WorldPool, process_pool

SIM = SimConfig(scene=SceneConfig(pieces=(6,)), push=PushConfig(max_length=0.08, settle_time=0.04))


@pytest.fixture(scope="module")
def processes():
    with process_pool(2) as p:
        yield p


def test_pool_reset_and_push_equal_one_world_at_a_time(processes):
    pool, env = WorldPool(SIM, processes), PileEnv(SIM, backend="mujoco")
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    states = pool.reset(keys)
    centre = np.asarray(states.pos)[:, :, :2].mean(1)  # push through each pile, along x, y and a diagonal
    actions = np.concatenate([centre - [[0.04, 0], [0, 0.04], [0.03, 0.03]],
                              centre + [[0.03, 0], [0, 0.03], [0.02, 0.02]]], 1).astype(np.float32)
    pushed = pool.push(states, actions)
    for i, key in enumerate(keys):
        one = env.reset(key)
        np.testing.assert_array_equal(np.asarray(states.pos[i]), np.asarray(one.pos))
        one = env.push(one, actions[i])
        for name in ("qpos", "pos", "mat", "broken"):
            np.testing.assert_array_equal(np.asarray(getattr(pushed, name)[i]), np.asarray(getattr(one, name)))
        np.testing.assert_array_equal(np.asarray(pushed.obs.depth[i]), np.asarray(one.obs.depth))
    assert np.abs(np.asarray(pushed.pos) - np.asarray(states.pos)).max() > 0.005  # the pushes moved pieces


def test_pool_names_a_bad_action():
    pool = WorldPool(SIM)
    states = pool.reset(jax.random.split(jax.random.PRNGKey(0), 1))
    with pytest.raises(ValueError, match="leaves the workspace"):
        pool.push(states, np.array([[0.0, 0.0, 0.5, 0.0]]))


def test_push_poses_are_the_states_of_the_rollout_cut_at_each_sub_push():
    """PileEnv.push_poses: the push's end state is ``push``'s, each pose inside it equals the end of the same
    trajectory cut after that step, and that step is the first at which the plate has covered i / S of its way."""
    env = PileEnv(SIM, backend="mujoco")
    state = env.reset(jax.random.PRNGKey(1))
    centre = np.asarray(state.pos)[:, :2].mean(0)
    action = np.concatenate([centre - [0.04, 0.01], centre + [0.03, 0.01]]).astype(np.float32)
    end, pos, mat = env.push_poses(state, action, 3)
    np.testing.assert_array_equal(np.asarray(end.pos), np.asarray(env.push(state, action).pos))
    plate_pos, plate_quat = env.plate_trajectory(action)
    way = np.linalg.norm(np.asarray(plate_pos)[:, :2] - action[:2], axis=1)
    length = np.linalg.norm(action[2:] - action[:2])
    for i, k in enumerate(env.sub_push_steps(action, 3)):
        assert way[k] >= (i + 1) / 3 * length - 1e-6 > way[k - 1]
        cut = env.simulate(state, plate_pos[:k + 1], plate_quat[:k + 1])
        np.testing.assert_array_equal(pos[i], np.asarray(cut.pos))
        np.testing.assert_array_equal(mat[i], np.asarray(cut.mat))
    assert np.abs(pos[1] - pos[0]).max() > 1e-3  # the pile moves between the sub-pushes
    with pytest.raises(ValueError, match="backend='mujoco'"):
        PileEnv(SIM, backend="mjx").push_poses(state, action, 3)
