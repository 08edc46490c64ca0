"""The paper's evaluation (Fig. 5): task score against threshold for adaptive ω and every fixed ω, on Gather and
Redistribute, many episodes at once; Sort's episodes with the same statistics.

    python -m experiments.evaluate --task gather --episodes 64 --out runs/eval
    python -m experiments.evaluate --task gather --methods 50 --adam-steps 100 --out runs/gather50
    python -m experiments.evaluate --task sort --kind almond mnm --methods 50 rerank --mpc-steps 30 --out runs/sort

Episode i of a task has the same pile, goal and planner keys for every method and any --episodes (seeded by (--seed,
i)). Each method runs all episodes together: perception and planning vmapped on the JAX device, pushes in the engine
of ``--backend``. With ``--time-budget S`` every method plans under the same budget of S seconds a decision, spent by
one timing table (``timing.json``, measured here or given by ``--timing``): a coarse ω affords more Adam steps.
Without it every decision runs ``--adam-steps``. Methods (``--methods``): fixed ω;
"adaptive", the regressor g picks ω every step; "probe", no labels: each step plans at each ω of PROBE_OMEGAS on an
equal share of the budget and keeps the plan whose model predicts the largest fall of c per second; "oracle" (an
upper bound) plans at each ω of ORACLE_OMEGAS and keeps the push that left the lowest d on copies of the worlds (the
summary says how much of its gain over the best fixed ω adaptive recovers, ``oracle_gap``); "cnn", the paper's
CNN-dynamics baseline at ``--cnn-omega``. The ladder of docs/ladder, where the simulator picks among the planner's
candidates at ``--best-omega`` (``choosers.BestOfK``, ``SimulatorScored``): "bestK" (e.g. best5) among K plans from
independent keys, the oracle's control; "sim" among the M first samples, no model; "rerank" among the M plans after
the model's Adam steps. Redistribute's episode i draws the letter i modulo ``--letters``; ``--goal-png G.png`` gives
every episode the user's goal (its pile still the task's, from (--seed, i)). Sort (``--kind A B``,
``--pieces NA NB``, default each kind at half its one-pile count; the shipped Sort model) plans along A*'s waypoints
(``sort.SortEpisodes``) at a fixed ω or on the ladder at --best-omega; its d is to the true goals, its inside share
the lower kind's, its success each kind at least 80 % inside and mixing below 5 % (``tasks.sort_succeeded``). Writes
per method
``METHOD.json`` (final d, inside share and success per episode, both at every step and their means per step;
finished methods are skipped on a rerun),
``summary.json`` (means with 95 % intervals, success rates and the share that met the rule at some step, every method
paired with adaptive or the first: Δ final d with a paired-bootstrap interval, McNemar's test), ``score.png`` and
``steps.png`` (mean d over the MPC steps).

Several processes share the episodes through jax.distributed (a launcher, or --coordinator, --num-processes,
--process-id): process I runs episodes I, I + K, ... of every method and writes ``parts/METHOD.I-of-K.json``;
process 0 merges them into ``METHOD.json`` and writes the summary.
"""

from __future__ import annotations

import contextlib
import json
import os

import numpy as np
from jax._src import xla_bridge  # whether the backends have started: XLA reads XLA_FLAGS when they do

from dynres_jax import distributed, progress
from dynres_jax.commands import checks, guard, methods
from dynres_jax.commands.evaluate_methods import (
    DEFAULT_METHODS,
    SORT_DEFAULT,
    SORT_ONLY,
    check_cnn,
    check_methods,
    method_chooser,
    method_omega,
    method_omegas,
    sort_chooser,
)
from dynres_jax.commands.evaluation import episode_results, label, merge, report, sort_records, summarise
from dynres_jax.commands.models import load_model
from dynres_jax.commands.planner_args import (
    add_planner_args,
    check_budget,
    load_timing,
    mpc_config,
    resolve_planner_args,
    timing_table,
)
from dynres_jax.commands.task import check_pile, check_visible, objective_default, objectives_text, resolve_objective
from dynres_jax.config import DEFAULT_PIECES, KINDS, CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control import tasks
from dynres_jax.control.goals import OBJECTIVES, make_goals, with_objective
from dynres_jax.control.mpc import run
from dynres_jax.control.sort import ARRIVED, MIXING
from dynres_jax.control.views import SensorView
from dynres_jax.io import ckpt, files
from dynres_jax.io.draw import evaluation_plots
from dynres_jax.io.frames import load_goal
from dynres_jax.models.registry import SHIPPED_CNN_DYNAMICS, SHIPPED_REGRESSOR, shipped_dynamics
from dynres_jax.resolution.regressor import load_regressor
from dynres_jax.sim import engines
from dynres_jax.sim.camera import Camera
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import make_pool, process_pool
from dynres_jax.sim.sensor import SENSORS

