"""Task goals: sized to the pile, inside the bin, reproducible from the seed."""

import numpy as np
import pytest

from dynres_jax import tasks
from dynres_jax.config import SceneConfig, SimConfig
from dynres_jax.sim.env import PileEnv


@pytest.fixture(scope="module")
def env():
    return PileEnv(SimConfig(scene=SceneConfig(pieces=(60,))), backend="mujoco", render=False)


def _fill(env, mask):
    pixel_area = (2 * env.config.camera.view_half_width / env.camera.width) ** 2
    return mask.sum() * pixel_area / np.sum(np.pi * env.scene.footprint**2)


@pytest.mark.parametrize("seed", range(3))
def test_gather_disc_holds_the_pile(env, seed):
    mask, info = tasks.gather_goal(np.random.default_rng(seed), env)
    assert info["shape"] == "disc" and tasks.FILL[0] * 0.9 < _fill(env, mask) < tasks.FILL[1] * 1.1
    again, _ = tasks.gather_goal(np.random.default_rng(seed), env)
    np.testing.assert_array_equal(mask, again)


@pytest.mark.parametrize("letter", ["T", "J", "U"])
def test_redistribute_letter_holds_the_pile(env, letter):
    mask, info = tasks.redistribute_goal(np.random.default_rng(0), env, letter)
    assert info["text"] == letter and tasks.FILL[0] * 0.85 < _fill(env, mask) < tasks.FILL[1] * 1.15
