"""The paper's evaluation (Fig. 5): task score against threshold for adaptive ω and every fixed ω, on Gather and
Redistribute, many episodes at once.

    python -m experiments.evaluate --task gather --episodes 64 --out runs/eval
    python -m experiments.evaluate --task gather --methods 50 --adam-steps 100 --out runs/gather50

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
the model's Adam steps. Redistribute's episode i draws the letter i modulo ``--letters``. Writes per method
``METHOD.json`` (final d and inside share per episode, means per step; finished methods are skipped on a rerun),
``summary.json`` (means with 95 % intervals, success rates, every method paired with adaptive or the first: Δ final d
with a paired-bootstrap interval, McNemar's test), ``score.png`` and ``steps.png`` (mean d over the MPC steps).

Several processes share the episodes through jax.distributed (a launcher, or --coordinator, --num-processes,
--process-id): process I runs episodes I, I + K, ... of every method and writes ``parts/METHOD.I-of-K.json``;
process 0 merges them into ``METHOD.json`` and writes the summary.
"""

from __future__ import annotations

import contextlib
import json
import os

import jax
import numpy as np
from jax._src import xla_bridge  # whether the backends have started: XLA reads XLA_FLAGS when they do

from dynres_jax import distributed, progress
from dynres_jax.commands import checks
from dynres_jax.commands.planner_args import (
    add_planner_args,
    check_budget,
    load_timing,
    mpc_config,
    resolve_planner_args,
    timing_table,
)
from dynres_jax.commands.task import check_visible, load_model, resolve_pieces
from dynres_jax.config import KINDS, OMEGA_MAX, OMEGA_MIN, CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control import resolution, tasks
from dynres_jax.control.choosers import (
    ORACLE_OMEGAS,
    PROBE_OMEGAS,
    AdaptiveOmega,
    Chooser,
    FixedOmega,
    OracleOmega,
    ProbeOmega,
    best_of,
    climb,
    on_ladder,
)
from dynres_jax.control.goals import make_goals
from dynres_jax.control.mpc import SensorView, run
from dynres_jax.io import ckpt, files
from dynres_jax.io.draw import evaluation_plots
from dynres_jax.models.registry import (
    SHIPPED_CNN_DYNAMICS,
    SHIPPED_DYNAMICS,
    SHIPPED_REGRESSOR,
    describe,
    trained_n_max,
)
from dynres_jax.sim import engines
from dynres_jax.sim.camera import Camera
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import make_pool, process_pool
from dynres_jax.sim.sensor import SENSORS
from dynres_jax.stats import mcnemar, paired_bootstrap, wilson

QUICK = dict(episodes=4, mpc_steps=3, samples=8, adam_steps=10)  # --quick's sizes, where a flag does not set them


def episode_results(records: list[dict], episodes, name: str, starts, finals) -> dict:
    """One process's episodes of a method (``run_episodes``' records): per-step arrays [T][B] and the final values
    [B], with the episode indices [B], and where every piece started and ended (starts, finals: State [B])."""
    steps = lambda key: np.stack([x[key] for x in records]).tolist()  # noqa: E731
    xy = lambda states: np.round(np.asarray(states.pos)[..., :2], 5).tolist()  # noqa: E731  (0.01 mm)
    return dict(episode=[int(i) for i in episodes], distance=steps("distance"), inside=steps("inside"),
                start_pieces=xy(starts), final_pieces=xy(finals),
                omega=steps("omega"), adam_steps=steps("adam_steps"), broken=records[-1]["broken"].tolist(),
                seconds=float(sum(x["seconds"] for x in records)), dynamics=name,
                device=jax.devices()[0].device_kind)


