"""Plan one push for a recorded RGBD frame (a real camera's, or one the simulator saved with ``frames.save_frame``):

    python -m experiments.plan --depth D.png --rgb C.png --camera cam.json --goal out/G.png --out out/push.png

Depth is a 16-bit PNG in millimetres (as depth cameras save it), the camera a JSON file (``Camera.to_json``: K,
rotation camera-to-world, centre, width, height; world frame z up, table at z = 0), the goal a black-and-white PNG
of the camera's size. Prints the push (x_start, y_start, x_end, y_end) in metres and draws it over the frame.
"""

from __future__ import annotations

import argparse
import json
import sys

import cv2
import jax
import numpy as np

from dynres_jax.commands import checks
from dynres_jax.commands.models import load_model
from dynres_jax.config import SceneConfig
from dynres_jax.control.budget import bucket_for
from dynres_jax.control.decision import DecisionSpec, batch, decide_batch, episode
from dynres_jax.control.goals import check_within, make_goal
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.io import files, frames
from dynres_jax.io.draw import overlay
from dynres_jax.models.registry import SHIPPED_DYNAMICS, SWEEP_NAME
from dynres_jax.perception import WORKSPACE_HALF_WIDTH, calibrate, visible_points
from dynres_jax.sim.pushes import wall_reach
from dynres_jax.sim.sensor import SENSORS


def build_parser():
    """``plan``'s flags."""
    parser = checks.parser("plan", __doc__)
    parser.add_argument("--depth", required=True)
    parser.add_argument("--rgb", required=True)
    parser.add_argument("--camera", required=True)
    parser.add_argument("--goal", required=True)
    parser.add_argument("--resolution", type=checks.omega, default=50, help="ω")
    parser.add_argument("--bound", type=checks.number(0.0, 2.0, above=True), default=PlannerConfig.bound,
                        help="pushes stay within ±bound m (default: the coffee bin's, as the export's)")
    parser.add_argument("--plate-half-width", type=checks.number(0.005, 0.5), default=None,
                        help=f"m: the sweep heuristic's plate (default {SceneConfig.plate_half_width}; a learned "
                             "model has its own)")
    parser.add_argument("--samples", type=checks.samples, default=50)
    parser.add_argument("--adam-steps", type=checks.adam_steps, default=100)
    parser.add_argument("--dynamics", default="auto", choices=["auto", "learned", "sweep"])
    parser.add_argument("--ckpt", default=None, help=f"dynamics checkpoint (default {SHIPPED_DYNAMICS})")
    parser.add_argument("--seed", type=checks.seed, default=0)
    parser.add_argument("--out", default="out/push.png", help="the frame with the goal, particles and push drawn")
    parser.add_argument("--real-depth", action=argparse.BooleanOptionalAction, default=True,
                        help="perception for a real camera's depth (a 3 x 3 median, the table plane fitted from the "
                             "frame: perception.foreground); --no-real-depth for a simulator's exact depth")
    parser.add_argument("--sensor", default="none", choices=sorted(SENSORS),
                        help="pass the frame through a depth camera's errors first (sim.sensor; to try a saved "
                             "simulator frame as a camera would give it)")
    parser.add_argument("--calibrate", action="store_true",
                        help="refine the camera's pose from the bin in the frame before planning (perception.calibrate:"
                             " the table plane and the walls of a bin of --bin-half-width and --wall-height)")
    parser.add_argument("--bin-half-width", type=checks.number(0.02, 2.0), default=None,
                        help=f"m (default {SceneConfig().bin_half_width}; read by --calibrate and --wall-pushes)")
    parser.add_argument("--wall-pushes", action=argparse.BooleanOptionalAction, default=True,
                        help="pushes may start outside a wall of a bin of --bin-half-width, as the closed loop's do "
                             "(PileEnv.reach), to sweep pieces off the walls")
    parser.add_argument("--wall-height", type=checks.number(0.005, 1.0), default=None,
                        help=f"m (default {SceneConfig().wall_height}; read by --calibrate)")
    return parser


