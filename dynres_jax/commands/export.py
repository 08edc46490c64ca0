"""Export a trained dynamics model's whole MPC decision as one file, for a robot computer that has JAX but not this
code:

    python -m experiments.export --out out/decision.jaxexport    # the shipped model; --ckpt runs/NAME/ckpt for another

writes FILE (a ``jax.export`` serialised StableHLO program: depth frame + goal mask -> push, with the goal's distance
field, perception, the model weights, the camera and the planner settings inside) and FILE.json (its inputs and
outputs with shapes, dtypes and units, the error bits, the settings, camera and checkpoint step). On the robot,
``pip install jax flatbuffers`` (jaxlib no older than the exporting one) and:

    exported = jax.export.deserialize(open("out/decision.jaxexport", "rb").read())
    out = exported.call(depth, goal_mask, key, omega, adam_steps, init, warm)
    push = out["push"]   # (x_start, y_start, x_end, y_end), metres; execute it when out["error"] == 0

depth: the camera's [H, W] z-depth in metres (0: no reading), goal_mask: [H, W] bool (a goal PNG, experiments.goal),
key: jax.random.PRNGKey(seed), omega: the resolution (up to the bucket of --resolution), adam_steps: up to
--adam-steps. The camera (--camera, as calibrated on the robot) is fixed in the file. --platforms: default this
machine's backend; --platforms cuda for a GPU robot works on any machine. On the CPU a one-platform file decides bit
for bit what the library's closed loop decides (dynres_jax/export.py).
"""

from __future__ import annotations

import argparse
import json
import os

import jax

from dynres_jax import export
from dynres_jax.commands import checks
from dynres_jax.config import CameraConfig, PushConfig, SceneConfig
from dynres_jax.control.budget import bucket_for
from dynres_jax.control.decision import DecisionSpec
from dynres_jax.control.goals import MAX_GOAL_SAMPLES
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.io import files, frames
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
    parser.add_argument("--judge", default=None, metavar="CKPT",
                        help="a second dynamics checkpoint, in the same file, that chooses the push among the "
                             "planner's refined candidates (control/judge.py); default: none, the planner's best")
    parser.add_argument("--out", required=True, help="the file to write; its description goes to OUT.json")
    parser.add_argument("--resolution", type=checks.omega, default=50,
                        help="the largest ω the robot will ask for: the file holds its bucket's particle slots "
                             "(control.budget.bucket_for), and the call's omega may be any ω up to them")
    parser.add_argument("--real-depth", action=argparse.BooleanOptionalAction, default=True,
                        help="perception for a real camera's depth (a 3 x 3 median, the table plane fitted from the "
                             "frame); --no-real-depth for a simulator's exact depth")
    parser.add_argument("--samples", type=checks.samples, default=50, help="action sequences optimised at once (M)")
    parser.add_argument("--adam-steps", type=checks.adam_steps, default=100, help="Adam steps per plan (N)")
    parser.add_argument("--horizon", type=checks.count(1, 10), default=defaults.horizon, help="pushes per sequence (T)")
    parser.add_argument("--bound", type=checks.positive, default=defaults.bound,
                        help="pushes stay within ±bound m (default: the coffee bin's PileEnv.action_bound)")
    parser.add_argument("--min-length", type=checks.positive, default=PushConfig.min_length, help="shortest push, m")
    parser.add_argument("--max-length", type=checks.positive, default=PushConfig.max_length, help="longest push, m")
    parser.add_argument("--lr", type=checks.lr, default=defaults.lr, help="Adam learning rate, m")
    parser.add_argument("--wall-pushes", action=argparse.BooleanOptionalAction, default=True,
                        help="pushes may start outside a wall of the default bin, as the closed loop's do "
                             "(PileEnv.reach), to sweep pieces off the walls")
    parser.add_argument("--camera", default=None,
                        help="camera JSON (Camera.to_json: K, rotation, centre, width, height) of the robot's frames "
                             "and goals, its pose calibrated (default: the simulator's top-down 128 x 128 camera)")
    parser.add_argument("--goal-samples", type=checks.count(1, MAX_GOAL_SAMPLES), default=export.DEFAULT_GOAL_SAMPLES,
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
    checks.out_file(args.out, (".jaxexport",), beside=".json", inputs={"--camera": args.camera})
    sidecar = args.out + ".json"  # read only a small regular file: a FIFO would block the read
    earlier = files.read_json(sidecar) if os.path.isfile(sidecar) and os.path.getsize(sidecar) <= 1 << 20 else None
    if os.path.lexists(sidecar) and not (isinstance(earlier, dict) and "sha256" in earlier):
        parser.error(f"--out {args.out}: {sidecar} exists and is not an export's description (the file export writes "
                     "beside it); move it or give another --out")
    spec = DecisionSpec(bucket_for(args.resolution), config, real_depth=args.real_depth)
    try:
        exported, info = export.export_checkpoint(args.ckpt, spec, camera, goal_samples=args.goal_samples,
                                                  platforms=args.platforms, judge_dir=args.judge)
    except CheckpointError as e:  # the message names the folder
        parser.error(f"{'--judge' if args.judge is not None and args.judge in str(e) else '--ckpt'}: {e}")
    except ValueError as e:
        parser.error(f"--resolution {args.resolution}: {e}")
    size = export.save(exported, args.out, info)
    summary = dict(out=os.path.abspath(args.out), sidecar=os.path.abspath(args.out) + ".json", bytes=size,
                   platforms=list(exported.platforms), checkpoint_step=info["checkpoint"]["step"],
                   judge_step=info["judge"] and info["judge"]["step"], signature=export.signature(exported))
    judged = "" if args.judge is None else f", judge step {summary['judge_step']}"
    print(f"wrote {args.out} ({size / 1e6:.2f} MB, {', '.join(exported.platforms)}; checkpoint step "
          f"{summary['checkpoint_step']}{judged}) and {args.out}.json")
    print(f"signature: {summary['signature']}")
    print(json.dumps(dict(planner=info["planner"], capacity=info["capacity"], perception=info["perception"])))
    return summary


if __name__ == "__main__":
    main()
