"""On-policy training data for f: episodes whose pushes the closed loop's own planner chooses.

Random pushes (``PileEnv.sample_push``) cover where a pile can go, not where the closed loop takes it: the planner
refines its pushes by gradient descent through f, so it seeks out the pushes f is most optimistic about, and a model
trained on random pushes alone ranks those wrongly (docs/ladder: the simulator ranking the model's own refined plans
rescues most failures). An on-policy episode (``planned_episodes``) draws a task goal from its key (a Gather disc
where the pile fits one, else a Redistribute letter); at every push each world pushes as the closed loop's planner
(``PLANNER``, at one ω per shard, on the policy model) plans with probability ``planned``, and randomly otherwise, so
the data holds the states the planner visits and both kinds of push from them. Only the worlds whose push is planned
are planned for, and a plan starts from the world's previous one where that was planned too (the closed loop's warm
start). Frames and actions are recorded as ``learn.data`` records random episodes. On C workers a shard runs
in lanes, groups of worlds that take turns: one pushes on the host while another plans on the device (docs/warp:
1.47x one lane on one H200 and 16 cores).
"""

from __future__ import annotations

import functools
import math
import os
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.control import budget, tasks
from dynres_jax.control.decision import decide_batch, fold
from dynres_jax.control.goals import disc_goal, make_goals
from dynres_jax.control.mpc import MPCConfig, shift
from dynres_jax.control.planner import planner_config
from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics
from dynres_jax.perception import visible_count

OMEGAS = (25, 50, 100)  # the resolution of shard i's plans: OMEGAS[i % 3]
LETTERS = "JTUCLSYO"  # Redistribute goals an episode may draw
PLANNER = dict(samples=50, adam_steps=100)  # the closed loop's planner (docs/ladder's settings)
HOST_LANES = 2  # groups of worlds a shard on C workers steps in turn: one pushes on the host while another plans
PLAN_SLACK = 3.0  # a decision's worlds: the expected planned count plus this many standard deviations (_chunk_size)


def policy_dir(policy: str) -> str:
    """The checkpoint folder of ``DataConfig.policy``: itself, or ``checkpoints/dynamics`` for "shipped"."""
    return SHIPPED_DYNAMICS if policy == "shipped" else policy


def policy_dynamics(policy: str, plate_half_width: float):
    """The policy model's planner dynamics (radius -> model) from ``policy_dir(policy)``. Loaded once per
    process."""
    return _load(policy_dir(policy), float(plate_half_width))


@functools.lru_cache(maxsize=2)
def _load(ckpt_dir: str, plate_half_width: float):
    return load_dynamics("learned", ckpt_dir, plate_half_width).dynamics


def episode_goal(key, env) -> np.ndarray:
    """An episode's goal mask [H, W] bool from its key (raw uint32 [2]): a Gather disc or a letter of LETTERS, each
    half the time; a letter whenever the pile is too large for a disc (``tasks.largest_pile``): the letters in a
    random order until one at the pile's area fits the bin, else a disc at the centre as wide as the bin allows."""
    rng = np.random.default_rng(np.asarray(key, np.uint32).tolist())
    scene = env.config.scene
    if rng.uniform() < 0.5 and sum(scene.pieces) <= tasks.largest_pile(scene):
        return tasks.gather_goal(rng, env)[0]
    for letter in rng.permutation(list(LETTERS)):
        try:
            return tasks.redistribute_goal(rng, env, str(letter))[0]
        except ValueError:  # this letter at the pile's area reaches outside the bin
            continue
    return disc_goal(env.camera, (0.0, 0.0), scene.bin_half_width - tasks.GOAL_MARGIN)


def episode_goals(keys, env) -> np.ndarray:
    """``episode_goal`` of each of keys [B, 2] (raw uint32) -> masks [B, H, W] bool, drawn on all the host's cores
    at once (OpenCV and NumPy release the GIL; each mask depends on its key alone, so the masks are the serial
    ones)."""
    keys = np.asarray(keys)
    with ThreadPoolExecutor(max(1, min(len(keys), os.cpu_count() or 1))) as threads:
        return np.stack(list(threads.map(lambda k: episode_goal(k, env), keys)))


