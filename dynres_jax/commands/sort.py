"""Sort (paper Sec. V): two piles of different kinds, each pushed into its own disc without mixing, an A* planner
over blob centres choosing which pile moves where (``dynres_jax.control.sort``):

    python -m experiments.sort --out out/sort
    python -m experiments.sort --kind coffee candy --pieces 40 20 --mpc-steps 30

Writes ``episode.gif`` (observation; goal of kind 0 blue, of kind 1 orange; the current waypoint disc green; the
moved kind's particles red), ``final.png`` and ``metrics.json`` (a record per MPC step, the start and final share
of each kind inside its own goal, the mixing: the share of pieces inside the other kind's goal, and ``success`` by
Sort's rule, ``tasks.sort_succeeded``: each kind at least 80 % inside, mixing below 5 %; each step's ``inside`` is
the share of all pieces inside their own kind's goal and ``distance`` d to the step's waypoint discs, ``kind_inside``
the share per kind and ``goal_distance`` d to the true goals). A pile counts as arrived (A* leaves it at its goal)
at ``--arrived`` of its particles inside its goal, by default Sort's success share. ``evaluate --task sort`` runs
many such episodes with paired statistics. Dynamics: the trained checkpoint given by ``--ckpt`` (default: the shipped
one); ``--dynamics sweep`` plans with the sweep heuristic instead. ``--method`` climbs the ladder of
``experiments.evaluate`` on the same A* waypoints: ``bestK`` keeps the best of K plans from independent keys by their
pushes on copies of the world, ``sim`` lets the simulator choose among the planner's first samples (no model; M pushes
a step, slow) and ``rerank`` among its plans after the model's Adam steps.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from dynres_jax.commands import checks
from dynres_jax.commands.task import (
    add_loop_args,
    build_loop,
    check_pile,
    finished,
    run_resumable,
    write_episode,
    write_metrics,
)
from dynres_jax.config import KINDS, CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control.choosers import climb, on_ladder
from dynres_jax.control.decision import batch
from dynres_jax.control.goals import make_goal
from dynres_jax.control.mpc import measure_timing
from dynres_jax.control.sort import ARRIVED, MIXING, SortPolicy
from dynres_jax.control.tasks import sort_goal, sort_scores, sort_succeeded, success_rule
from dynres_jax.io.draw import sort_frames


def build_parser():
    """``sort``'s flags."""
    parser = checks.parser("sort", __doc__)
    add_loop_args(parser, "sort", adaptive=False)
    parser.add_argument("--kind", nargs=2, dest="kinds", default=["coffee", "candy"], choices=sorted(KINDS),
                        metavar="KIND",
                        help=f"the two piece kinds, one a pile (from {', '.join(sorted(KINDS))})")
    parser.add_argument("--pieces", nargs=2, type=checks.count(1), default=[40, 20], metavar="N",
                        help="pieces of each kind")
    parser.add_argument("--grid-step", type=checks.number(0.002, 0.1), default=0.02, help="A*'s grid spacing (m)")
    parser.add_argument("--arrived", type=checks.number(0.01, 1.0), default=ARRIVED,
                        help="a pile counts as arrived at its goal (A* moves it no more) when this share of its "
                             "particles lies inside it (default: Sort's success share)")
    parser.add_argument("--mixing", type=checks.number(0.0, 100.0), default=MIXING,
                        help=f"weight in each kind's objective of its particles' depth inside the other kind's goal "
                             f"(default {MIXING:g}; 0: none)")
    parser.add_argument("--method", default="model",
                        help="model: the planner with the dynamics model (default); bestK (e.g. best5): the best of "
                             "K plans by their simulated pushes; sim: the simulator chooses among the planner's first "
                             "samples; rerank: among its plans after the model's Adam steps")
    return parser


@checks.guarded("sort")
def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.method != "model" and not on_ladder(args.method):
        parser.error(f"--method takes 'model', 'sim', 'rerank' or 'bestK' (K >= 1), got {args.method!r}")
    if args.kinds[0] == args.kinds[1]:
        parser.error(f"--kind must name two different kinds, got {args.kinds[0]} twice")
    check_pile(parser, args.kinds, args.pieces)

    sim = SimConfig(scene=SceneConfig(kinds=tuple(args.kinds), pieces=tuple(args.pieces)),
                    pile=PileConfig(layout="two_blobs"), camera=CameraConfig())
    loop = build_loop(args, sim, parser, "sort")
    env, cfg, timing = loop.env, loop.cfg, loop.timing

    try:
        goals_xy, radius, masks = sort_goal(np.random.default_rng(args.seed), env)
    except ValueError as e:
        parser.error(str(e))
    resumed = checks.claim(args.out, "sort", checks.settings(args), args.fresh, loop.inputs)
    done = finished(args.out, resumed, args.fresh)
    if done is not None:
        return done
    goals = [make_goal(m, env.camera) for m in masks]
    state = env.reset(jax.random.PRNGKey(args.seed))
    start_inside, start_mixing = sort_scores(state.pos, env.scene.kind, goals, env.camera)
    print(f"sort: {args.pieces[0]} {args.kinds[0]} + {args.pieces[1]} {args.kinds[1]} pieces, goals "
          f"{np.round(goals_xy, 3).tolist()} radius {radius:.3f} m; dynamics: {loop.model.name}; "
          f"ω = {args.resolution}; {args.samples} x {args.adam_steps} Adam steps")
    t0 = time.perf_counter()
    key = jax.random.PRNGKey(args.seed)
    policy = SortPolicy(env, cfg, loop.omega, key, goals_xy, radius, grid_step=args.grid_step, arrived=args.arrived,
                        mixing=args.mixing, objective=args.objective)  # orders from each frame alone: resumable
    frames = sort_frames(masks, lambda: policy.target_mask, env.camera)
    chooser = policy if args.method == "model" else climb(policy, args.method)
    state, records, timing = run_resumable(
        args.out, args.fresh, env, state, chooser, loop.model.dynamics, cfg, key, timing, frames,
        lambda: measure_timing(state.obs, goals[0], loop.model.dynamics, cfg, env.camera, omegas=[loop.omega]),
        [loop.omega])
    write_episode(args.out, frames.finish(batch(state)))
    summary = dict(task="sort", seed=args.seed, method=args.method, dynamics=loop.model.name, kinds=args.kinds,
                   pieces=args.pieces,
                   goals=goals_xy.tolist(), radius=radius, resolution=args.resolution, start_inside=start_inside,
                   start_mixing=start_mixing, final_inside=records[-1]["kind_inside"],
                   final_mixing=records[-1]["mixing"], final_distance=records[-1]["goal_distance"],
                   success=sort_succeeded(records[-1]["kind_inside"], records[-1]["mixing"]),
                   seconds=time.perf_counter() - t0, mpc=dataclasses.asdict(cfg),
                   timing=timing.to_json() if timing else None, steps=records)
    write_metrics(args.out, summary)
    inside = summary["final_inside"]
    print(f"inside own goal: {args.kinds[0]} {start_inside[0]:.0%} -> {inside[0]:.0%}, {args.kinds[1]} "
          f"{start_inside[1]:.0%} -> {inside[1]:.0%}; mixing {start_mixing:.0%} -> {summary['final_mixing']:.0%}; "
          f"{'success' if summary['success'] else 'no success'} ({success_rule('sort')}); wrote "
          f"{args.out}/episode.gif, final.png, metrics.json")
    return summary


if __name__ == "__main__":
    main()
