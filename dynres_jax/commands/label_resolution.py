"""Label scenes with their best resolution by Bayesian optimisation (paper Sec. IV-C), for the regressor g.

    python -m experiments.label_resolution --out runs/labels --scenes 1024
    python -m experiments.label_resolution --out /tmp/labels --quick        # a CPU smoke run

For every scene (a settled pile and a goal), ``c+(ω) = c*(ω) + w_R · d_0 · ω`` is evaluated at ω = 2, 25, 50, 75,
100 and then at ``--evals`` - 5 more ω chosen by Expected Improvement; c*(ω) is the distribution distance d after one
push planned at ω under the time budget (``--time-budget`` seconds per decision on this device, spent by a timing
table measured once per resolution bucket and saved as ``timing.json``: a coarse ω affords more Adam steps) and
executed in the simulator, averaged over ``--repeats`` plans (common random numbers: every ω of a scene is planned
from the same --repeats keys); d_0 is d before the push. The label is the argmin
of the GP posterior mean; the GP's noise is never below the measured variance of an evaluation (the repeats'
variance over their count, averaged over the scene's evaluations so far; ``repeat_var`` in the shards).

Scenes come in shards of ``--batch`` scenes, all simulated, planned and optimised together (vmapped; pushes in C
worker processes). Pairs for the paper's Fig. 4, as the paper poses them: in every shard, scenes 2j and 2j + 1 share
the pile and differ in the goal (a disc and a letter of the same centre, near the bin centre, and the same area);
shards 2s and 2s + 1 share their goals and differ in the pile (spread over the bin vs one blob near the bin centre,
so near the goal). With ``--mid-episode K`` each scene first runs K steps of the closed loop towards its goal, so the
labels cover the states adaptive ω meets mid-episode (the pairs then no longer share their piles).
Each shard is written atomically (``shard_NNNNN.npz``) and a rerun skips finished shards. --backend: the engine that
executes the planned pushes (default "mujoco", C worker processes; "mjx-fast" and "auto" as in generate_data); with
--backend warp, ``--cpu-workers K`` C processes label shards beside it, whichever engine is free taking the next (each
shard records its ``engine``). Several
processes share a run through jax.distributed (a launcher, or --coordinator, --num-processes, --process-id): process
I labels shards I, I + K, ... into the same --out.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import time

import jax
import numpy as np

from dynres_jax import distributed, progress
from dynres_jax.commands import checks
from dynres_jax.commands.models import load_model
from dynres_jax.commands.planner_args import (
    add_planner_args,
    load_timing,
    mpc_config,
    resolve_planner_args,
    timing_table,
)
from dynres_jax.commands.task import check_pile
from dynres_jax.config import KINDS, OMEGA_MAX, OMEGA_MIN, SceneConfig
from dynres_jax.io import files
from dynres_jax.io.shards import complete_shards, fill, read_shard, save_npz, shard_path
from dynres_jax.learn.data import shards_todo
from dynres_jax.learn.labels import MID_EPISODE_OMEGA, LabelConfig, label_shard, scene_config, shard_scenes
from dynres_jax.models.registry import SHIPPED_DYNAMICS
from dynres_jax.sim import engines
from dynres_jax.sim.pool import make_pool, process_pool


def build_parser():
    """``label_resolution``'s flags."""
    parser = checks.parser("label_resolution", __doc__)
    parser.add_argument("--out", required=True)
    checks.add_fresh(parser)
    parser.add_argument("--scenes", type=checks.count(1), default=1024)
    parser.add_argument("--batch", type=checks.count(2), default=128, help="scenes per shard (even)")
    parser.add_argument("--evals", type=checks.count(1), default=10, help="c+ evaluations per scene (reference 10)")
    parser.add_argument("--repeats", type=checks.count(1), default=2,
                        help="plans averaged per evaluation (reference 5)")
    add_planner_args(parser)
    parser.add_argument("--kind", default="coffee", choices=sorted(KINDS))
    parser.add_argument("--pieces", type=checks.count(1), default=100)
    parser.add_argument("--ckpt", default=SHIPPED_DYNAMICS)
    parser.add_argument("--dynamics", default="auto", choices=["auto", "learned", "sweep"])
    parser.add_argument("--workers", type=checks.workers(), default=None,
                        help="C engine processes (default: every core)")
    parser.add_argument("--cpu-workers", type=checks.workers(0), default=0,
                        help="C MuJoCo processes labelling shards beside --backend warp, whichever engine is free "
                             "(default 0: the engine alone)")
    parser.add_argument("--seed", type=checks.seed, default=0, help="the scenes (piles and goals)")
    parser.add_argument("--plan-seed", type=checks.seed, default=None,
                        help="the plans and the BO's random draws (default: --seed + 1); the same --seed with another "
                             "--plan-seed labels the same scenes again independently (label reliability)")
    parser.add_argument("--mid-episode", type=checks.count(0, 100), default=0, metavar="K",
                        help=f"label mid-episode states: each scene first runs K MPC steps towards its goal at "
                             f"ω = {MID_EPISODE_OMEGA} under the same budget (default 0: fresh piles, Fig. 4's pairs)")
    checks.add_engine(parser)
    parser.add_argument("--quick", action="store_true", help="tiny sizes for a CPU smoke run")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    distributed.add_args(parser)
    return parser


