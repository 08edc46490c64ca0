"""Export the MPC planner of a trained dynamics model as one file, for a robot computer that has JAX but not this code:

    python -m experiments.export --ckpt checkpoints/dynamics --out planner.jaxexport

writes FILE (a ``jax.export`` serialised StableHLO program: one planning call, the model weights, the camera and the
planner settings inside) and FILE.json (its inputs and outputs with shapes, dtypes and units, the planner settings,
camera and checkpoint step). On the robot (needs jax, jaxlib no older than the exporting ones, and flatbuffers):

    exported = jax.export.deserialize(open("planner.jaxexport", "rb").read())
    out = exported.call(positions, mask, radius, goal_mask, goal_distance, goal_samples, goal_sample_mask, key,
                        init, warm)
    push = out["best"][0]   # (x_start, y_start, x_end, y_end), metres

The particles (positions, mask, radius) come from perception (dynres_jax.perception.sample_particles), the goal
arrays from dynres_jax.control.goals.make_goal (computed once per goal, on any machine), key is
jax.random.PRNGKey(seed). --platforms: default this machine's backend; --platforms cuda for a GPU robot works on any
machine. On the CPU a one-platform file plans bit for bit what the live planner plans; --platforms cpu cuda gives one
file for both, whose plans differ from the live ones by float rounding, amplified by the optimisation (on a GPU
neither the live planner nor the file repeats bit for bit from run to run; dynres_jax/export.py).
"""

from __future__ import annotations

import argparse
import json
import os

import jax

from dynres_jax import export
from dynres_jax.commands import checks
from dynres_jax.config import CameraConfig, PushConfig, SceneConfig
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.io import frames
from dynres_jax.io.ckpt import CheckpointError
from dynres_jax.models.registry import SHIPPED_DYNAMICS
from dynres_jax.sim.camera import Camera
from dynres_jax.sim.pushes import wall_reach

PLATFORMS = ("cpu", "cuda", "rocm", "tpu")


@checks.guarded("export")
def main(argv=None):
    parser = checks.parser("export", __doc__)
    defaults = PlannerConfig()
    parser.add_argument("--ckpt", default=SHIPPED_DYNAMICS, help="dynamics checkpoint (default: the shipped one)")
    parser.add_argument("--out", required=True, help="the file to write; its description goes to OUT.json")
    parser.add_argument("--samples", type=checks.count(1), default=50, help="action sequences optimised at once (M)")
    parser.add_argument("--adam-steps", type=checks.count(1), default=100, help="Adam steps per plan (N)")
    parser.add_argument("--horizon", type=checks.count(1, 10), default=defaults.horizon, help="pushes per sequence (T)")
    parser.add_argument("--bound", type=checks.positive, default=defaults.bound,
                        help="pushes stay within ±bound m (default: the coffee bin's PileEnv.action_bound)")
    parser.add_argument("--min-length", type=checks.positive, default=PushConfig.min_length, help="shortest push, m")
    parser.add_argument("--max-length", type=checks.positive, default=PushConfig.max_length, help="longest push, m")
    parser.add_argument("--lr", type=checks.positive, default=defaults.lr, help="Adam learning rate, m")
    parser.add_argument("--wall-pushes", action=argparse.BooleanOptionalAction, default=True,
                        help="pushes may start outside a wall of the default bin, as the closed loop's do "
                             "(PileEnv.reach), to sweep pieces off the walls")
    parser.add_argument("--camera", default=None,
                        help="camera JSON (Camera.to_json: K, rotation, centre, width, height) the goals' pixels "
                             "belong to (default: the simulator's top-down 128 x 128 camera)")
    parser.add_argument("--goal-samples", type=checks.count(1, 100_000), default=export.DEFAULT_GOAL_SAMPLES,
                        help="Q, the goal's FPS samples (goals.make_goal's n_samples)")
    parser.add_argument("--platforms", nargs="+", choices=PLATFORMS, default=None,
                        help=f"platforms to lower for (default: this machine's, now "
                             f"{jax.export.default_export_platform()}); several give one file for all")
    args = parser.parse_args(argv)

    try:
        scene = SceneConfig()
        config = PlannerConfig(samples=args.samples, adam_steps=args.adam_steps, horizon=args.horizon, bound=args.bound,
                               min_length=args.min_length, max_length=args.max_length, lr=args.lr,
                               reach=wall_reach(scene.bin_half_width, scene.plate_thickness) if args.wall_pushes
                               else None)
    except ValueError as e:
        parser.error(str(e))
    camera = Camera.top_down(CameraConfig()) if args.camera is None else frames.load_camera(args.camera)
    checks.out_file(args.out, (".jaxexport",))
    try:
        exported, info = export.export_checkpoint(args.ckpt, config, camera, goal_samples=args.goal_samples,
                                                  platforms=args.platforms)
    except CheckpointError as e:
        parser.error(f"--ckpt: {e}")
    size = export.save(exported, args.out, info)
    summary = dict(out=os.path.abspath(args.out), sidecar=os.path.abspath(args.out) + ".json", bytes=size,
                   platforms=list(exported.platforms), checkpoint_step=info["checkpoint"]["step"],
                   signature=export.signature(exported))
    print(f"wrote {args.out} ({size / 1e6:.2f} MB, {', '.join(exported.platforms)}; checkpoint step "
          f"{summary['checkpoint_step']}) and {args.out}.json")
    print(f"signature: {summary['signature']}")
    print(json.dumps(dict(planner=info["planner"], n_max=info["n_max"])))
    return summary


if __name__ == "__main__":
    main()