QUICK = dict(episodes=4, mpc_steps=3, samples=8, adam_steps=10)  # --quick's sizes, where a flag does not set them


def deterministic(parser) -> None:
    """Ask XLA for deterministic GPU kernels (``--xla_gpu_deterministic_ops``) before JAX starts its backends;
    parser.error when they have started already (the flag would do nothing)."""
    if xla_bridge.backends_are_initialized():
        parser.error("--deterministic must be set before JAX starts (run the command in a fresh process)")
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_gpu_deterministic_ops=true".strip()


def build_parser():
    """``evaluate``'s flags."""
    parser = checks.parser("evaluate", __doc__)
    parser.add_argument("--task", default="gather", choices=sorted(tasks.TASKS))
    parser.add_argument("--episodes", type=checks.count(1), default=64)
    parser.add_argument("--mpc-steps", type=checks.count(1), default=None,
                        help="MPC steps per episode (default: the task's, " + ", ".join(
                            f"{name} {task.mpc_steps}" for name, task in sorted(tasks.TASKS.items())) + ")")
    parser.add_argument("--stop-share", type=checks.stop_share, default=None,
                        help="an episode pushes no more once this share of the foreground its camera sees lies inside "
                             "the goal (Sort: of each kind's perceived pieces inside its own), or 'off' (default: the "
                             "task's, " + ", ".join(f"{name} {task.stop_share or 'off'}"
                                                    for name, task in sorted(tasks.TASKS.items())) + ")")
    parser.add_argument("--objective", default=None, choices=OBJECTIVES, nargs="+", metavar="C",
                        help=f"c's SDF term (Sort: one for both target discs or one per kind): {objectives_text()}; "
                             "default: the task's, " + ", ".join(
                                 f"{name} {objective_default(name)}" for name in sorted(tasks.TASKS)))
    parser.add_argument("--methods", nargs="+", default=None,
                        help=f"default {' '.join(DEFAULT_METHODS)} (Sort: {' '.join(SORT_DEFAULT)}). "
                             "Fixed ω (integers), 'adaptive' (the regressor picks ω), 'probe' (every step plans at "
                             "each ω of PROBE_OMEGAS on a share of the budget, keeps the one the model rates best per "
                             "second: no labels), 'oracle' (every step keeps the "
                             "best of ω in ORACLE_OMEGAS by the simulated outcome), 'bestK' (e.g. best5: every step "
                             "keeps the best of K plans at --best-omega by the simulated outcome, the oracle's "
                             "control), 'sim' (the simulator chooses among the planner's first samples, no model), "
                             "'rerank' (the simulator chooses among the planner's plans after the model's Adam steps), "
                             "'judge' (--judge's model chooses among them, at --best-omega) "
                             "and 'cnn' (the CNN-dynamics baseline at --cnn-omega); Sort takes fixed ω and the ladder")
    parser.add_argument("--best-omega", type=checks.omega, default=50, help="ω of the bestK, sim and rerank methods")
    add_planner_args(parser)
    parser.add_argument("--kind", nargs="+", default=None, choices=sorted(KINDS), metavar="KIND",
                        help=f"the piece kind (default coffee); Sort: two kinds, one a pile (default coffee candy); "
                             f"from {', '.join(sorted(KINDS))}")
    parser.add_argument("--letters", type=checks.text, default="JTU",
                        help="Redistribute: episode i's goal is character i modulo these (default JTU)")
    parser.add_argument("--goal-png", default=None, metavar="PNG",
                        help="every episode's goal: a mask PNG of the camera's size, white = goal (experiments.goal "
                             "writes them), instead of the task's drawn goals and --letters (not Sort)")
    parser.add_argument("--sensor", default="none", choices=sorted(SENSORS),
                        help="a real depth camera's errors on every observation the planner sees (sim.sensor; "
                             "perception then treats the depth as a real camera's); d and success use the true state")
    parser.add_argument("--pieces", nargs="+", type=checks.count(1), default=None, metavar="N",
                        help="pieces in the pile (default: the kind's count for a pile of 100 coffee beans' area); "
                             "Sort: of each kind (default: half that count each)")
    parser.add_argument("--arrived", type=checks.number(0.01, 1.0), default=None,
                        help=f"Sort: a pile counts as arrived (A* moves it no more) at this share of its particles "
                             f"inside its goal (default {ARRIVED}, Sort's success share)")
    parser.add_argument("--mixing", type=checks.number(0.0, 100.0), default=None,
                        help=f"Sort: weight in each kind's objective of its particles' depth inside the other kind's "
                             f"goal (default {MIXING:g}; 0: none)")
    parser.add_argument("--grid-step", type=checks.number(0.002, 0.1), default=None,
                        help="Sort: A*'s grid spacing (m; default 0.02)")
    parser.add_argument("--ckpt", default=None, help="the dynamics checkpoint (default: the task's shipped one)")
    parser.add_argument("--dynamics", default="auto", choices=["auto", "learned", "sweep"])
    parser.add_argument("--regressor", default=SHIPPED_REGRESSOR)
    parser.add_argument("--cnn-ckpt", default=SHIPPED_CNN_DYNAMICS, help="the CNN-dynamics checkpoint of method 'cnn'")
    parser.add_argument("--cnn-omega", type=checks.omega, default=50, help="ω of method 'cnn'")
    parser.add_argument("--judge", default=None, metavar="CKPT",
                        help="the judge's dynamics checkpoint, for method 'judge' (control/judge.py)")
    parser.add_argument("--workers", type=checks.workers(), default=None)
    checks.add_engine(parser)
    parser.add_argument("--seed", type=checks.seed, default=0)
    parser.add_argument("--out", required=True)
    checks.add_fresh(parser)
    parser.add_argument("--quick", action="store_true",
                        help="a CPU smoke run: 64 x 64 images; unless given, " + ", ".join(
                            f"--{k.replace('_', '-')} {v}" for k, v in QUICK.items()))
    parser.add_argument("--deterministic", action="store_true",
                        help="GPU: XLA's deterministic kernels for every op; the planner repeats without it, "
                             "this covers the rest (MJX engines); slower (docs/repeat)")
    distributed.add_args(parser)
    return parser


