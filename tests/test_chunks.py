"""Episodes independent of their batch (issue 70 item 7): ``chunks.in_chunks`` against a loop, and a decision and a
rendered frame of episode i alike whether it runs beside one other episode or four (CPU; at these sizes, the
shipped model's, both differed before the chunks, 2026-11-28)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.chunks import in_chunks
from dynres_jax.config import CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control import tasks
from dynres_jax.control.decision import DecisionSpec, decide_batch
from dynres_jax.control.goals import make_goals
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics
from dynres_jax.sim.pool import WorldPool


@pytest.mark.parametrize("size", [1, 2, 3, 5, 8])
def test_chunks_equal_a_loop_and_drop_their_padding(size):
    x = np.arange(5 * 3, dtype=np.float32).reshape(5, 3)
    calls = []

    def fn(a, b):
        calls.append(len(a))
        return {"sum": jnp.sum(a, axis=1) + b, "rows": a * 2}

    out = in_chunks(fn, x, np.arange(5.0), size=size)
    np.testing.assert_array_equal(out["sum"], [row.sum() + i for i, row in enumerate(x)])
    np.testing.assert_array_equal(out["rows"], x * 2)
    assert set(calls) == {size} and len(calls) == -(-5 // size)  # one compiled shape, the last chunk padded
    with pytest.raises(ValueError, match="at least one"):
        in_chunks(fn, x, np.arange(5.0), size=0)


@pytest.mark.slow
def test_an_episode_decides_and_renders_alike_beside_one_or_four_others():
    sim = SimConfig(scene=SceneConfig(pieces=(40,)), camera=CameraConfig(width=64, height=64),
                    pile=PileConfig(layout="spread"))
    pool = WorldPool(sim)
    piles, keys = tasks.episode_keys(0, np.arange(5))
    five = pool.reset(piles)
    two = pool.reset(piles[:2])
    np.testing.assert_array_equal(np.asarray(two.obs.depth), np.asarray(five.obs.depth)[:2])
    goals = make_goals([tasks.draw_goal("gather", i, 0, pool.env)[0] for i in range(5)], pool.camera)
    spec = DecisionSpec(64, PlannerConfig(samples=10, adam_steps=5, bound=pool.env.action_bound,
                                          max_length=sim.push.max_length), max_points=4096)

    dynamics = load_dynamics("learned", SHIPPED_DYNAMICS, sim.scene.plate_half_width)[0]

    def decide(b):
        obs, g = jax.tree.map(lambda x: x[:b], five.obs), jax.tree.map(lambda x: x[:b], goals)
        return decide_batch(obs, g, keys[:b], jnp.zeros((b, 1, 4)), False, np.full(b, 50), np.full(b, 5), spec=spec,
                            dynamics=dynamics, camera=pool.camera)

    (p2, c2, r2), (p5, c5, r5) = decide(2), decide(5)
    np.testing.assert_array_equal(np.asarray(p2.positions), np.asarray(p5.positions)[:2])
    np.testing.assert_array_equal(np.asarray(c2), np.asarray(c5)[:2])
    for name in ("best", "best_cost", "costs", "history"):
        np.testing.assert_array_equal(np.asarray(getattr(r2, name)), np.asarray(getattr(r5, name))[:2], err_msg=name)
    assert not np.array_equal(np.asarray(r5.best)[0], np.asarray(r5.best)[1])  # the episodes differ
