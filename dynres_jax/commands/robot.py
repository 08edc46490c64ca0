"""A robot's closed loop (``control.robot``) on the simulator as camera and arm, or on recorded frames:

    python -m experiments.robot --out out/robot                             # the simulator, a RealSense's profile
    python -m experiments.robot --goal out/G.png --image-size 256 --out out/robot   # a goal PNG of 256 x 256 pixels
    python -m experiments.robot --replay out/robot/frames --out out/replay  # recorded frames: a dry run

Each step reads a frame, stops when ``--success`` of its foreground lies inside the goal (or after ``--steps`` pushes),
plans one push at ω with the dynamics model (``--judge CKPT``: a second model chooses among the planner's refined
candidates), checks it against the bin's workspace and sends it. The simulator's frames pass through ``--sensor``
(default: a RealSense D455's noise, holes and calibration error) and ``--calibrate`` refines the camera's pose from the
first frame, as on a real setup. ``--dry-run`` plans and records but pushes nothing (always so with ``--replay``).
Writes ``frames/NNN/`` (each frame as a camera saves it: depth.png in mm, rgb.png, camera.json; a replay source),
``episode.gif`` (the goal green, the particles red, the push blue) and ``metrics.json`` (per frame: d and the share
inside as the robot saw them, the push; for the simulator also the true share of pieces inside at the end and
``succeeded``, whether it meets the task's success rule; ``reached`` is the camera's stop rule). Interrupted (Ctrl-C),
the same command goes on after the last push (``progress.npz``; ``--calibrate`` then refines the pose from the frame it
resumes on). A real camera and arm plug into ``control.robot.run_robot`` (its docstring shows a RealSense and an arm in
a few lines).
"""

from __future__ import annotations

import json
import os

import jax
import numpy as np

from dynres_jax.commands import checks, guard, methods
from dynres_jax.commands.models import add_judge_arg, judged, load_judge, load_model
from dynres_jax.commands.task import (
    PROGRESS,
    add_resolution_args,
    check_visible,
    resolution_chooser,
    resolve_pieces,
    write_episode,
    write_metrics,
)
from dynres_jax.config import KINDS, CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control import progress
from dynres_jax.control.goals import disc_goal, make_goal
from dynres_jax.control.mpc import MPCConfig
from dynres_jax.control.objective import inside_share
from dynres_jax.control.planner import planner_config
from dynres_jax.control.robot import STOP_SHARE, DryRun, ReplaySource, SimulatedRobot, Workspace, run_robot
from dynres_jax.control.tasks import succeeded
from dynres_jax.io.draw import caption, overlay
from dynres_jax.io.frames import load_goal, read_mask, save_frame
from dynres_jax.models.registry import SHIPPED_DYNAMICS
from dynres_jax.sim.camera import MAX_IMAGE, MIN_IMAGE
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.sensor import SENSORS


def build_parser():
    """``robot``'s flags."""
    parser = checks.parser("robot", __doc__)
    parser.add_argument("--replay", default=None, metavar="DIR", help="recorded frames instead of the simulator")
    parser.add_argument("--dry-run", action="store_true", help="plan and record, push nothing")
    parser.add_argument("--goal", default=None, help="goal PNG of the camera's size (default: a disc of 8 cm at the "
                                                     "bin's centre)")
    parser.add_argument("--kind", default=None, choices=sorted(KINDS), help="the simulator's pieces (default coffee)")
    parser.add_argument("--pieces", type=checks.count(1), default=None, help="default: the kind's count")
    parser.add_argument("--sensor", default=None, choices=sorted(SENSORS),
                        help="the simulator's camera profile (default realsense; a --replay's frames are as recorded)")
    parser.add_argument("--image-size", type=checks.count(MIN_IMAGE, MAX_IMAGE), default=None,
                        help=f"the simulator camera's width and height, pixels (default {CameraConfig().width}; a goal "
                             "PNG's size: 256 for one `goal` made from `simulate`'s frame)")
    parser.add_argument("--calibrate", action="store_true", help="refine the camera's pose from the first frame")
    parser.add_argument("--steps", type=checks.count(1), default=20, help="pushes at most (default 20)")
    parser.add_argument("--success", type=checks.number(0.01, 1.0), default=STOP_SHARE,
                        help=f"stop when this share of the foreground the camera sees lies inside the goal (default "
                             f"{STOP_SHARE})")
    add_resolution_args(parser)
    add_judge_arg(parser)
    parser.add_argument("--samples", type=checks.samples, default=50)
    parser.add_argument("--adam-steps", type=checks.adam_steps, default=100)
    parser.add_argument("--ckpt", default=SHIPPED_DYNAMICS)
    parser.add_argument("--dynamics", default="auto", choices=["auto", "learned", "sweep"])
    parser.add_argument("--seed", type=checks.seed, default=0)
    parser.add_argument("--out", default="out/robot")
    checks.add_fresh(parser)
    return parser


