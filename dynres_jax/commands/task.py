"""One closed-loop episode of a task (``dynres_jax.control.tasks``) at a fixed or adaptive resolution ω; the body of
the task commands:

    python -m experiments.gather --out out/gather                          # a disc of random centre and radius
    python -m experiments.gather --resolution adaptive --out out/adaptive  # the regressor g picks ω every step
    python -m experiments.gather --time-budget 0.25 --out out/budget       # the Adam steps that fit in 0.25 s
    python -m experiments.redistribute --letter T --out out/redistribute   # any characters OpenCV draws
    python -m experiments.goal --letter 7 --height 0.12 --out seven.png    # your own shape (or --mask drawing.png)
    python -m experiments.redistribute --goal-png seven.png --out out/seven   # into it (gather takes --goal-png too)

Writes ``episode.gif`` (observation, goal in green, particles in red), ``final.png`` and ``metrics.json`` (a record
per MPC step). Dynamics: the trained checkpoint given by ``--ckpt`` (default: the shipped one); ``--dynamics sweep``
plans with the sweep heuristic instead.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import imageio.v3 as iio
import jax
import numpy as np

from dynres_jax.commands import checks, docstring, guard, methods
from dynres_jax.commands.models import add_judge_arg, judged, load_judge, load_model
from dynres_jax.commands.planner_args import add_budget_args, check_budget, load_timing
from dynres_jax.config import (
    DEFAULT_PIECES,
    KINDS,
    CameraConfig,
    PileConfig,
    SceneConfig,
    SimConfig,
)
from dynres_jax.control import budget, progress, tasks
from dynres_jax.control.choosers import Chooser
from dynres_jax.control.decision import batch
from dynres_jax.control.goals import OBJECTIVES, make_goal, with_objective
from dynres_jax.control.mpc import MPCConfig, measure_timing, run_episode
from dynres_jax.control.objective import inside_share
from dynres_jax.control.planner import planner_config
from dynres_jax.errors import InputError
from dynres_jax.io import files
from dynres_jax.io.ckpt import CheckpointError
from dynres_jax.io.draw import goal_frames
from dynres_jax.io.frames import load_goal
from dynres_jax.models.registry import (
    SHIPPED_REGRESSOR,
    LoadedDynamics,
    shipped_dynamics,
)
from dynres_jax.perception import visible_points
from dynres_jax.progress import at_terminal
from dynres_jax.resolution.regressor import load_regressor
from dynres_jax.sim.camera import Camera
from dynres_jax.sim.env import PileEnv, make_env

PROGRESS = "progress.npz"  # an unfinished episode's last step (``control.progress``), gone once metrics.json is written


def objectives_text() -> str:
    """--objective's choices in words (``goals.OBJECTIVES``), for the help of the commands that take it."""
    return " or ".join(f"'{name}' ({words})" for name, words in OBJECTIVES.items())


def objective_default(task: str) -> str:
    """The task's default c in words, with the kinds that plan on another (``tasks.Task.objective_for``)."""
    spec = tasks.TASKS[task]
    own = [f"{kind}: {objective}" for kind, objective in spec.kind_objectives]
    return spec.objective + (f" ({', '.join(own)})" if own else "")