@checks.guarded("label_resolution")
def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    distributed.from_args(parser, args)
    args.backend = checks.engine(parser, args.backend)
    checks.check_workers(parser, args.workers, args.backend)
    checks.quick_sets(parser, args, ("scenes", "batch", "evals", "repeats", "pieces", "samples", "adam_steps"))
    if args.quick:
        args.scenes, args.batch, args.evals, args.repeats, args.pieces = 8, 4, 6, 1, 60  # 60: points for ω = 100
        args.samples, args.adam_steps = 4, 4
    resolve_planner_args(parser, args)
    load_timing(parser, args)
    check_pile(parser, (args.kind,), (args.pieces,))
    try:
        cfg = LabelConfig(kind=args.kind, pieces=args.pieces, batch=args.batch, evals=args.evals, repeats=args.repeats,
                          seed=args.seed, plan_seed=args.plan_seed, mid_episode=args.mid_episode, quick=args.quick,
                          backend=args.backend)
        helper_cfg = engines.beside(cfg, args.cpu_workers)
    except ValueError as e:
        parser.error(str(e))
    dynamics, n_max, name = load_model(parser, args.dynamics, args.ckpt, SceneConfig.plate_half_width)
    if n_max < OMEGA_MAX:
        parser.error(f"the dynamics checkpoint holds {n_max} particles; labels need {OMEGA_MAX}")
    checks.claim(args.out, "label_resolution", checks.settings(args), args.fresh,
                 {"--ckpt": args.ckpt, "--timing": args.timing})
    progress.start(checks.prog("label_resolution"), f"{args.scenes} {args.kind} scenes of {args.pieces} pieces in "
                   f"shards of {args.batch}, into {args.out} (finished shards are kept); the first shard compiles "
                   "(minutes on a CPU)")
    if distributed.is_writer():
        files.write_json(os.path.join(args.out, "config.json"), dict(vars(args), dynamics_name=name))
    n_shards = -(-args.scenes // args.batch)
    todo = shards_todo(args.out, n_shards)
    t0 = time.perf_counter()
    planner = functools.partial(mpc_config, args=args)
    workers = process_pool(args.workers) if engines.uses_workers(args.backend) else None
    helpers = process_pool(args.cpu_workers) if args.cpu_workers and todo else None
    with workers or contextlib.nullcontext() as processes, helpers or contextlib.nullcontext():
        timing = None
        # One table for the run, measured on the first scene to do if not given; in a job every process takes part
        # (process 0 measures, the rest wait for its table), whether or not it has shards left.
        if args.time_budget is not None and (todo or distributed.part()[1] > 1):
            first = (todo or [0])[0]
            pool = make_pool(scene_config(cfg, first), args.backend, processes)
            start, _, goals, _ = shard_scenes(cfg, first, pool)
            timing = timing_table(args, args.out, start.obs, goals, dynamics, planner(pool.env), pool.camera,
                                  [OMEGA_MIN])
        bar = progress.bar(total=len(todo), desc="label", unit="shard", quiet=args.quiet)

        def producer(engine_cfg: LabelConfig, pool_processes):
            def produce(s: int) -> None:
                save_npz(shard_path(args.out, s), label_shard(engine_cfg, s, dynamics, planner, pool_processes, timing))
                bar.update()

            return produce

        fill(todo, [producer(cfg, processes)] + ([producer(helper_cfg, helpers)] if helpers else []))
        bar.close()
    minutes = (time.perf_counter() - t0) / 60
    distributed.barrier(f"label {os.path.abspath(args.out)}")
    labels = np.concatenate([read_shard(p, ("label",))["label"] for p in complete_shards(args.out, "--out", "labels")])
    summary = dict(scenes=len(labels), shards_written=len(todo), minutes=minutes,
                   labels_per_minute=len(todo) * args.batch / minutes if todo else 0.0,
                   device=jax.devices()[0].device_kind, dynamics=name,
                   label_mean=float(labels.mean()), label_histogram=np.histogram(labels, bins=10, range=(2, 102))[0]
                   .tolist())
    if distributed.is_writer():
        files.write_json(os.path.join(args.out, "summary.json"), summary)
    print(json.dumps(summary))  # JSON, as every command prints a record
    return summary


if __name__ == "__main__":
    main()