@checks.guarded("robot")
def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.replay:
        given = [flag for flag in ("--sensor", "--kind", "--pieces", "--image-size")
                 if getattr(args, flag[2:].replace("-", "_")) is not None]
        if given:
            parser.error(f"{', '.join(given)}: the simulator's; a --replay's frames are read as they were recorded")
    args.kind, args.image_size = args.kind or "coffee", args.image_size or CameraConfig().width
    resolve_pieces(parser, args)
    args.sensor = None if args.replay else args.sensor or "realsense"
    sim = SimConfig(scene=SceneConfig(kinds=(args.kind,), pieces=(args.pieces,)), pile=PileConfig(layout="spread"),
                    camera=CameraConfig(width=args.image_size, height=args.image_size))
    model = load_model(parser, args.dynamics, args.ckpt, sim.scene.plate_half_width)
    env = PileEnv(sim, backend="mujoco", render=args.replay is None)
    source = ReplaySource(args.replay) if args.replay else SimulatedRobot(env, jax.random.PRNGKey(args.seed),
                                                                          SENSORS[args.sensor])
    camera = source.camera
    _, choose, read = resolution_chooser(parser, args, camera, model.n_max)
    judge = load_judge(parser, args, sim.scene.plate_half_width, read)
    try:
        goal_mask = load_goal(args.goal, camera) if args.goal else disc_goal(camera, np.zeros(2), 0.08)
        make_goal(goal_mask, camera)
    except ValueError as e:
        size = read_mask(args.goal, "goal file").shape if "camera's images are" in str(e) else ()
        hint = (f" (--image-size {size[0]}: the simulator's frames at the goal's size)"
                if len(size) == 2 and size[0] == size[1] and not args.replay else "")
        parser.error(f"--goal: {e}{hint}")
    cfg = MPCConfig(mpc_steps=args.steps, real_depth=True, planner=planner_config(
        env, samples=args.samples, adam_steps=args.adam_steps, seed=args.seed))
    if isinstance(source, SimulatedRobot):  # the first frame, as the camera gives it, can hold ω particles
        check_visible(parser, source.peek(), camera, methods.finest(args.resolution, args), cfg, flag="--image-size",
                      remedy="a larger --image-size, more --pieces or a lower --resolution")
    checks.claim(args.out, "robot", checks.settings(args), args.fresh,
                 {"--ckpt": args.ckpt, "--goal": args.goal, "--replay": args.replay, **read})
    pusher = DryRun() if args.dry_run or args.replay else source
    resume, frames, kept = resumed(args.out, source, args.steps)

    def record(t, obs, particles, step):  # the robot's view: saved as a camera saves it, and a GIF frame
        save_frame(os.path.join(args.out, "frames", f"{t:03d}"), obs, camera)
        label = caption(particles, dict(step=t, omega=[step.get("omega", args.resolution)], distance=[step["distance"]],
                                        inside=[step["inside"]]))
        frames.append(overlay(np.asarray(obs.rgb), goal_mask, particles, camera, label=label,
                              push=step.get("action")))

    print(f"robot: {'replay of ' + args.replay + ' (recorded frames)' if args.replay else 'the simulator'}"
          f"{'' if args.replay else f' ({args.sensor} camera)'}, "
          f"{'dry run' if isinstance(pusher, DryRun) else 'pushing'}; dynamics {model.name}"
          f"{'' if judge is None else '; judge ' + judge.name}; ω = {args.resolution}")
    steps = run_robot(source, pusher, goal_mask, model.dynamics, cfg, judged(choose, judge),
                      jax.random.PRNGKey(args.seed),
                      workspace=Workspace.of(env), success=args.success, on_step=record,
                      bin_size=(sim.scene.bin_half_width, sim.scene.wall_height) if args.calibrate else None,
                      resume=resume, on_progress=lambda now: kept(now, frames))
    write_episode(args.out, frames)
    summary = dict(source=args.replay or "simulator", sensor=args.sensor, dry_run=isinstance(pusher, DryRun),
                   dynamics=model.name, judge=None if judge is None else judge.name, resolution=args.resolution,
                   pushes=sum("action" in s for s in steps),
                   reached=steps[-1]["inside"] >= args.success, steps=steps)
    if isinstance(source, SimulatedRobot):  # what the robot could not see: the pieces' true places
        true_goal = make_goal(goal_mask if args.goal else disc_goal(env.camera, np.zeros(2), 0.08), env.camera)
        pos = source.state.pos
        summary["true_inside"] = float(inside_share(pos, np.ones(len(pos), bool), true_goal, env.camera))
        summary["succeeded"] = bool(succeeded(summary["true_inside"]))  # the task's rule (reached: the camera's)
    write_metrics(args.out, summary)
    print(json.dumps({k: v for k, v in summary.items() if k != "steps"}))
    return summary


def resumed(out: str, source, steps: int):
    """An interrupted episode in ``out`` (``PROGRESS``): (its ``Progress`` or None, the GIF frames drawn so far, and
    ``kept(now, frames)``, which saves the progress after every push), the source moved on to the frame after the last
    push (the simulator's world as it was left). A real camera needs nothing: its world stayed where the arm left it."""
    saved, simulated = os.path.join(out, PROGRESS), isinstance(source, SimulatedRobot)

    def kept(now, frames):
        progress.save(saved, now._replace(states=source.state if simulated else None), frames)
        guard.kept(guard.span("the episode's push", len(now.records), steps))

    if not os.path.isfile(saved):
        guard.kept("")  # no push finished yet
        return None, [], kept
    now, frames = progress.load(saved, source.state if simulated else None)
    now = now._replace(records=[{k: np.asarray(v).tolist() for k, v in r.items()} for r in now.records])
    if simulated:  # frame t is the world's read t + 1 (its sensor's key)
        source.state, source.frames = now.states, len(now.records)
    elif isinstance(source, ReplaySource):
        source.next = len(now.records)
    print(f"resuming the interrupted episode after push {len(now.records)} of {steps} ({saved})")
    guard.kept(guard.span("the episode's push", len(now.records), steps))
    return now, frames, kept


if __name__ == "__main__":
    main()
