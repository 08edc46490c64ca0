"""On-policy data (``learn.on_policy``): the planner's pushes take piles towards each episode's goal where random
pushes do not, the piles start the same whatever the policy, and a planned shard is written like a random one."""

import jax
import numpy as np
import pytest

from dynres_jax.control.goals import make_goal
from dynres_jax.control.objective import inside_share
from dynres_jax.learn import data, on_policy
from dynres_jax.models.registry import sweep_dynamics
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import EnvWorlds

CONFIG = data.quick_config(pushes=3, worlds=6, episodes=6, backend="mujoco")
WORLDS = 6


@pytest.fixture(scope="module")
def episodes():
    """Six quick piles, three pushes each, every push random (planned 0) and every push planned (planned 1), on
    the sweep heuristic with a small planner."""
    sim = data.shard_sim_config(CONFIG, 0)
    worlds = EnvWorlds(PileEnv(sim, backend="mujoco"))
    keys = jax.random.split(jax.random.PRNGKey(3), WORLDS)
    dynamics = sweep_dynamics(sim.scene.plate_half_width)
    small = dict(samples=16, adam_steps=10)
    saved = dict(on_policy.PLANNER)
    on_policy.PLANNER.update(small)
    try:
        runs = {p: on_policy.planned_episodes(worlds, keys, 3, p, dynamics, 8, data.frame_record)
                for p in (0.0, 1.0)}
    finally:
        on_policy.PLANNER.update(saved)
    return worlds, keys, runs


@pytest.mark.slow
def test_planned_pushes_move_piles_into_their_goals(episodes):
    worlds, keys, runs = episodes
    goals = [make_goal(on_policy.episode_goal(k, worlds.env), worlds.camera) for k in on_policy.fold(keys, 0)]
    mask = np.ones(runs[0.0]["pos"].shape[2], bool)

    def inside(run, frame):
        return np.array([float(inside_share(run["pos"][b, frame], mask, g, worlds.camera))
                         for b, g in enumerate(goals)])

    start = inside(runs[0.0], 0)
    np.testing.assert_array_equal(start, inside(runs[1.0], 0))  # the same piles, whatever the policy
    random_gain, planned_gain = inside(runs[0.0], -1) - start, inside(runs[1.0], -1) - start
    assert planned_gain.mean() > random_gain.mean() + 0.1, (planned_gain, random_gain)
    assert not np.allclose(runs[0.0]["action"], runs[1.0]["action"])


@pytest.mark.slow  # the planned episodes fixture (49 s on the 2-core CPU): CI's second tier
def test_random_share_follows_the_piles_sampler(episodes):
    """planned = 0: every push is ``PileEnv.sample_push`` of the frame it starts from, under the step's key."""
    worlds, keys, runs = episodes
    run = runs[0.0]
    for t in range(3):
        step_keys = on_policy.fold(on_policy.fold(on_policy.fold(keys, 2), t), 1)
        expected = jax.vmap(worlds.env.sample_push)(step_keys, run["pos"][:, t])
        np.testing.assert_allclose(run["action"][:, t], np.asarray(expected), atol=1e-6)


@pytest.mark.slow  # the planned episodes fixture (49 s on the 2-core CPU): CI's second tier
def test_episode_arrays_have_the_random_episodes_layout(episodes):
    _, _, runs = episodes
    run = runs[1.0]
    assert run["depth"].shape[:2] == run["pos"].shape[:2] == (WORLDS, 4)
    assert run["action"].shape == (WORLDS, 3, 4)
    assert run["depth"].dtype == np.float16 and run["piece"].dtype == np.int16
    assert not run["broken"].any()


def test_planned_share_is_checked():
    with pytest.raises(ValueError, match="planned must be a share"):
        data.DataConfig(planned=1.5)


def test_every_key_draws_a_goal_inside_the_bin_even_for_a_large_pile():
    """The largest piles of the data (100 M&Ms) fit no disc and not every letter: a goal is still drawn, inside the
    bin, for every key (the first on-policy run on a GPU stopped at a letter S wider than the bin); drawn on threads,
    the masks are the serial ones."""
    from dynres_jax.config import CameraConfig, SceneConfig, SimConfig

    env = PileEnv(SimConfig(scene=SceneConfig(kinds=("mnm",), pieces=(100,)), camera=CameraConfig(width=64, height=64)),
                  backend="mujoco", render=False)
    keys = jax.random.split(jax.random.PRNGKey(0), 24)
    masks = [on_policy.episode_goal(k, env) for k in keys]
    assert all(m.shape == (64, 64) and m.any() and not m.all() for m in masks)
    assert len({m.tobytes() for m in masks}) > 3
    np.testing.assert_array_equal(on_policy.episode_goals(keys, env), np.stack(masks))  # on threads, the same