@checks.guarded("plan")
def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.wall_height is not None and not args.calibrate:
        parser.error("--wall-height is read by --calibrate only (the bin's walls it fits the camera's pose to)")
    if args.bin_half_width is not None and not (args.calibrate or args.wall_pushes):
        parser.error("--bin-half-width is read by --calibrate and --wall-pushes only; with --no-wall-pushes and no "
                     "--calibrate nothing reads it")
    args.bin_half_width = args.bin_half_width or SceneConfig().bin_half_width
    args.wall_height = args.wall_height or SceneConfig().wall_height

    obs, camera = frames.load_frame(args.depth, args.rgb, args.camera)
    goal_mask = frames.load_goal(args.goal, camera)
    try:
        check_within(goal_mask, camera, WORKSPACE_HALF_WIDTH)
        goal = make_goal(goal_mask, camera)
    except ValueError as e:
        parser.error(f"--goal {args.goal}: {e}")
    checks.out_file(args.out, (".png", ".jpg"), inputs={"--depth": args.depth, "--rgb": args.rgb,
                                                        "--camera": args.camera, "--goal": args.goal})
    if SENSORS[args.sensor] is not None:
        sensor = SENSORS[args.sensor]
        obs = sensor.observe(obs, jax.random.PRNGKey(args.seed + 1))
        camera = sensor.believed_camera(camera, args.seed)
    if args.calibrate:
        try:
            camera = calibrate(obs, camera, bin_half_width=args.bin_half_width, wall_height=args.wall_height)
        except ValueError as e:
            parser.error(f"--calibrate: {e}")
    if visible_points(obs, camera, DecisionSpec.max_points, args.real_depth) == 0:  # before the model and compiling
        parser.error(f"--depth {args.depth}: the frame shows no pile (no point above the table, inside the "
                     "workspace): nothing to push")
    plate = SceneConfig.plate_half_width if args.plate_half_width is None else args.plate_half_width
    dynamics, n_max, name = load_model(parser, args.dynamics, args.ckpt, plate)
    if args.plate_half_width is not None and name != SWEEP_NAME:
        parser.error("--plate-half-width is the sweep heuristic's (--dynamics sweep); a learned model has its own")
    if args.resolution > n_max:
        parser.error(f"--resolution {args.resolution} exceeds the model's n_max = {n_max}")
    reach = wall_reach(args.bin_half_width, SceneConfig().plate_thickness) if args.wall_pushes else None
    try:
        config = PlannerConfig(samples=args.samples, adam_steps=args.adam_steps, bound=args.bound, seed=args.seed,
                               reach=reach)
    except ValueError as e:
        parser.error(f"--bound {args.bound} with pushes from outside the walls (--no-wall-pushes to plan without): {e}")
    spec = DecisionSpec(bucket_for(args.resolution), config, real_depth=args.real_depth)
    print(f"planning at ω = {args.resolution}, {args.samples} samples x {args.adam_steps} Adam steps (compiling the "
          "planner first: tens of seconds on a CPU)", file=sys.stderr, flush=True)  # stdout stays the JSON alone
    # the decision the closed loop and the exported file make (decision.perceive_and_decide): the same push for the
    # same frame, goal and key
    try:
        particles, _, result = decide_batch(batch(obs), batch(goal), batch(jax.random.PRNGKey(args.seed)),
                                            np.zeros((1, config.horizon, 4), np.float32), False, [args.resolution],
                                            [args.adam_steps], spec=spec, dynamics=dynamics, camera=camera)
    except ValueError as e:
        parser.error(f"--depth {args.depth}: {e}")
    particles, result = episode(particles), episode(result)
    action = np.asarray(result.best[0], np.float64)
    image = overlay(np.asarray(obs.rgb), goal_mask, np.asarray(particles.positions)[np.asarray(particles.mask)],
                    camera, push=action)
    files.write_image(args.out, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    out = dict(push=action.tolist(), predicted_objective=float(result.best_cost), dynamics=name,
               omega=args.resolution, image=args.out)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