def resolve_scene(parser, args) -> tuple[tuple[str, ...], tuple[int, ...]]:
    """The scene's kinds and piece counts from --kind and --pieces (the task's count of kinds: one, Sort's two,
    different); parser.error naming a bad count or a pile too large for the bin. A single kind's task keeps --kind
    and --pieces as one value each (as its run.json records them)."""
    n = tasks.TASKS[args.task].kinds
    kinds = args.kind or (["coffee", "candy"] if n == 2 else ["coffee"])
    if len(kinds) != n:
        parser.error(f"--kind: {args.task} takes {n} kind{'s' if n > 1 else ''}, got {' '.join(kinds)}")
    if len(set(kinds)) < n:
        parser.error(f"--kind must name two different kinds, got {kinds[0]} twice")
    pieces = args.pieces or [DEFAULT_PIECES[k] // n for k in kinds]
    if len(pieces) != n:
        parser.error(f"--pieces: {args.task} takes {n} count{'s' if n > 1 else ''} (one per --kind), got "
                     f"{' '.join(map(str, pieces))}")
    check_pile(parser, kinds, pieces)
    args.kind, args.pieces = (kinds[0], pieces[0]) if n == 1 else (kinds, pieces)
    return tuple(kinds), tuple(pieces)


def apply_defaults(parser, args) -> None:
    """The defaults that depend on other flags: --quick's sizes (``QUICK``) where a flag does not set them, then the
    task's MPC steps and stop share (``tasks.Task``) where neither does ("off": no stop rule); the objective waits
    for the kinds (``check_args``)."""
    for name, value in QUICK.items() if args.quick else ():
        if getattr(args, name) == parser.get_default(name):
            setattr(args, name, value)
    if args.mpc_steps is None:
        args.mpc_steps = tasks.TASKS[args.task].mpc_steps
    task_share = tasks.TASKS[args.task].stop_share
    args.stop_share = task_share if args.stop_share is None else checks.stop_rule(args.stop_share)


def check_args(parser, args):
    """Resolve and check the flags before any work (parser.error naming the problem). Returns (rank, size, sim,
    main_model, cnn_model): this process in the job, the worlds' SimConfig and the loaded models."""
    apply_defaults(parser, args)
    if args.deterministic:
        deterministic(parser)
    rank, size = distributed.from_args(parser, args)
    resolve_planner_args(parser, args)
    table = load_timing(parser, args)
    sort = tasks.TASKS[args.task].kinds == 2
    check_methods(parser, args, sort)
    if " " in args.letters:
        parser.error(f"--letters: a space draws no goal, got {args.letters!r}")
    if args.letters != parser.get_default("letters") and not tasks.TASKS[args.task].letter:
        parser.error(f"--letters draws Redistribute's goals; --task {args.task} draws no letter")
    if "cnn" in args.methods:
        check_cnn(parser, args)
    if args.episodes < size:
        parser.error(f"--episodes must be at least the {size} processes of the job, got {args.episodes}")
    kinds, pieces = resolve_scene(parser, args)
    resolve_objective(parser, args, args.task, kinds)
    args.backend = checks.engine(parser, args.backend)
    checks.check_workers(parser, args.workers, args.backend)
    camera = CameraConfig(width=64, height=64) if args.quick else CameraConfig()
    sim = SimConfig(scene=SceneConfig(kinds=kinds, pieces=pieces), camera=camera,
                    pile=PileConfig(layout=tasks.TASKS[args.task].layout))
    args.ckpt = shipped_dynamics(args.task) if args.ckpt is None else args.ckpt
    main_model = load_model(parser, args.dynamics, args.ckpt, sim.scene.plate_half_width, shipped_dynamics(args.task))
    cnn_model = load_model(parser, "learned", args.cnn_ckpt, sim.scene.plate_half_width) if "cnn" in args.methods \
        else None
    judge = None if args.judge is None else load_model(parser, "learned", args.judge, sim.scene.plate_half_width,
                                                       flag="--judge")
    if judge is not None and args.best_omega > judge.n_max:
        parser.error(f"method judge: ω = {args.best_omega} exceeds the judge's n_max = {judge.n_max}")
    for m in args.methods:
        omega = method_omega(m, args) if m != "cnn" else None
        if omega is not None and omega > main_model.n_max:
            parser.error(f"method {m}: ω = {omega} exceeds the model's n_max = {main_model.n_max}")
    if "adaptive" in args.methods:
        try:
            load_regressor(args.regressor, Camera.top_down(camera))
        except ckpt.CheckpointError as e:
            parser.error(f"--regressor (method adaptive): {e}")
    env = PileEnv(sim, backend="mujoco")
    if args.goal_png is not None:
        if sort:
            parser.error("--goal-png: Sort draws a goal disc per kind, it takes no goal mask")
        try:
            tasks.mask_goal(env, load_goal(args.goal_png, env.camera))
        except ValueError as e:
            parser.error(f"--goal-png {args.goal_png}: {e}")
    if sort:
        try:
            tasks.draw_goal(args.task, 0, args.seed, env)
        except ValueError as e:
            parser.error(f"--pieces: {e}")
    cfg = mpc_config(env, args, args.mpc_steps)
    if table is not None:  # a given table must afford every method a step, before the first method runs
        check_budget(cfg, table, method_omegas(args), max(methods.reach(m, args) for m in args.methods))
    finest = max(methods.finest(m, args) for m in args.methods)
    check_visible(parser, env.reset(tasks.episode_keys(args.seed, [0])[0][0]).obs, env.camera, finest, cfg)
    return rank, size, sim, main_model, cnn_model, judge


def run_methods(args, rank: int, size: int, sim, main_model, cnn_model, judge=None) -> dict:
    """Every method of --methods on this process's share of the episodes (resuming finished methods and parts), merged
    over the job's processes. Returns {method: results}."""
    os.makedirs(os.path.join(args.out, "parts"), exist_ok=True)
    mine = np.arange(rank, args.episodes, size)  # this process's episodes
    results = {}
    with process_pool(args.workers) if engines.uses_workers(args.backend) else contextlib.nullcontext() as processes:
        pool = make_pool(sim, args.backend, processes)
        drawn = ([tasks.draw_goal(args.task, int(i), args.seed, pool.env, args.letters) for i in mine]
                 if args.goal_png is None else  # the user's goal, every episode's
                 [tasks.mask_goal(pool.env, load_goal(args.goal_png, pool.camera))] * len(mine))
        sort = tasks.TASKS[args.task].kinds == 2  # its goals: a disc per kind; d and the timing table: kind 0's
        goals = with_objective(make_goals([mask[0] if sort else mask for mask, _ in drawn], pool.camera),
                               args.objective[0] if sort else args.objective)  # episode i's goal (Sort: kind 0's)
        # depends on (seed, i) alone: each process draws its own
        pile_keys, keys = tasks.episode_keys(args.seed, mine)
        todo = [m for m in args.methods if not os.path.exists(os.path.join(args.out, f"{m}.json"))]
        _say_kept(args.methods, todo)
        cfg = mpc_config(pool.env, args, mpc_steps=args.mpc_steps, real_depth=args.sensor != "none",
                         stop_share=args.stop_share)
        timing = None
        if args.time_budget is not None and todo:  # one table for every method: the main model on the first episode
            timing = timing_table(args, args.out, pool.reset(pile_keys[:1]).obs, goals, main_model.dynamics, cfg,
                                  pool.camera, method_omegas(args))
        for method in args.methods:
            path = os.path.join(args.out, f"{method}.json")
            if method not in todo:
                with open(path) as f:
                    results[method] = json.load(f)
                continue
            model = cnn_model if method == "cnn" else main_model
            print(f"{args.task}: method {method}, {len(mine)} of {args.episodes} episodes, dynamics {model.name}")
            part = os.path.join(args.out, "parts", f"{method}.{rank}-of-{size}.json")
            if os.path.exists(part):
                with open(part) as f:
                    mine_done = json.load(f)
            else:
                starts = pool.reset(pile_keys)
                view = None if args.sensor == "none" else SensorView(SENSORS[args.sensor], pool.env)
                chooser = (sort_chooser(method, [info for _, info in drawn], pool.env, cfg, keys, mine, args) if sort
                           else method_chooser(method, goals, args, pool.camera,
                                               None if judge is None else judge.dynamics))
                finals, records = run(pool, starts, chooser, model.dynamics, cfg, keys, timing=timing, view=view)
                mine_done = episode_results(sort_records(records) if sort else records, mine, model.name, starts,
                                            finals)
                if size > 1:
                    files.write_json(part, mine_done)
            if size > 1:
                distributed.barrier(f"evaluate {os.path.abspath(path)}")
                parts = []
                for i in range(size):
                    with open(os.path.join(args.out, "parts", f"{method}.{i}-of-{size}.json")) as f:
                        parts.append(json.load(f))
            else:
                parts = [mine_done]
            results[method] = merge(parts)
            results[method]["success"] = tasks.episode_success(args.task, results[method]).tolist()
            if distributed.is_writer():
                files.write_json(path, results[method])
            _say_kept(args.methods, todo[todo.index(method) + 1:])
    return results


def _say_kept(methods: list[str], todo: list[str]) -> None:
    """What an interrupt's line says was kept: the finished methods (a method is kept whole, ``METHOD.json``), or
    nothing (an interrupted method starts again on a rerun)."""
    finished = [m for m in methods if m not in todo]
    guard.kept(f"method{'s' * (len(finished) > 1)} {', '.join(finished)} finished; a rerun goes on with the others"
               if finished else "")


@checks.guarded("evaluate")
def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    rank, size, sim, main_model, cnn_model, judge = check_args(parser, args)  # bad input: one line, nothing else
    sort_only = () if tasks.TASKS[args.task].kinds == 2 else SORT_ONLY  # another task's run.json is as before
    checks.claim(args.out, "evaluate", checks.settings(args, ignore=("methods", *sort_only)), args.fresh,
                 {"--ckpt": args.ckpt, "--regressor": args.regressor, "--cnn-ckpt": args.cnn_ckpt,
                  "--timing": args.timing, "--judge": args.judge, "--goal-png": args.goal_png})
    progress.start(checks.prog("evaluate"), f"{args.task}, methods {' '.join(args.methods)} on {args.episodes} "
                   f"episodes of {args.mpc_steps} steps, into {args.out} (finished methods are kept)")
    results = run_methods(args, rank, size, sim, main_model, cnn_model, judge)
    devices = sorted({r.get("device", "unrecorded") for r in results.values()})  # where the methods ran
    summary = dict(task=args.task, kind=args.kind, pieces=args.pieces, sensor=args.sensor, dynamics=main_model.name,
                   **({} if judge is None else {"judge": judge.name}),
                   device=", ".join(devices),
                   time_budget=args.time_budget, samples=args.samples, adam_steps=args.adam_steps,
                   deterministic=args.deterministic,
                   mpc_steps=args.mpc_steps, **summarise(results, args.task))
    if distributed.is_writer():
        files.write_json(os.path.join(args.out, "summary.json"), summary)
        evaluation_plots(results, args.task, args.out, {m: label(m, r) for m, r in results.items()})
    report(summary)
    return summary


if __name__ == "__main__":
    main()
