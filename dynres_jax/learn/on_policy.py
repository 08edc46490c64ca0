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

from dynres_jax.control import tasks
from dynres_jax.control.choosers import Candidate, Chooser, Orders
from dynres_jax.control.decision import Situation, fold
from dynres_jax.control.goals import disc_goal, make_goals
from dynres_jax.control.mpc import MPCConfig, propose, run
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
    """``planned_episodes`` of one group of worlds: keys [B, 2], goals (Goal [B]), through the closed loop
    (``mpc.run``) with the ``OnPolicy`` chooser."""
    env, b = worlds.env, len(keys)
    cfg = MPCConfig(mpc_steps=pushes, planner=planner_config(env, **PLANNER))
    frames = []
    chooser = OnPolicy(goals, env, omega, planned, _chunk_size(b, planned), cfg, dynamics)
    final, steps = run(worlds, worlds.reset(fold(keys, 1)), chooser, dynamics, cfg, fold(keys, 2),
                       on_step=[lambda t, before, particles, r: frames.append(jax.device_get(record(before)))],
                       log=lambda line: None)
    frames.append(jax.device_get(record(final)))
    actions = [r["action"] for r in steps]
    while len(actions) < pushes:  # the loop stops once every world broke: its last frame stands (broken is sticky)
        frames.append(frames[-1])
        actions.append(np.zeros_like(actions[-1]))
    out = {name: np.stack([f[name] for f in frames], axis=1) for name in frames[0]}
    return dict(out, action=np.stack(actions, axis=1).astype(np.float32))


class OnPolicy(Chooser):
    """Each push of each world the planner's with probability ``planned``, else random (``PileEnv.sample_push``),
    against goals [B]. Its orders ask the loop for no plan: its keep rule plans only the worlds it draws, in chunks of
    ``size`` (one compile a bucket; ``_chunks``) at ``omega`` (or the frame's foreground points where fewer: a chunk
    of such frames may plan in a smaller bucket), each from its last plan where its last push was planned too (warm
    start), and pushes every world."""

    def __init__(self, goals, env, omega: int, planned: float, size: int, cfg: MPCConfig, dynamics):
        self.goals, self.env, self.omega, self.planned, self.size = goals, env, omega, planned, size
        self.cfg, self.dynamics = cfg, dynamics

    def __call__(self, t, obs) -> Orders:
        return Orders(self.goals, (), keep=self.keep)

    def keep(self, worlds, now: Situation, plans, score, timing) -> dict:
        """``mpc.run``'s keep rule (``Orders.keep``): the pushes above; records no score (NaN), warm [B] the worlds
        planned."""
        chosen = np.asarray(jax.vmap(jax.random.uniform)(fold(now.keys, 2)) < self.planned)
        action = np.array(_random_pushes(fold(now.keys, 1), now.states.pos, env=self.env), np.float32)
        best = np.array(now.init, np.float32)  # where planned, replaced by the plan (the next step's warm start)
        omega, bucket = np.zeros(len(chosen), np.int32), np.zeros(len(chosen), np.int32)  # 0: a random push
        warm = np.broadcast_to(np.asarray(now.warm, bool), chosen.shape)
        for rows, n in _chunks(np.flatnonzero(chosen), self.size):
            seen = jax.tree.map(lambda x, r=rows: x[r], now.seen)
            visible = np.asarray(_visible_points(seen, camera=now.camera, max_points=self.cfg.max_points))
            part = Situation(None, seen, now.camera, jax.tree.map(lambda x, r=rows: x[r], now.goals), None,
                             now.keys[rows], now.init[rows], warm[rows])
            plan = propose(part, Candidate(np.minimum(self.omega, visible)), cfg=self.cfg, timing=None,
                           dynamics=self.dynamics)
            action[rows[:n]], best[rows[:n]] = plan["proposals"][:n, 0, 0], plan["proposals"][:n, 0]
            omega[rows[:n]], bucket[rows[:n]] = plan["omega"][:n], plan["bucket"][:n]
        nothing = np.full(len(chosen), np.nan)
        return dict(omega=omega, bucket=bucket, adam_steps=np.where(chosen, self.cfg.planner.adam_steps, 0),
                    objective=nothing, predicted_objective=nothing, distance=nothing, inside=nothing, action=action,
                    best=best,
                    states=worlds.push(now.states, action), particles=None, wall=nothing, warm=chosen)


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