def merge(parts: list[dict]) -> dict:
    """The processes' ``episode_results`` of one method -> the method's results in episode order: final d and inside
    share [E], their means per step [T], ω and Adam steps per step [T][E], broken [E], seconds (the slowest
    process's), and every piece's (x, y) at the start and the end [E][N][2] (m)."""
    order = np.argsort(np.concatenate([p["episode"] for p in parts]))
    cat = lambda key: np.concatenate([np.asarray(p[key]) for p in parts], axis=-1)[..., order]  # noqa: E731
    distance, inside = cat("distance"), cat("inside")
    pieces = lambda key: np.concatenate([np.asarray(p[key]) for p in parts])[order].tolist()  # noqa: E731
    return dict(final_distance=distance[-1].tolist(), final_inside=inside[-1].tolist(),
                start_pieces=pieces("start_pieces"), final_pieces=pieces("final_pieces"),
                mean_distance=distance.mean(axis=1).tolist(), mean_inside=inside.mean(axis=1).tolist(),
                omega=cat("omega").tolist(), broken=cat("broken").tolist(), adam_steps=cat("adam_steps").tolist(),
                seconds=max(p["seconds"] for p in parts), dynamics=parts[0]["dynamics"], device=parts[0]["device"],
                processes=len(parts))


def summarise(results: dict) -> dict:
    """Per method: means with 95 % intervals and the success share. Beside them, ``paired``: each other method
    against the reference (adaptive when evaluated, else the first method) on the same episodes: the mean of its
    final d minus the reference's with a paired-bootstrap 95 % interval, and McNemar's test on success."""
    out = {}
    for method, r in results.items():
        d, inside = np.array(r["final_distance"]), np.array(r["final_inside"])
        n, k = len(d), int(np.sum(tasks.succeeded(inside)))
        out[method] = dict(episodes=n, final_distance=float(d.mean()),
                           final_distance_ci95=float(1.96 * d.std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0,
                           final_inside=float(inside.mean()), success_share=k / n, success_ci95=wilson(k, n),
                           mean_omega=float(np.mean(r["omega"])), broken=int(np.sum(r["broken"])),
                           dynamics=r.get("dynamics"))
    reference = "adaptive" if "adaptive" in results else next(iter(results))
    ref = results[reference]
    paired = {}
    for method, r in results.items():
        if method == reference or len(r["final_distance"]) < 2:
            continue
        paired[method] = dict(
            delta_d=paired_bootstrap(r["final_distance"], ref["final_distance"]),
            success=mcnemar(tasks.succeeded(r["final_inside"]), tasks.succeeded(ref["final_inside"])))
    summary = dict(methods=out, reference=reference, paired=paired)
    fixed = [m for m in results if m.isdigit()]
    if fixed and "oracle" in results and "adaptive" in results:  # how much of the oracle's gain adaptive recovers
        best = min(fixed, key=lambda m: out[m]["final_distance"])
        gain = out[best]["final_distance"] - out["oracle"]["final_distance"]
        summary["oracle_gap"] = dict(best_fixed=best, oracle_gain=gain,
                                     adaptive_gain=out[best]["final_distance"] - out["adaptive"]["final_distance"],
                                     recovered=((out[best]["final_distance"] - out["adaptive"]["final_distance"]) / gain
                                                if gain > 0 else None))
    return summary


def label(method: str, r: dict) -> str:
    """A method's name in the plots: "ω = 50", "adaptive", "CNN, ω = 50", "best of 5, ω = 50"."""
    if method.isdigit():
        return f"ω = {method}"
    if best_of(method):
        return f"best of {best_of(method)}, ω = {round(float(np.mean(r['omega'])))}"
    if method == "sim":
        return "simulator chooses among samples"
    if method == "rerank":
        return "simulator ranks the model's plans"
    return f"CNN, ω = {round(float(np.mean(r['omega'])))}" if method == "cnn" else method


def method_chooser(method: str, goals, args, camera) -> Chooser:
    """The chooser of an evaluation method against goals [B]: a fixed ω ("50"; "cnn" at --cnn-omega), the
    regressor ("adaptive"), the probe of PROBE_OMEGAS judged by the model ("probe"), the oracle over
    ORACLE_OMEGAS, the best of K plans at --best-omega ("bestK", e.g. "best5"), or the simulator choosing among
    the planner's first samples ("sim") or among its plans after the model's Adam steps ("rerank"), both at
    --best-omega."""
    if method == "adaptive":
        return AdaptiveOmega(goals, resolution.load_regressor(args.regressor, camera))
    if method == "oracle":
        return OracleOmega(goals, ORACLE_OMEGAS)
    if method == "probe":
        return ProbeOmega(goals)
    if on_ladder(method):
        return climb(FixedOmega(goals, args.best_omega), method)
    return FixedOmega(goals, args.cnn_omega if method == "cnn" else int(method))


def deterministic(parser) -> None:
    """Ask XLA for deterministic GPU kernels (``--xla_gpu_deterministic_ops``) before JAX starts its backends;
    parser.error when they have started already (the flag would do nothing)."""
    if xla_bridge.backends_are_initialized():
        parser.error("--deterministic must be set before JAX starts (run the command in a fresh process)")
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_gpu_deterministic_ops=true".strip()


def method_omega(method: str, args) -> int | None:
    """The one ω a method plans at (a fixed ω, --best-omega of bestK, sim and rerank, cnn's --cnn-omega), or None for
    the methods that choose among ω (adaptive, oracle)."""
    if method.isdigit():
        return int(method)
    if on_ladder(method):
        return args.best_omega
    return args.cnn_omega if method == "cnn" else None


def method_omegas(args) -> list[int]:
    """The ω at which each method of --methods must afford an Adam step under a budget: a fixed method's ω, the
    coarsest for those that choose among ω."""
    return [OMEGA_MIN if (w := method_omega(m, args)) is None else w for m in args.methods]


def check_cnn(parser, args) -> None:
    """Method "cnn" needs a CNN checkpoint at --cnn-ckpt and a valid --cnn-omega; parser.error naming what is wrong."""
    try:
        meta = ckpt.load_meta(args.cnn_ckpt)
    except ckpt.CheckpointError as e:
        parser.error(f"method 'cnn' needs a CNN dynamics checkpoint (python -m experiments.train_dynamics --model cnn)"
                     f"; --cnn-ckpt: {e}")
    if meta.get("model_class", "gnn") != "cnn":
        parser.error(f"--cnn-ckpt {args.cnn_ckpt!r} holds {describe(meta)}, not a cnn dynamics model")
    try:
        if args.cnn_omega > (n_max := trained_n_max(meta, args.cnn_ckpt)):
            parser.error(f"--cnn-omega {args.cnn_omega} exceeds the CNN model's n_max = {n_max}")
    except ckpt.CheckpointError as e:
        parser.error(f"--cnn-ckpt: {e}")


def build_parser():
    """``evaluate``'s flags."""
    parser = checks.parser("evaluate", __doc__)
    parser.add_argument("--task", default="gather", choices=sorted(tasks.TASKS))
    parser.add_argument("--episodes", type=checks.count(1), default=64)
    parser.add_argument("--mpc-steps", type=checks.count(1), default=20, help="MPC steps per episode")
    parser.add_argument("--methods", nargs="+", default=["10", "25", "50", "75", "100", "adaptive"],
                        help="fixed ω (integers), 'adaptive' (the regressor picks ω), 'probe' (every step plans at "
                             "each ω of PROBE_OMEGAS on a share of the budget, keeps the one the model rates best per "
                             "second: no labels), 'oracle' (every step keeps the "
                             "best of ω in ORACLE_OMEGAS by the simulated outcome), 'bestK' (e.g. best5: every step "
                             "keeps the best of K plans at --best-omega by the simulated outcome, the oracle's "
                             "control), 'sim' (the simulator chooses among the planner's first samples, no model), "
                             "'rerank' (the simulator chooses among the planner's plans after the model's Adam steps) "
                             "and 'cnn' (the CNN-dynamics baseline at --cnn-omega)")
    parser.add_argument("--best-omega", type=checks.omega, default=50, help="ω of the bestK, sim and rerank methods")
    add_planner_args(parser)
    parser.add_argument("--kind", default="coffee", choices=sorted(KINDS))
    parser.add_argument("--letters", type=checks.text, default="JTU",
                        help="Redistribute: episode i's goal is character i modulo these (default JTU)")
    parser.add_argument("--sensor", default="none", choices=sorted(SENSORS),
                        help="a real depth camera's errors on every observation the planner sees (sim.sensor; "
                             "perception then treats the depth as a real camera's); d and success use the true state")
    parser.add_argument("--pieces", type=checks.count(1), default=None,
                        help="pieces in the pile (default: the kind's count for a pile of 100 coffee beans' area)")
    parser.add_argument("--ckpt", default=SHIPPED_DYNAMICS)
    parser.add_argument("--dynamics", default="auto", choices=["auto", "learned", "sweep"])
    parser.add_argument("--regressor", default=SHIPPED_REGRESSOR)
    parser.add_argument("--cnn-ckpt", default=SHIPPED_CNN_DYNAMICS, help="the CNN-dynamics checkpoint of method 'cnn'")
    parser.add_argument("--cnn-omega", type=checks.omega, default=50, help="ω of method 'cnn'")
    parser.add_argument("--workers", type=checks.count(1, 1024), default=None)
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


def check_args(parser, args):
    """Resolve and check the flags before any work (parser.error naming the problem). Returns (rank, size, sim,
    main_model, cnn_model): this process in the job, the worlds' SimConfig and the loaded models."""
    for name, value in QUICK.items() if args.quick else ():
        if getattr(args, name) == parser.get_default(name):
            setattr(args, name, value)
    if args.deterministic:
        deterministic(parser)
    rank, size = distributed.from_args(parser, args)
    resolve_planner_args(parser, args)
    table = load_timing(parser, args)
    for m in args.methods:
        fixed = m.isdigit() and OMEGA_MIN <= int(m) <= OMEGA_MAX
        if m not in ("adaptive", "probe", "oracle", "cnn") and not fixed and not on_ladder(m):
            parser.error(f"--methods takes 'adaptive', 'probe', 'oracle', 'cnn', 'sim', 'rerank', 'bestK' (K >= 1) or "
                         f"integers in [{OMEGA_MIN}, {OMEGA_MAX}], got {m!r}")
    args.methods = [str(int(m)) if m.isdigit() else m for m in args.methods]  # "050" is ω = 50
    if len(set(args.methods)) < len(args.methods):
        parser.error(f"--methods names a method twice: {' '.join(args.methods)}")
    if " " in args.letters:
        parser.error(f"--letters: a space draws no goal, got {args.letters!r}")
    if "cnn" in args.methods:
        check_cnn(parser, args)
    if args.episodes < size:
        parser.error(f"--episodes must be at least the {size} processes of the job, got {args.episodes}")
    resolve_pieces(parser, args)
    args.backend = checks.engine(parser, args.backend)
    camera = CameraConfig(width=64, height=64) if args.quick else CameraConfig()
    sim = SimConfig(scene=SceneConfig(kinds=(args.kind,), pieces=(args.pieces,)), camera=camera,
                    pile=PileConfig(layout=tasks.TASKS[args.task].layout))
    main_model = load_model(parser, args.dynamics, args.ckpt, sim.scene.plate_half_width)
    cnn_model = load_model(parser, "learned", args.cnn_ckpt, sim.scene.plate_half_width) if "cnn" in args.methods \
        else None
    for m in args.methods:
        omega = method_omega(m, args) if m != "cnn" else None
        if omega is not None and omega > main_model.n_max:
            parser.error(f"method {m}: ω = {omega} exceeds the model's n_max = {main_model.n_max}")
    if "adaptive" in args.methods:
        try:
            resolution.load_regressor(args.regressor, Camera.top_down(camera))
        except ckpt.CheckpointError as e:
            parser.error(f"--regressor (method adaptive): {e}")
    env = PileEnv(sim, backend="mujoco")
    cfg = mpc_config(env, args, args.mpc_steps)
    if table is not None:  # a given table must afford every method a step, before the first method runs
        check_budget(cfg, table, method_omegas(args))
    finest = max(max(ORACLE_OMEGAS) if m == "oracle" else max(PROBE_OMEGAS) if m == "probe" else w
                 for m, w in zip(args.methods, method_omegas(args), strict=True))  # adaptive: at least OMEGA_MIN
    check_visible(parser, env.reset(tasks.episode_keys(args.seed, [0])[0][0]).obs, env.camera, finest, cfg)
    return rank, size, sim, main_model, cnn_model


def run_methods(args, rank: int, size: int, sim, main_model, cnn_model) -> dict:
    """Every method of --methods on this process's share of the episodes (resuming finished methods and parts), merged
    over the job's processes. Returns {method: results}."""
    os.makedirs(os.path.join(args.out, "parts"), exist_ok=True)
    mine = np.arange(rank, args.episodes, size)  # this process's episodes
    results = {}
    with process_pool(args.workers) if engines.uses_workers(args.backend) else contextlib.nullcontext() as processes:
        pool = make_pool(sim, args.backend, processes)
        goals = make_goals([tasks.episode_goal(args.task, int(i), args.seed, pool.env, args.letters) for i in mine],
                           pool.camera)  # episode i's goal depends on (seed, i) alone: each process draws its own
        pile_keys, keys = tasks.episode_keys(args.seed, mine)
        todo = [m for m in args.methods if not os.path.exists(os.path.join(args.out, f"{m}.json"))]
        cfg = mpc_config(pool.env, args, mpc_steps=args.mpc_steps, real_depth=args.sensor != "none")
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
                finals, records = run(pool, starts, method_chooser(method, goals, args, pool.camera), model.dynamics,
                                      cfg, keys, timing=timing, view=view)
                mine_done = episode_results(records, mine, model.name, starts, finals)
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
            if distributed.is_writer():
                files.write_json(path, results[method])
    return results


def report(summary: dict) -> None:
    """Each method's line and each paired comparison's."""
    for method, s in summary["methods"].items():
        print(f"{method:>8}: final d {s['final_distance']:8.2f} ± {s['final_distance_ci95']:.2f}  inside "
              f"{s['final_inside']:.1%}  ≥{tasks.SUCCESS:.0%} inside in {s['success_share']:.0%} of episodes  "
              f"mean ω {s['mean_omega']:.1f}")
    for method, p in summary["paired"].items():
        lo, hi = p["delta_d"]["ci95"]
        m = p["success"]
        print(f"{method:>8} - {summary['reference']}: Δd {p['delta_d']['mean']:+.2f} [{lo:+.2f}, {hi:+.2f}]  "
              f"successes only here {m['first_only']}, only there {m['second_only']} (McNemar p = {m['p']:.3f})")


@checks.guarded("evaluate")
def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    progress.start(checks.prog("evaluate"), f"{args.task}, methods {' '.join(args.methods)} on {args.episodes} "
                   f"episodes of {args.mpc_steps} steps, into {args.out} (finished methods are kept); loading the "
                   "models and the simulator")
    rank, size, sim, main_model, cnn_model = check_args(parser, args)
    checks.claim(args.out, "evaluate", checks.settings(args, ignore=("methods",)), args.fresh,
                 {"--ckpt": args.ckpt, "--regressor": args.regressor, "--cnn-ckpt": args.cnn_ckpt,
                  "--timing": args.timing})
    results = run_methods(args, rank, size, sim, main_model, cnn_model)
    devices = sorted({r.get("device", "unrecorded") for r in results.values()})  # where the methods ran
    summary = dict(task=args.task, kind=args.kind, pieces=args.pieces, sensor=args.sensor, dynamics=main_model.name,
                   device=", ".join(devices),
                   time_budget=args.time_budget, samples=args.samples, adam_steps=args.adam_steps,
                   deterministic=args.deterministic,
                   mpc_steps=args.mpc_steps, **summarise(results))
    if distributed.is_writer():
        files.write_json(os.path.join(args.out, "summary.json"), summary)
        evaluation_plots(results, args.task, args.out, {m: label(m, r) for m, r in results.items()})
    report(summary)
    return summary


if __name__ == "__main__":
    main()