@pytest.mark.slow
def test_lanes_step_each_group_as_it_would_alone():
    """Two lanes on C workers (one group pushes while the other plans): each world's episode is the one its group of
    worlds makes alone, and the groups' worlds are not mixed up; lanes are checked."""
    from dynres_jax.sim.pool import WorldPool, process_pool

    sim = data.shard_sim_config(CONFIG, 0)
    keys = np.asarray(jax.random.split(jax.random.PRNGKey(5), 4))
    dynamics = sweep_dynamics(sim.scene.plate_half_width)
    saved = dict(on_policy.PLANNER)
    on_policy.PLANNER.update(samples=8, adam_steps=4)
    try:
        with process_pool(2) as processes:
            worlds = WorldPool(sim, processes)
            run = lambda k, lanes: on_policy.planned_episodes(worlds, k, 2, 0.5, dynamics, 8,  # noqa: E731
                                                              data.frame_record, lanes)
            both, first, second = run(keys, 2), run(keys[:2], 1), run(keys[2:], 1)
            with pytest.raises(ValueError, match="lanes must be between 1 and the 4 worlds"):
                run(keys, 5)
    finally:
        on_policy.PLANNER.update(saved)
    for name in ("pos", "action", "depth", "broken"):
        np.testing.assert_array_equal(both[name], np.concatenate([first[name], second[name]]))
    assert np.abs(both["pos"][:, -1] - both["pos"][:, 0]).max() > 0.005  # the pushes moved pieces


def test_only_planned_worlds_are_planned_warm_after_a_planned_push():
    """planned = 0.5: a push plans exactly the worlds whose push it plans (padding copies aside), warm-started where
    the world's previous push was planned; random pushes are the piles sampler's; chunks of one world (each decided
    alone) and of several give the same pushes, so chunking mixes up no worlds."""
    sim = data.shard_sim_config(CONFIG, 0)
    worlds = EnvWorlds(PileEnv(sim, backend="mujoco"))
    keys = jax.random.split(jax.random.PRNGKey(7), WORLDS)
    dynamics = sweep_dynamics(sim.scene.plate_half_width)
    from dynres_jax.control import mpc

    calls, decide = [], mpc.decide_batch  # every decision of the loop (``mpc.propose``)

    def spy(obs, goals, step_keys, init, warm, *args, **kwargs):
        calls.append((np.asarray(step_keys), np.asarray(warm)))
        return decide(obs, goals, step_keys, init, warm, *args, **kwargs)

    saved, chunk_size = dict(on_policy.PLANNER), on_policy._chunk_size
    on_policy.PLANNER.update(samples=8, adam_steps=4)
    mpc.decide_batch = spy
    try:
        runs = {}
        for size in (None, 1):  # the rule's chunks (all the worlds here), chunks of one world
            on_policy._chunk_size = chunk_size if size is None else lambda b, planned: 1
            calls.clear()
            runs[size] = on_policy.planned_episodes(worlds, keys, 3, 0.5, dynamics, 8, data.frame_record)
    finally:
        on_policy.PLANNER.update(saved)
        mpc.decide_batch, on_policy._chunk_size = decide, chunk_size
    run = runs[1]
    planned_before = np.zeros(WORLDS, bool)
    for t in range(3):
        step_keys = np.asarray(on_policy.fold(on_policy.fold(keys, 2), t))
        chosen = np.asarray(jax.vmap(jax.random.uniform)(on_policy.fold(step_keys, 2)) < 0.5)
        world = {key.tobytes(): i for i, key in enumerate(step_keys)}  # this push's plan keys -> their worlds
        seen = {world[key.tobytes()]: bool(warm) for k, w in calls for key, warm in zip(k, w, strict=True)
                if key.tobytes() in world}  # world -> the warm flag it was planned with at this push
        assert sorted(seen) == list(np.flatnonzero(chosen)), (t, seen, chosen)
        assert all(warm == planned_before[i] for i, warm in seen.items())
        random = np.asarray(jax.vmap(worlds.env.sample_push)(on_policy.fold(step_keys, 1), run["pos"][:, t]))
        np.testing.assert_allclose(run["action"][~chosen, t], random[~chosen], atol=1e-6)
        assert not np.allclose(run["action"][chosen, t], random[chosen], atol=1e-3)
        planned_before = chosen
    assert 0 < sum(len(k) for k, _ in calls)
    np.testing.assert_allclose(runs[1]["action"], runs[None]["action"], atol=1e-4)


@pytest.mark.parametrize("b, planned", [(6, 0.5), (64, 0.5), (128, 0.25), (512, 0.5), (512, 0.9), (40, 1.0)])
def test_chunk_size_makes_nearly_every_push_one_decision(b, planned):
    """A group's decision size holds the planned worlds of nearly every push (binomial draws: at most 1 % need a
    second decision), stays within the group, and pads by a few standard deviations at most."""
    size = on_policy._chunk_size(b, planned)
    counts = np.random.default_rng(0).binomial(b, planned, 100_000)
    assert size <= b and np.mean(counts > size) <= 0.01
    assert size <= b * planned + 4 * np.sqrt(b * planned * (1 - planned)) + 1
