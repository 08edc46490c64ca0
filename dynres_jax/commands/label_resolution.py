"""Label scenes with their best resolution by Bayesian optimisation (paper Sec. IV-C), for the regressor g.

    python -m experiments.label_resolution --out runs/labels --scenes 1024
    python -m experiments.label_resolution --out /tmp/labels --quick        # a CPU smoke run

For every scene (a settled pile and a goal), ``c+(ω) = c*(ω) + w_R · d_0 · ω`` is evaluated at ω = 2, 25, 50, 75,
100 and then at ``--evals`` - 5 more ω chosen by Expected Improvement; c*(ω) is the distribution distance d after one
push planned at ω under the time budget (``--time-budget`` seconds per decision on this device, spent by a timing
table measured once per resolution bucket and saved as ``timing.json``: a coarse ω affords more Adam steps) and
executed in the simulator, averaged over ``--repeats`` plans; d_0 is d before the push. The label is the argmin
of the GP posterior mean; the GP's noise is never below the measured variance of an evaluation (the repeats'
variance over their count, averaged over the scene's evaluations so far; ``repeat_var`` in the shards).

Scenes come in shards of ``--batch`` scenes, all simulated, planned and optimised together (vmapped; pushes in C
worker processes). Pairs for the paper's Fig. 4, as the paper poses them: in every shard, scenes 2j and 2j + 1 share
the pile and differ in the goal (a disc and a letter of the same centre, near the bin centre, and the same area);
shards 2s and 2s + 1 share their goals and differ in the pile (spread over the bin vs one blob near the bin centre,
so near the goal). With ``--mid-episode K`` each scene first runs K steps of the closed loop towards its goal, so the
labels cover the states adaptive ω meets mid-episode (the pairs then no longer share their piles).
Each shard is written atomically (``shard_NNNNN.npz``) and a rerun skips finished shards.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from dynres_jax.commands.task import add_budget_args, load_timing
from dynres_jax.config import CameraConfig, PileConfig, PushConfig, SceneConfig, SimConfig
from dynres_jax.control import budget, resolution, tasks
from dynres_jax.control.mpc import MPCConfig, decide, measure_timing, run_episodes
from dynres_jax.control.objective import distribution_distance, make_goal
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.io import files
from dynres_jax.learn.data import parse_part, save_npz, shard_path, shards_todo
from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics
from dynres_jax.perception import check_particles
from dynres_jax.sim.pool import WorldPool, process_pool

FIRST = (2, 25, 50, 75, 100)  # the reference's initial ω
MID_EPISODE_OMEGA = 50  # the resolution of the closed loop that brings scenes mid-episode (--mid-episode)
LETTERS = "JTU"


NEAR_GOAL = 0.03  # m: "near the goal" piles and every goal centre lie within this of the bin centre


def scene_config(args, shard: int) -> SimConfig:
    """Shard 2s: spread piles; shard 2s + 1: one blob near the bin centre, so near the (central) goals."""
    pile = (PileConfig(layout="spread") if shard % 2 == 0 else
            PileConfig(layout="blob", centre_margin=SceneConfig.bin_half_width - NEAR_GOAL))
    push = PushConfig(max_length=0.1, settle_time=0.04) if args.quick else PushConfig()
    camera = CameraConfig(width=64, height=64) if args.quick else CameraConfig()
    return SimConfig(scene=SceneConfig(kinds=(args.kind,), pieces=(args.pieces,)), pile=pile, push=push,
                     camera=camera)


def add_planner_args(parser) -> None:
    """The planner flags shared with ``experiments.evaluate``."""
    add_budget_args(parser)
    parser.add_argument("--samples", type=int, default=20, help="action sequences per plan (paper M = 20)")
    parser.add_argument("--plan-steps", type=int, default=100, help="Adam steps per plan (the most, under a budget)")
    parser.add_argument("--horizon", type=int, default=1, help="pushes per planned sequence (paper T = 1)")


def check_planner_args(parser, args) -> None:
    """parser.error naming a bad planner flag, before any work."""
    load_timing(parser, args)
    if args.plan_steps < 1 or args.samples < 1:
        parser.error("--plan-steps and --samples must be positive")


def planner_config(env, args) -> MPCConfig:
    """The planner the flags ask for (shared with ``experiments.evaluate``)."""
    planner = PlannerConfig(samples=args.samples, steps=args.plan_steps, horizon=args.horizon,
                            bound=env.action_bound, max_length=env.config.push.max_length,
                            min_length=env.config.push.min_length)
    return MPCConfig(steps=1, omega=resolution.OMEGA_MAX, planner=planner, max_points=1024 if args.quick else 4096,
                     time_budget=args.time_budget)


def timing_table(args, out_dir: str, obs, goal, dynamics, cfg: MPCConfig, camera) -> budget.TimingTable | None:
    """The run's timing table: ``--timing``'s, else the one an earlier run in ``out_dir`` saved (so a resumed run
    spends the budget as it began), else measured here on one observation and goal (unbatched) and saved there as
    ``timing.json``. None without a time budget."""
    if cfg.time_budget is None:
        return None
    saved = os.path.join(out_dir, "timing.json")
    path = args.timing or (saved if os.path.exists(saved) else None)
    if path is not None:
        table = budget.TimingTable.load(path)
    else:
        table = measure_timing(jax.tree.map(lambda x: x[0], obs), jax.tree.map(lambda x: x[0], goal), dynamics, cfg,
                               camera)
    table.save(saved)
    print(f"timing table ({table.device}, {'from ' + path if path else 'measured'}): Adam steps in "
          f"{cfg.time_budget} s: " + ", ".join(f"bucket {b}: {cfg.plan_steps(b, table)}" for b in cfg.buckets))
    return table


def shard_goals(args, shard: int, env) -> tuple[np.ndarray, np.ndarray]:
    """Goal masks [B, H, W] and shapes [B] (0 disc, 1 letter) of a shard: scenes 2j and 2j + 1 a disc and a letter of
    the same centre (near the bin centre) and area (``tasks.disc_and_letter``); shards 2s and 2s + 1 draw the same."""
    masks = []
    for j in range(0, args.batch, 2):
        rng = np.random.default_rng((args.seed, shard // 2, j // 2))
        disc, letter, _ = tasks.disc_and_letter(rng, env, LETTERS[rng.integers(len(LETTERS))])
        masks += [disc, letter]
    return np.stack(masks), np.arange(args.batch) % 2


def label_shard(args, shard: int, dynamics, processes, timings: list) -> dict:
    """Label one shard. timings: the run's timing table once known (``timing_table`` on the first shard's first
    scene, appended here), empty before; a list so every shard spends the budget by the same table."""
    sim = scene_config(args, shard)
    pool = WorldPool(sim, processes)
    camera, cfg = pool.camera, planner_config(pool.env, args)
    b, r = args.batch, args.repeats
    pile_keys = jax.vmap(lambda j: jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(args.seed), shard), j))(
        jnp.arange(b) // 2)  # scenes 2j and 2j + 1: the same pile
    start = pool.reset(pile_keys)
    goal_masks, shapes = shard_goals(args, shard, pool.env)
    goals = jax.tree.map(lambda *g: jnp.stack(g), *[make_goal(m, camera) for m in goal_masks])
    measure = jax.jit(jax.vmap(lambda obs, goal: distribution_distance(obs, goal, camera)))
    if not timings:
        timings.append(timing_table(args, args.out, start.obs, goals, dynamics, cfg, camera))
    timing = timings[0]
    plan_seed = args.seed + 1 if args.plan_seed is None else args.plan_seed
    if args.mid_episode:  # the closed loop at ω = MID_EPISODE_OMEGA first: scenes as adaptive ω meets them
        mid = dataclasses.replace(cfg, steps=args.mid_episode, omega=MID_EPISODE_OMEGA)
        keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(plan_seed), 200_000 + shard), b)
        start, _ = run_episodes(pool, start, goals, dynamics, mid, keys, log=lambda s: None, timing=timing)
    d0 = measure(start.obs, goals)

    def plan_at(obs, goal, key, omega, steps, bucket):
        particles, _, result = decide(obs, goal, key, None, dynamics, cfg, camera, omega, bucket=bucket, steps=steps)
        return result.best[0], particles

    plan_all = jax.jit(jax.vmap(plan_at, in_axes=(0, 0, 0, 0, 0, None)), static_argnums=5)
    rep = lambda x: jnp.repeat(x, r, axis=0)  # noqa: E731  [B] -> [B * R], repeats of a scene adjacent
    starts, goals_r = jax.tree.map(rep, start), jax.tree.map(rep, goals)

    def c_star(omega, i):
        """c*(ω) [B] of every scene (the mean of its repeats), the variance of that mean [B] (0 with one repeat) and
        the Adam steps [B] each plan ran (its bucket's, under the budget)."""
        keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(plan_seed), shard * 100 + i), b * r)
        buckets, steps = cfg.allot(omega, timing)
        bucket = int(buckets.max())
        actions, particles = plan_all(starts.obs, goals_r, keys, rep(omega), rep(jnp.asarray(steps)), bucket)
        check_particles(particles, rep(omega), bucket, f"shard {shard}: perception failed in plans (scene x "
                        f"{r} repeats)")
        after = pool.push(starts, actions)
        values = np.asarray(measure(after.obs, goals_r)).reshape(b, r)
        spread = values.var(axis=1, ddof=1) / r if r > 1 else np.zeros(b)
        return jnp.asarray(values.mean(axis=1)), spread, steps

    k = args.evals
    omega = jnp.zeros((b, k), jnp.int32)
    target, c_stars, plan_steps = jnp.zeros((b, k)), jnp.zeros((b, k)), np.zeros((b, k), np.int32)
    repeat_var = np.zeros((b, k))  # the measured variance of each evaluation: the GP's noise floor is its mean
    mask = jnp.zeros((b, k), bool)
    propose = jax.jit(jax.vmap(resolution.next_omega))
    for i in range(k):
        if i < len(FIRST):
            w = jnp.full(b, FIRST[i], jnp.int32)
        else:
            w = propose(omega, target, mask, jax.random.split(jax.random.fold_in(jax.random.PRNGKey(plan_seed), i), b),
                        jnp.asarray(repeat_var[:, :i].mean(axis=1)))
        c, repeat_var[:, i], plan_steps[:, i] = c_star(w, i)
        omega, mask = omega.at[:, i].set(w), mask.at[:, i].set(True)
        c_stars, target = c_stars.at[:, i].set(c), target.at[:, i].set(resolution.penalised(c, d0, w))
    label, mean = jax.jit(jax.vmap(resolution.best_omega))(omega, target, mask, jax.random.split(
        jax.random.fold_in(jax.random.PRNGKey(plan_seed), 100_000 + shard), b), jnp.asarray(repeat_var.mean(axis=1)))
    inputs = jax.vmap(lambda o, m: resolution.observation_input(o, m, camera))(start.obs, jnp.asarray(goal_masks))
    return dict(inputs=np.asarray(inputs), label=np.asarray(label), gp_mean=np.asarray(mean),
                omega=np.asarray(omega), c_plus=np.asarray(target), c_star=np.asarray(c_stars), d0=np.asarray(d0),
                plan_steps=plan_steps, repeat_var=repeat_var,
                goal_shape=shapes, layout=np.full(b, shard % 2), pile=np.arange(b) // 2, shard=np.int64(shard),
                mid_episode=np.int64(args.mid_episode))


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m experiments.label_resolution", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--scenes", type=int, default=1024)
    parser.add_argument("--batch", type=int, default=128, help="scenes per shard (even)")
    parser.add_argument("--evals", type=int, default=10, help="c+ evaluations per scene (reference 10)")
    parser.add_argument("--repeats", type=int, default=2, help="plans averaged per evaluation (reference 5)")
    add_planner_args(parser)
    parser.add_argument("--kind", default="coffee")
    parser.add_argument("--pieces", type=int, default=100)
    parser.add_argument("--ckpt", default=SHIPPED_DYNAMICS)
    parser.add_argument("--dynamics", default="auto", choices=["auto", "learned", "sweep"])
    parser.add_argument("--workers", type=int, default=None, help="C engine processes (default: every core)")
    parser.add_argument("--seed", type=int, default=0, help="the scenes (piles and goals)")
    parser.add_argument("--plan-seed", type=int, default=None,
                        help="the plans and the BO's random draws (default: --seed + 1); the same --seed with another "
                             "--plan-seed labels the same scenes again independently (label reliability)")
    parser.add_argument("--mid-episode", type=int, default=0, metavar="K",
                        help=f"label mid-episode states: each scene first runs K MPC steps towards its goal at "
                             f"ω = {MID_EPISODE_OMEGA} under the same budget (default 0: fresh piles, Fig. 4's pairs)")
    parser.add_argument("--part", default="0/1", help="I/K: label only shards I, I + K, ... so K machines share a "
                        "run over one folder (default 0/1: all)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes for a CPU smoke run")
    args = parser.parse_args(argv)
    try:
        part = parse_part(args.part)
    except ValueError as e:
        parser.error(str(e))
    if args.quick:
        args.scenes, args.batch, args.evals, args.repeats, args.pieces = 8, 4, 6, 1, 60  # 60: points for ω = 100
        args.samples, args.plan_steps = 4, 4
    if args.batch % 2 or args.batch < 2:
        parser.error("--batch must be even (scenes come in pairs)")
    check_planner_args(parser, args)
    if args.mid_episode < 0:
        parser.error(f"--mid-episode must be >= 0, got {args.mid_episode}")
    if args.evals <= len(FIRST):
        parser.error(f"--evals must exceed the {len(FIRST)} initial evaluations")
    dynamics, n_max, name = load_dynamics(args.dynamics, args.ckpt, SceneConfig.plate_half_width)
    if n_max < resolution.OMEGA_MAX:
        parser.error(f"the dynamics checkpoint holds {n_max} particles; labels need {resolution.OMEGA_MAX}")
    timings = []
    os.makedirs(args.out, exist_ok=True)
    files.write_json(os.path.join(args.out, "config.json"), dict(vars(args), dynamics_name=name))
    n_shards = -(-args.scenes // args.batch)
    todo = shards_todo(args.out, n_shards, part)
    t0 = time.perf_counter()
    with process_pool(args.workers) as processes:
        for s in tqdm(todo, desc="label shards", unit="shard"):
            save_npz(shard_path(args.out, s), label_shard(args, s, dynamics, processes, timings))
    minutes = (time.perf_counter() - t0) / 60
    labels = np.concatenate([np.load(p)["label"] for p in sorted(glob.glob(os.path.join(args.out, "shard_*.npz")))])
    summary = dict(scenes=len(labels), shards_written=len(todo), minutes=minutes,
                   labels_per_minute=len(todo) * args.batch / minutes if todo else 0.0,
                   device=jax.devices()[0].device_kind, dynamics=name,
                   label_mean=float(labels.mean()), label_histogram=np.histogram(labels, bins=10, range=(2, 102))[0]
                   .tolist())
    files.write_json(os.path.join(args.out, "summary.json"), summary)
    print(summary)
    return summary


if __name__ == "__main__":
    main()