def planned_episodes(worlds, keys, pushes: int, planned: float, dynamics, omega: int, record, lanes: int = 1) -> dict:
    """One episode per key [B, 2] in ``worlds`` (``sim.pool.Worlds`` whose states carry observations): a reset, then
    ``pushes`` pushes, each world's the planner's (at ``omega``, or the frame's foreground points where fewer; on
    ``dynamics``: radius -> model) with probability ``planned``, else random. record: States [B] -> the arrays kept of
    a frame (``data.frame_record``). lanes: the worlds split into this many groups (``np.array_split``), each stepped
    in a thread of its own, so that one group's pushes (C workers on the host) overlap another's decisions (on the
    device); ``worlds`` must then be safe to call from several threads (a ``WorldPool`` on worker processes is). A
    world's episode depends on its key and, to float rounding, on the worlds planned beside it. Returns record's
    arrays stacked [B, F, ...] (F = pushes + 1; broken is sticky, as every State's) and action [B, F - 1, 4]."""
    if not 0.0 <= planned <= 1.0:
        raise ValueError(f"planned must be a share in [0, 1], got {planned}")
    keys = np.asarray(keys)
    if not 1 <= lanes <= len(keys):
        raise ValueError(f"lanes must be between 1 and the {len(keys)} worlds, got {lanes}")
    goals = make_goals(episode_goals(fold(keys, 0), worlds.env), worlds.camera)

    def lane(group):
        return _episodes(worlds, jnp.asarray(keys[group]), jax.tree.map(lambda g: g[group], goals), pushes, planned,
                         dynamics, omega, record)

    with ThreadPoolExecutor(lanes) as threads:
        parts = list(threads.map(lane, np.array_split(np.arange(len(keys)), lanes)))
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def _episodes(worlds, keys, goals, pushes: int, planned: float, dynamics, omega: int, record) -> dict:
    """``planned_episodes`` of one group of worlds: keys [B, 2], goals (Goal [B]). A push plans only for the worlds
    whose push it plans, in chunks of one size (``_chunk_size``: one compile); a world's plan starts from its previous
    one (warm start) where its previous push was planned too."""
    env, camera, b = worlds.env, worlds.camera, len(keys)
    cfg = MPCConfig(planner=planner_config(env, **PLANNER))
    spec = cfg.spec(budget.bucket_for(omega, cfg.buckets))
    size = _chunk_size(b, planned)
    steps = np.full(size, cfg.planner.adam_steps, np.int32)
    states = worlds.reset(fold(keys, 1))
    frames, actions = [jax.device_get(record(states))], []
    plans, warm = np.zeros((b, cfg.planner.horizon, 4), np.float32), np.zeros(b, bool)
    for t in range(pushes):
        step_keys = fold(fold(keys, 2), t)
        chosen = np.asarray(jax.vmap(jax.random.uniform)(fold(step_keys, 2)) < planned)
        action = np.array(_random_pushes(fold(step_keys, 1), states.pos, env=env), np.float32)
        for rows, n in _chunks(np.flatnonzero(chosen), size):
            obs = jax.tree.map(lambda x, r=rows: x[r], states.obs)
            visible = np.asarray(_visible_points(obs, camera=camera, max_points=cfg.max_points))
            best = np.asarray(decide_batch(obs, jax.tree.map(lambda x, r=rows: x[r], goals), step_keys[rows],
                                           plans[rows], warm[rows], np.minimum(omega, visible),
                                           steps, spec=spec, dynamics=dynamics, camera=camera)[2].best)
            action[rows[:n]], plans[rows[:n]] = best[:n, 0], np.asarray(shift(best))[:n]
        warm = chosen
        states = worlds.push(states, action)
        frames.append(jax.device_get(record(states)))
        actions.append(action)
    out = {name: np.stack([f[name] for f in frames], axis=1) for name in frames[0]}
    return dict(out, action=np.stack(actions, axis=1))


def _chunk_size(b: int, planned: float) -> int:
    """Worlds a decision takes in a group of b worlds, each planned with probability ``planned``: the expected count
    plus PLAN_SLACK binomial standard deviations (at most b), so nearly every push is one decision. On a GPU a few
    large decisions beat many small ones (docs/warp: one chunk against four, 1.22x a shard of 256 worlds)."""
    mean = b * planned
    return min(b, max(1, math.ceil(mean + PLAN_SLACK * math.sqrt(mean * (1 - planned)))))


def _chunks(rows: np.ndarray, size: int):
    """rows [K] in chunks of ``size``: (chunk [size], n) with its first n rows real, the last chunk padded with
    copies of its last row (planned again, the copies' plans unused)."""
    for i in range(0, len(rows), size):
        chunk = rows[i:i + size]
        yield np.concatenate([chunk, np.full(size - len(chunk), chunk[-1])]), len(chunk)


@functools.partial(jax.jit, static_argnames=("camera", "max_points"))
def _visible_points(obs, *, camera, max_points):
    """``perception.visible_count`` of each frame of obs [B]: -> [B] int."""
    return jax.vmap(lambda o: visible_count(o, camera, max_points))(obs)


@functools.partial(jax.jit, static_argnames="env")
def _random_pushes(keys, pos, *, env):
    """``env.sample_push`` of each world: keys [B, 2], pos [B, N, 3] -> actions [B, 4] (compiled once per env)."""
    return jax.vmap(env.sample_push)(keys, pos)
