"""The task as a mujoco_playground-style environment (control.task_env): reset and step under jit and vmap on the MJX
engine, rewards that add up to the fall in d, and a random-shooting loop written only against the interface that
brings the pile nearer the goal (CPU)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.config import CameraConfig, PileConfig, PushConfig, SceneConfig, SimConfig
from dynres_jax.control.goals import disc_goal
from dynres_jax.control.objective import distribution_distance
from dynres_jax.control.task_env import State, TaskEnv
from dynres_jax.sim.camera import Camera

pytestmark = pytest.mark.slow  # end to end: CI's second tier (python -m pytest -m slow)

WORLDS = 8  # worlds stepped at once, and the random-shooting loop's candidates


@pytest.fixture(scope="module")
def env():
    sim = SimConfig(scene=SceneConfig(pieces=(8,)), pile=PileConfig(layout="spread"),
                    push=PushConfig(max_length=0.12, settle_time=0.04), camera=CameraConfig(width=48, height=48))
    task = TaskEnv(sim, disc_goal(Camera.top_down(sim.camera), np.zeros(2), 0.07), episode_length=3)
    return task, jax.jit(jax.vmap(task.reset)), jax.jit(jax.vmap(task.step))


def uniform_pushes(key, n, reach):
    return jax.random.uniform(key, (n, 4), minval=-reach, maxval=reach)


def test_a_batch_of_random_policies_steps_it(env):
    """vmap'd reset and step: every field batched, rewards are the fall in d measured independently, done after
    episode_length steps, the step counter counts."""
    task, reset, step = env
    states = reset(jax.random.split(jax.random.PRNGKey(0), WORLDS))
    assert isinstance(states, State) and states.reward.shape == (WORLDS,) and np.all(states.done == 0)
    assert states.obs.depth.shape == (WORLDS, *task.observation_size["depth"]) and task.action_size == 4
    total, start = np.zeros(WORLDS), np.asarray(states.metrics["distance"])
    for t in range(3):
        states = step(states, uniform_pushes(jax.random.PRNGKey(t + 1), WORLDS, task.pile.reach))
        total += np.asarray(states.reward)
        assert np.all(np.asarray(states.info["step"]) == t + 1)
    d = np.array([distribution_distance(jax.tree.map(lambda x, b=b: x[b], states.obs), task.goal, task.pile.camera)
                  for b in range(WORLDS)])
    np.testing.assert_allclose(np.asarray(states.metrics["distance"]), d, rtol=1e-5)
    np.testing.assert_allclose(total, start - d, rtol=1e-4, atol=1e-4)
    assert np.all(np.asarray(states.done) == 1) and not np.any(np.asarray(states.data.broken))
    assert np.any(np.abs(np.asarray(states.data.pos) - np.asarray(reset(jax.random.split(
        jax.random.PRNGKey(0), WORLDS)).data.pos)) > 1e-3)  # the pushes moved pieces


def test_random_shooting_on_the_interface_brings_the_pile_nearer(env):
    """Random shooting written against reset/step alone: each step tries WORLDS pushes on copies of the state and
    keeps the one with the highest reward. Three steps lower d more than three random pushes do."""
    task, reset, step = env
    state = jax.tree.map(lambda x: x[:1], reset(jax.random.split(jax.random.PRNGKey(5), WORLDS)))
    random = state
    for t in range(3):
        copies = jax.tree.map(lambda x: jnp.repeat(x, WORLDS, axis=0), state)
        tried = step(copies, uniform_pushes(jax.random.PRNGKey(100 + t), WORLDS, task.pile.reach))
        best = int(np.argmax(np.asarray(tried.reward)))
        state = jax.tree.map(lambda x, b=best: x[b:b + 1], tried)
        random = jax.tree.map(lambda x: x[:1], step(jax.tree.map(lambda x: jnp.repeat(x, WORLDS, axis=0), random),
                                                       uniform_pushes(jax.random.PRNGKey(200 + t), WORLDS,
                                                                      task.pile.reach)))
    start = float(reset(jax.random.split(jax.random.PRNGKey(5), WORLDS)).metrics["distance"][0])
    final = float(state.metrics["distance"][0])
    assert final < start and final < float(random.metrics["distance"][0])


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="episode_length"):
        TaskEnv(SimConfig(camera=CameraConfig(width=48, height=48)), episode_length=0, backend="mujoco")
    with pytest.raises(ValueError, match="goal_mask must be the camera's"):
        TaskEnv(SimConfig(camera=CameraConfig(width=48, height=48)), np.ones((8, 8), bool), backend="mujoco")
