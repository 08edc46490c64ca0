"""Resolution labels (paper Sec. IV-C): the best ω of a scene by Bayesian optimisation of c+(ω), for the regressor g.
The command is ``experiments.label_resolution`` (its docstring tells the recipe); this module holds the scenes of a
shard (Fig. 4's pairs) and the labelling of one shard.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import CameraConfig, PileConfig, PushConfig, SceneConfig, SimConfig, check_fields
from dynres_jax.control import budget, mpc, tasks
from dynres_jax.control.choosers import FixedOmega
from dynres_jax.control.decision import Situation
from dynres_jax.control.goals import make_goals
from dynres_jax.control.objective import distribution_distance
from dynres_jax.resolution import bo
from dynres_jax.resolution.regressor import observation_input
from dynres_jax.sim import engines
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import make_pool

FIRST = (2, 25, 50, 75, 100)  # the reference's initial ω
MID_EPISODE_OMEGA = 50  # the resolution of the closed loop that brings scenes mid-episode (--mid-episode)
LETTERS = "JTU"


NEAR_GOAL = 0.03  # m: "near the goal" piles and every goal centre lie within this of the bin centre



@dataclass(frozen=True)
class LabelConfig:
    """kind, pieces: the piles; batch: scenes per shard (even: scenes come in pairs); evals: c+ evaluations per scene
    (the first ``len(FIRST)`` at FIRST, the rest by Expected Improvement); repeats: plans averaged per evaluation;
    seed: the scenes; plan_seed: the plans and the BO's draws (default seed + 1); mid_episode: closed-loop steps at
    ω = MID_EPISODE_OMEGA before labelling (0: fresh piles); quick: tiny camera and pushes for CPU tests; backend:
    the engine that executes the plans' pushes (``engines.NAMES``; "mjx-fast" labels c*(ω) in the fast scene's
    physics)."""

    kind: str = "coffee"
    pieces: int = 100
    batch: int = 128
    evals: int = 10
    repeats: int = 2
    seed: int = 0
    plan_seed: int | None = None
    mid_episode: int = 0
    quick: bool = False
    backend: str = "mujoco"

    def __post_init__(self):
        check_fields(self)
        if self.batch % 2 or self.batch < 2:
            raise ValueError(f"batch must be even (scenes come in pairs), got {self.batch}")
        if self.evals <= len(FIRST):
            raise ValueError(f"evals must exceed the {len(FIRST)} initial evaluations, got {self.evals}")
        if self.mid_episode < 0 or self.repeats < 1:
            raise ValueError("mid_episode must be >= 0 and repeats >= 1")
        if self.backend not in engines.NAMES:
            raise ValueError(f"backend must be one of {', '.join(engines.NAMES)}, got {self.backend!r}")


def scene_config(cfg: LabelConfig, shard: int) -> SimConfig:
    """Shard 2s: spread piles; shard 2s + 1: one blob near the bin centre, so near the (central) goals."""
    pile = (PileConfig(layout="spread") if shard % 2 == 0 else
            PileConfig(layout="blob", centre_margin=SceneConfig.bin_half_width - NEAR_GOAL))
    push = PushConfig(max_length=0.1, settle_time=0.04) if cfg.quick else PushConfig()
    camera = CameraConfig(width=64, height=64) if cfg.quick else CameraConfig()
    return SimConfig(scene=SceneConfig(kinds=(cfg.kind,), pieces=(cfg.pieces,)), pile=pile, push=push,
                     camera=camera)


def shard_goals(cfg: LabelConfig, shard: int, env) -> tuple[np.ndarray, np.ndarray]:
    """Goal masks [B, H, W] and shapes [B] (0 disc, 1 letter) of a shard: scenes 2j and 2j + 1 a disc and a letter of
    the same centre (near the bin centre) and area (``tasks.disc_and_letter``); shards 2s and 2s + 1 draw the same."""
    masks = []
    for j in range(0, cfg.batch, 2):
        rng = np.random.default_rng((cfg.seed, shard // 2, j // 2))
        disc, letter, _ = tasks.disc_and_letter(rng, env, LETTERS[rng.integers(len(LETTERS))])
        masks += [disc, letter]
    return np.stack(masks), np.arange(cfg.batch) % 2


def shard_scenes(cfg: LabelConfig, shard: int, pool):
    """A shard's settled piles (batched State [B]), goal masks [B, H, W], goals (batched Goal) and goal shapes [B]."""
    pile_keys = jax.vmap(lambda j: jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(cfg.seed), shard), j))(
        jnp.arange(cfg.batch) // 2)  # scenes 2j and 2j + 1: the same pile
    goal_masks, shapes = shard_goals(cfg, shard, pool.env)
    goals = make_goals(goal_masks, pool.camera)
    return pool.reset(pile_keys), goal_masks, goals, shapes


def label_shard(cfg: LabelConfig, shard: int, dynamics, planner: Callable[[PileEnv], mpc.MPCConfig], processes,
                timing: budget.TimingTable | None) -> dict:
    """Label one shard: the arrays of its ``shard_NNNNN.npz``. planner: env -> the MPC settings of every plan (its
    planner and time budget; each c*(ω) is one ``mpc.act``: allot, decide, push, measure); processes: C worker
    processes (``pool.process_pool``) for backend "mujoco", else None; timing: the table the budget is spent by
    (None without a budget)."""
    pool = make_pool(scene_config(cfg, shard), cfg.backend, processes)
    camera, mpc_cfg = pool.camera, planner(pool.env)
    b, r = cfg.batch, cfg.repeats
    start, goal_masks, goals, shapes = shard_scenes(cfg, shard, pool)
    measure = jax.jit(jax.vmap(lambda obs, goal: distribution_distance(obs, goal, camera)))
    plan_seed = cfg.seed + 1 if cfg.plan_seed is None else cfg.plan_seed
    if cfg.mid_episode:  # the closed loop at ω = MID_EPISODE_OMEGA first: scenes as adaptive ω meets them
        keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(plan_seed), 200_000 + shard), b)
        mid = dataclasses.replace(mpc_cfg, mpc_steps=cfg.mid_episode)
        start = mpc.run(pool, start, FixedOmega(goals, MID_EPISODE_OMEGA), dynamics, mid, keys, timing=timing,
                        log=lambda s: None).states
    d0 = measure(start.obs, goals)
    rep = lambda x: jnp.repeat(x, r, axis=0)  # noqa: E731  [B] -> [B * R], repeats of a scene adjacent
    starts, goals_r = jax.tree.map(rep, start), jax.tree.map(rep, goals)
    init = jnp.zeros((b * r, mpc_cfg.planner.horizon, 4), jnp.float32)  # no warm start: each plan from its samples

    # Common random numbers: every ω of a scene is planned from the same R keys, so the same perception start and
    # the same starting pushes (decision.py); c*(ω) - c*(ω') is then the resolution's effect, not the draws'.
    keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(plan_seed), shard * 100), b * r)
    now = Situation(starts, starts.obs, camera, goals_r, None, keys, init, False)

    def c_star(omega):
        """c*(ω) [B] of every scene (the mean of its repeats), the variance of that mean [B] (0 with one repeat) and
        the Adam steps [B] each plan ran (its bucket's, under the budget)."""
        done = mpc.act(pool, now, rep(omega), cfg=mpc_cfg, timing=timing, dynamics=dynamics,
                       score=lambda after, g: dict(distance=measure(after.obs, g)))
        values = np.asarray(done["distance"]).reshape(b, r)
        spread = values.var(axis=1, ddof=1) / r if r > 1 else np.zeros(b)
        return jnp.asarray(values.mean(axis=1)), spread, done["adam_steps"][::r]

    k = cfg.evals
    omega = jnp.zeros((b, k), jnp.int32)
    target, c_stars, adam_steps = jnp.zeros((b, k)), jnp.zeros((b, k)), np.zeros((b, k), np.int32)
    repeat_var = np.zeros((b, k))  # the measured variance of each evaluation: the GP's noise floor is its mean
    mask = jnp.zeros((b, k), bool)
    propose = jax.jit(jax.vmap(bo.next_omega))
    for i in range(k):
        if i < len(FIRST):
            w = jnp.full(b, FIRST[i], jnp.int32)
        else:
            w = propose(omega, target, mask, jax.random.split(jax.random.fold_in(jax.random.PRNGKey(plan_seed), i), b),
                        jnp.asarray(repeat_var[:, :i].mean(axis=1)))
        c, repeat_var[:, i], adam_steps[:, i] = c_star(w)
        omega, mask = omega.at[:, i].set(w), mask.at[:, i].set(True)
        c_stars, target = c_stars.at[:, i].set(c), target.at[:, i].set(bo.penalised(c, d0, w))
    label, mean = jax.jit(jax.vmap(bo.best_omega))(omega, target, mask, jax.random.split(
        jax.random.fold_in(jax.random.PRNGKey(plan_seed), 100_000 + shard), b), jnp.asarray(repeat_var.mean(axis=1)))
    inputs = jax.vmap(lambda o, m: observation_input(o, m, camera))(start.obs, jnp.asarray(goal_masks))
    return dict(inputs=np.asarray(inputs), label=np.asarray(label), gp_mean=np.asarray(mean),
                omega=np.asarray(omega), c_plus=np.asarray(target), c_star=np.asarray(c_stars), d0=np.asarray(d0),
                adam_steps=adam_steps, repeat_var=repeat_var,
                goal_shape=shapes, layout=np.full(b, shard % 2), pile=np.arange(b) // 2, shard=np.int64(shard),
                mid_episode=np.int64(cfg.mid_episode), engine=np.array(cfg.backend))