def resolve_objective(parser: argparse.ArgumentParser, args, task: str, kinds) -> None:
    """args.objective from --objective (one for every kind or, in Sort, one per kind; default the task's for each
    kind, ``tasks.Task.objective_for``): a name for a one-kind task, a tuple of one per kind for Sort; parser.error
    naming a count that fits neither."""
    given = args.objective or [tasks.TASKS[task].objective_for(kind) for kind in kinds]
    if len(given) not in (1, len(kinds)):
        parser.error(f"--objective takes one value{' or one per kind' if len(kinds) > 1 else ''}, got "
                     f"{' '.join(given)}")
    chosen = tuple(given) * (len(kinds) // len(given))
    args.objective = chosen[0] if len(kinds) == 1 else chosen


def add_resolution_args(parser: argparse.ArgumentParser) -> None:
    """--resolution (a fixed ω, or a method of ``commands.methods`` that keeps by the model) and --regressor."""
    parser.add_argument("--resolution", type=methods.resolution_arg, default="50",
                        help="ω, the particles the planner reasons with: an integer, 'adaptive' (the regressor g picks "
                             "ω every step) or 'probe' (each step plans at 25, 50 and 100 and keeps the plan the "
                             "model rates best); neither is the default: neither beats the best fixed ω "
                             "(docs/results.md)")
    parser.add_argument("--regressor", default=None,
                        help=f"regressor checkpoint for --resolution adaptive (default {SHIPPED_REGRESSOR})")


def resolution_chooser(parser: argparse.ArgumentParser, args, camera, n_max: int
                       ) -> tuple[int | None, Callable[..., Chooser], dict]:
    """--resolution's (ω or None where it chooses among ω, goals [B] -> its Chooser, the files it reads by flag),
    parser.error naming --resolution or --regressor before any work."""
    name = args.resolution
    row = methods.method(name)
    omega = row.omega(name, args)
    if methods.finest(name, args) > n_max:
        parser.error(f"--resolution {name} plans at ω up to {methods.finest(name, args)}, beyond the model's n_max = "
                     f"{n_max}" + (f": give --resolution {n_max} or less" if name.isdigit() else ""))
    read = {}
    if row.needs != "--regressor" and args.regressor is not None:
        parser.error(f"--regressor is for --resolution adaptive; --resolution {name} would not use it")
    if row.needs == "--regressor":
        args = argparse.Namespace(**{**vars(args), "regressor": args.regressor or SHIPPED_REGRESSOR})
        try:
            load_regressor(args.regressor, camera)  # readable, before any work
        except CheckpointError as e:
            parser.error(f"--regressor: {e}")
        read["--regressor"] = args.regressor
    return omega, lambda goals: row.chooser(name, goals, args, camera, None), read


def add_loop_args(parser: argparse.ArgumentParser, task: str, adaptive: bool = True) -> None:
    """The flags every closed-loop task command takes (``--out`` defaults to out/TASK); adaptive: whether
    ``--resolution`` may be 'adaptive' (Sort plans at one ω)."""
    parser.add_argument("--seed", type=checks.seed, default=0)
    parser.add_argument("--mpc-steps", type=checks.count(1), default=tasks.TASKS[task].mpc_steps,
                        help=f"MPC steps per episode (default {tasks.TASKS[task].mpc_steps})")
    default, sort = tasks.TASKS[task].stop_share, tasks.TASKS[task].kinds == 2
    parser.add_argument("--stop-share", type=checks.stop_share, default=default,
                        help="stop pushing once this share of " + ("each kind's perceived pieces lies inside its goal"
                                                                   if sort else "the foreground the camera sees lies "
                                                                   "inside the goal") +
                             f", or 'off' (default {default or 'off'}; docs/redistribute, docs/sort)")
    parser.add_argument("--objective", default=None, choices=OBJECTIVES, nargs="+", metavar="C",
                        help=f"c's SDF term{', one for both target discs or one per kind' if sort else ''}: "
                             f"{objectives_text()}; default {objective_default(task)} (docs/redistribute)")
    if not adaptive:
        parser.add_argument("--resolution", type=checks.omega, default=50, help="ω: particles the planner reasons with")
    else:
        add_resolution_args(parser)
        add_judge_arg(parser)
    checks.add_engine(parser)
    parser.add_argument("--samples", type=checks.samples, default=50, help="action sequences optimised at once (M)")
    parser.add_argument("--adam-steps", type=checks.adam_steps, default=100,
                        help="Adam steps per plan (N; the most a plan may run under --time-budget)")
    add_budget_args(parser)
    parser.add_argument("--ckpt", default=None,
                        help=f"dynamics checkpoint (default {shipped_dynamics(task)} if present)")
    parser.add_argument("--dynamics", default="auto", choices=["auto", "learned", "sweep"],
                        help="auto: the checkpoint when there is one, else the sweep heuristic")
    parser.add_argument("--out", default=f"out/{task}")
    checks.add_fresh(parser)


def resolve_pieces(parser: argparse.ArgumentParser, args) -> None:
    """--pieces: the kind's default count (``DEFAULT_PIECES``) when not given; parser.error naming a pile too large for
    the bin, from the scene's config alone (before any scene is built)."""
    args.pieces = DEFAULT_PIECES[args.kind] if args.pieces is None else args.pieces
    check_pile(parser, (args.kind,), (args.pieces,))


def check_pile(parser: argparse.ArgumentParser, kinds, pieces) -> None:
    """parser.error naming --pieces when the pile of ``kinds`` x ``pieces`` is too large for the bin's goals
    (``tasks.check_pile_fits``), from the config alone."""
    try:
        tasks.check_pile_fits(SceneConfig(kinds=tuple(kinds), pieces=tuple(pieces)))
    except (InputError, ValueError) as e:
        parser.error(f"--pieces: {e}")


@dataclass(frozen=True)
class Loop:
    """What the loop flags ask for: the simulator, the planner's model, the MPC settings, the timing table of
    --timing (or None), the ω --resolution plans at (None where it chooses among ω, ``commands.methods``) and its
    chooser's factory (goals [B] -> Chooser); inputs: the files read, by flag (``checks.claim``'s); judge: --judge's
    model, or None."""

    env: PileEnv
    model: LoadedDynamics
    cfg: MPCConfig
    timing: budget.TimingTable | None
    omega: int | None
    choose: Callable[..., Chooser]
    inputs: dict
    judge: LoadedDynamics | None = None

    def chooser(self, goals) -> Chooser:
        """The loop's chooser against goals [B]: --resolution's; with a judge, its choice among that plan's refined
        candidates."""
        return judged(self.choose, self.judge)(goals)


def build_loop(args, sim: SimConfig, parser: argparse.ArgumentParser, task: str, own_inputs: dict | None = None
               ) -> Loop:
    """The ``Loop`` of ``task``'s loop flags; parser.error naming a bad flag, and --out's refusal (``own_inputs``: the
    command's own input files, by flag, hashed with the loop's), before any work (the scene is built last)."""
    resolve_objective(parser, args, task, sim.scene.kinds)
    model = load_model(parser, args.dynamics, args.ckpt, sim.scene.plate_half_width, shipped_dynamics(task))
    if isinstance(args.resolution, int):  # Sort: one ω, a SortPolicy plans at it
        if args.resolution > model.n_max:
            parser.error(f"--resolution {args.resolution} exceeds the model's n_max = {model.n_max}")
        omega, choose, read = args.resolution, None, {}
    else:
        omega, choose, read = resolution_chooser(parser, args, Camera.top_down(sim.camera), model.n_max)
    timing = load_timing(parser, args)
    inputs = {"--ckpt": None if args.dynamics == "sweep" else args.ckpt or shipped_dynamics(task),
              "--timing": args.timing, **read, **(own_inputs or {})}
    judge = load_judge(parser, args, sim.scene.plate_half_width, inputs) if hasattr(args, "judge") else None
    backend = checks.engine(parser, args.backend)
    checks.check_out(args.out, task, checks.settings(args), args.fresh, inputs)
    at_terminal(checks.prog(task), "building the scene: the simulator and its camera (seconds on a CPU)")
    env = make_env(sim, backend)
    try:
        planner = planner_config(env, samples=args.samples, adam_steps=args.adam_steps, seed=args.seed)
        cfg = MPCConfig(mpc_steps=args.mpc_steps, planner=planner, time_budget=args.time_budget,
                        stop_share=checks.stop_rule(args.stop_share),
                        buckets=getattr(args, "buckets", None) or MPCConfig.buckets)  # --timing's (``load_timing``)
    except ValueError as e:
        parser.error(str(e))
    name = str(args.resolution)
    check_budget(cfg, timing, [methods.coarsest(name, args)], methods.reach(name, args))
    return Loop(env, model, cfg, timing, omega, choose, inputs, judge)


def check_visible(parser: argparse.ArgumentParser, obs, camera: Camera, omega: int, cfg: MPCConfig,
                  flag: str = "--pieces", remedy: str = "use more pieces or a lower ω") -> None:
    """parser.error naming ``flag``, before any work, when the first frame shows fewer foreground points than the ω
    particles perception must sample (a pile of one or two pieces at ω = 50; the robot's frame of a few pixels),
    read as perception will read it (``cfg.real_depth``)."""
    points = visible_points(obs, camera, cfg.max_points, cfg.real_depth)
    if points < omega:
        parser.error(f"{flag}: the pile shows {points} foreground points, fewer than the ω = {omega} particles to "
                     f"sample from them; {remedy}")


def finished(out: str, resumed: bool, fresh: bool) -> dict | None:
    """The summary (metrics.json) of the same episode already finished in ``out`` (``resumed``: ``checks.claim``'s
    answer), said in one line, so a rerun does nothing; None to run it (nothing there yet, or ``fresh``)."""
    path = os.path.join(out, "metrics.json")
    if not resumed or fresh or not os.path.isfile(path):
        return None
    print(f"{out} holds this episode, finished (metrics.json, episode.gif, final.png); --fresh runs it again")
    with open(path) as f:
        return json.load(f)


def run_resumable(out: str, fresh: bool, env: PileEnv, state, chooser: Chooser, dynamics, cfg: MPCConfig, key,
                  timing: budget.TimingTable | None, frames, measure: Callable[[], budget.TimingTable], omegas
                  ) -> tuple:
    """A task command's episode (``run_episode`` from ``state`` with GIF ``frames``), resumable: after every step its
    progress (``control.progress``) and the timing table its decisions refined are saved in ``out``, and a rerun of
    the same settings goes on from the last finished step (``fresh``: from the start). Under a time budget without a
    table, ``measure()`` makes one (checked to afford ``omegas``). Returns (final state, records, timing table)."""
    saved, table, resume = os.path.join(out, PROGRESS), os.path.join(out, "timing.json"), None
    guard.kept("")  # no step finished yet
    if os.path.isfile(saved) and fresh:
        os.unlink(saved)
    elif os.path.isfile(saved):  # an interrupted run of these settings: go on from its last step, its table as it was
        resume, frames.frames = progress.load(saved, batch(state))
        frames.last = resume.records[-1]
        if cfg.time_budget is not None and os.path.isfile(table):  # refined as it was unless given frozen (--timing)
            timing = budget.TimingTable.load(table, frozen=timing is not None and timing.frozen)
            check_budget(cfg, timing, omegas or [min(cfg.buckets)])  # a table of other buckets: said before a step
        print(f"resuming the interrupted episode after step {len(resume.records)} of {cfg.mpc_steps} ({saved})")
        guard.kept(guard.span("the episode's step", len(resume.records), cfg.mpc_steps))
    if cfg.time_budget is not None and timing is None:
        timing = measure()
        check_budget(cfg, timing, omegas)

    def keep(now):  # after every step: the episode so far and the timing table its decisions refined
        progress.save(saved, now, frames.frames)
        if timing is not None:
            timing.save(table)
        guard.kept(guard.span("the episode's step", len(now.records), cfg.mpc_steps))

    state, records = run_episode(env, state, chooser, dynamics, cfg, key, timing=timing, on_step=[frames],
                                 resume=resume, on_progress=keep)  # keep saved the table after the last step too
    return state, records, timing


def write_metrics(out: str, summary: dict) -> None:
    """The finished episode's summary to ``out``/metrics.json; its progress file, no longer needed, removed."""
    files.write_json(os.path.join(out, "metrics.json"), summary)
    if os.path.exists(os.path.join(out, PROGRESS)):
        os.unlink(os.path.join(out, PROGRESS))


def write_episode(out: str, frames: list) -> None:
    """The episode's ``episode.gif`` (every frame) and ``final.png`` (the last) in ``out``, atomically."""
    files.atomic_write(os.path.join(out, "episode.gif"),
                       lambda f: iio.imwrite(f, np.stack(frames), extension=".gif", duration=400, loop=0))
    files.write_image(os.path.join(out, "final.png"), cv2.cvtColor(frames[-1], cv2.COLOR_RGB2BGR))


def _goal_png(parser: argparse.ArgumentParser, path: str, camera: Camera) -> np.ndarray:
    """--goal-png's mask [H, W] bool, read before the scene is built; parser.error naming the file."""
    try:
        return load_goal(path, camera)
    except ValueError as e:
        hint = (" (this command's camera is the simulator's: make the goal with `python -m experiments.goal` without "
                "--camera)" if "camera's images are" in str(e) else "")
        parser.error(f"--goal-png {path}: {e}{hint}")


def main(task: str, argv=None):
    spec = tasks.TASKS[task]
    _, examples, rest = (docstring(__name__).split("\n\n", 2) + ["", ""])[:3]
    mine = [line for line in examples.splitlines() if f"experiments.{task} " in line or "goal" in line.split("#")[0]]
    parser = checks.parser(task, "\n\n".join([spec.description, "\n".join(mine), rest]))
    add_loop_args(parser, task)
    parser.add_argument("--kind", default="coffee", choices=sorted(KINDS))
    parser.add_argument("--pieces", type=checks.count(1), default=None,
                        help="pieces in the pile (default: the kind's count for a pile of 100 coffee beans' area)")
    parser.add_argument("--layout", default=spec.layout, choices=["blob", "two_blobs", "spread"], help="initial pile")
    parser.add_argument("--goal-png", default=None, metavar="PNG",
                        help="the goal: a mask PNG of the camera's size, white = goal (experiments.goal writes them), "
                             "instead of the task's drawn goal")
    if spec.letter:
        parser.add_argument("--letter", default=None, type=checks.text,
                            help="the goal: any characters OpenCV draws (paper: J, T, U; default T)")
    args = parser.parse_args(argv)
    if spec.letter and args.letter is not None and args.goal_png is not None:
        parser.error("--letter and --goal-png each give the goal: give one")
    if spec.letter:
        args.letter = "T" if args.letter is None else args.letter
    resolve_pieces(parser, args)

    sim = SimConfig(scene=SceneConfig(kinds=(args.kind,), pieces=(args.pieces,)), pile=PileConfig(layout=args.layout),
                    camera=CameraConfig())
    drawn = None if args.goal_png is None else _goal_png(parser, args.goal_png, Camera.top_down(sim.camera))
    loop = build_loop(args, sim, parser, task, {"--goal-png": args.goal_png})
    env, cfg, timing = loop.env, loop.cfg, loop.timing

    rng = np.random.default_rng(args.seed)
    try:
        if drawn is not None:
            goal_mask, goal_info = tasks.mask_goal(env, drawn)
            goal_info["path"] = args.goal_png
        else:
            goal_mask, goal_info = spec.goal(rng, env, args.letter if spec.letter else None)
    except ValueError as e:
        parser.error(f"--goal-png {args.goal_png}: {e}" if args.goal_png is not None else
                     f"--letter {args.letter!r}: {e}" if spec.letter else str(e))
    state = env.reset(jax.random.PRNGKey(args.seed))
    check_visible(parser, state.obs, env.camera, methods.finest(args.resolution, args), cfg)
    done = finished(args.out, checks.claim(args.out, task, checks.settings(args), args.fresh, loop.inputs), args.fresh)
    if done is not None:
        return done
    objective = args.objective
    goal = with_objective(make_goal(goal_mask, env.camera), objective)
    start_inside = float(inside_share(state.pos, np.ones(env.scene.n_pieces, bool), goal, env.camera))
    budget_text = (f"{args.samples} samples, {args.adam_steps} Adam steps" if args.time_budget is None else
                   f"{args.samples} samples, {args.time_budget} s per decision (at most {args.adam_steps} Adam steps)")
    judged = "" if loop.judge is None else f"; judge: {loop.judge.name}"
    print(f"{task}: {args.pieces} {args.kind} pieces, goal {goal_info}; dynamics: {loop.model.name}{judged}; "
          f"ω = {args.resolution}; {budget_text}; c: {objective}")
    t0 = time.perf_counter()
    frames = goal_frames(goal_mask, env.camera)
    state, records, timing = run_resumable(
        args.out, args.fresh, env, state, loop.chooser(batch(goal)), loop.model.dynamics, cfg,
        jax.random.PRNGKey(args.seed), timing, frames,
        lambda: measure_timing(state.obs, goal, loop.model.dynamics, cfg, env.camera,
                               omegas=None if loop.omega is None else [loop.omega]),
        [methods.coarsest(args.resolution, args)])
    write_episode(args.out, frames.finish(batch(state)))
    summary = dict(task=task, seed=args.seed, kind=args.kind, pieces=args.pieces, dynamics=loop.model.name,
                   judge=None if loop.judge is None else loop.judge.name, goal=goal_info, resolution=args.resolution,
                   start_inside=start_inside,
                   final_inside=records[-1]["inside"], final_distance=records[-1]["distance"],
                   seconds=time.perf_counter() - t0, mpc=dataclasses.asdict(cfg),
                   timing=timing.to_json() if timing else None, steps=records)
    write_metrics(args.out, summary)
    print(f"pieces inside the goal: {start_inside:.0%} -> {summary['final_inside']:.0%}; "
          f"wrote {args.out}/episode.gif, final.png, metrics.json")
    return summary
