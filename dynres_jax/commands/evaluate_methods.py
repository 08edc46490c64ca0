"""``evaluate``'s methods (``commands.methods``' table): the flags that name them (checked before any work), the
chooser each one plans with, and the ω it plans at. Gather and Redistribute take every method; Sort (``--task sort``)
plans along A*'s waypoints at one ω a step (``sort.SortEpisodes``: one ``SortPolicy`` per episode), so it takes a
fixed ω and the ladder's rungs (bestK, sim, rerank) at --best-omega.
"""

from __future__ import annotations

from dynres_jax.commands import methods
from dynres_jax.control.choosers import Chooser, climb, on_ladder
from dynres_jax.control.sort import ARRIVED, MIXING, SortEpisodes, SortPolicy
from dynres_jax.io import ckpt
from dynres_jax.models.registry import describe, trained_n_max

DEFAULT_METHODS = ["10", "25", "50", "75", "100", "adaptive"]  # --methods' default (Sort's: SORT_DEFAULT)
SORT_DEFAULT = ["50"]
SORT_ONLY = ("arrived", "grid_step", "mixing")  # flags of Sort alone: not among another task's recorded settings
GRID_STEP = 0.02  # m: Sort's A* grid unless --grid-step


def default_methods(args, sort: bool) -> None:
    """--methods' default for the task (sort: whether it is Sort) when none are given."""
    if args.methods is None:
        args.methods = list(SORT_DEFAULT if sort else DEFAULT_METHODS)


def check_methods(parser, args, sort: bool) -> None:
    """--methods (each named once, "050" read as ω = 50) and the flags of Sort (sort: whether --task is Sort);
    parser.error naming a method no task runs, a method Sort cannot run, or Sort's flag given to another task."""
    default_methods(args, sort)
    for m in args.methods:
        if methods.method(m) is None:
            parser.error(f"--methods takes {methods.NAMES}, got {m!r}")
    args.methods = [str(int(m)) if m.isdigit() else m for m in args.methods]  # "050" is ω = 50
    if len(set(args.methods)) < len(args.methods):
        parser.error(f"--methods names a method twice: {' '.join(args.methods)}")
    if ("judge" in args.methods) != (args.judge is not None):
        parser.error("method 'judge' and --judge CKPT (the judge's checkpoint) go together; give both or neither")
    readers = {"best_omega": lambda m: on_ladder(m) or m == "judge", "cnn_omega": lambda m: m == "cnn",
               "cnn_ckpt": lambda m: m == "cnn", "regressor": lambda m: m == "adaptive"}
    for dest, reads in readers.items():
        if not any(map(reads, args.methods)) and getattr(args, dest) != parser.get_default(dest):
            what = {"best_omega": "bestK, sim, rerank and judge", "regressor": "adaptive"}.get(dest, "cnn")
            parser.error(f"--{dest.replace('_', '-')} is read by method {what}; --methods {' '.join(args.methods)} "
                         "runs none of them")
    if not sort:
        for flag in SORT_ONLY:
            if getattr(args, flag) is not None:
                parser.error(f"--{flag.replace('_', '-')} is Sort's (--task sort), not {args.task}'s")
        return
    args.arrived = ARRIVED if args.arrived is None else args.arrived
    args.grid_step = GRID_STEP if args.grid_step is None else args.grid_step
    args.mixing = MIXING if args.mixing is None else args.mixing
    odd = [m for m in args.methods if not methods.method(m).sort]
    if odd:
        parser.error(f"--methods: Sort plans along A*'s waypoints at one ω a step (fixed ω, or bestK, sim and rerank "
                     f"at --best-omega); it cannot run {' '.join(odd)}")
    if args.sensor != "none":
        parser.error("--sensor: Sort finds its piles on the simulator's exact frames (each kind's segmentation), "
                     "not through a depth camera's errors")


def method_chooser(name: str, goals, args, camera, judge=None) -> Chooser:
    """The chooser of evaluation method ``name`` against goals [B] (``methods.METHODS``' row: a fixed ω, "cnn" at
    --cnn-omega, the regressor, the probe, the oracle, the ladder's rungs at --best-omega, or the judge, ``judge``:
    radius -> --judge's model, choosing among the model's plans)."""
    return methods.method(name).chooser(name, goals, args, camera, judge)


def sort_chooser(method: str, drawn: list[dict], env, cfg, keys, episodes, args) -> Chooser:
    """Sort's chooser of an evaluation method: one ``SortPolicy`` per episode (its goal discs from ``drawn``, the
    goals' descriptions, and its planner key) at a fixed ω, or at --best-omega on the ladder's rung."""
    omega = args.best_omega if on_ladder(method) else int(method)
    policies = [SortPolicy(env, cfg, omega, key, goal["centres"], goal["radius"], grid_step=args.grid_step,
                           arrived=args.arrived, mixing=args.mixing, objective=args.objective,
                           log=lambda line, i=int(i): print(f"episode {i}: {line}"))
                for i, key, goal in zip(episodes, keys, drawn, strict=True)]
    chooser = SortEpisodes(policies)
    return climb(chooser, method) if on_ladder(method) else chooser


def method_omega(name: str, args) -> int | None:
    """The one ω a method plans at (a fixed ω, --best-omega of the ladder and the judge, cnn's --cnn-omega), or None
    for the methods that choose among ω (adaptive, probe, oracle)."""
    return methods.method(name).omega(name, args)


def method_omegas(args) -> list[int]:
    """The ω at which each method of --methods must afford an Adam step under a budget: a fixed method's ω, the
    coarsest for those that choose among ω."""
    return [methods.coarsest(m, args) for m in args.methods]


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
