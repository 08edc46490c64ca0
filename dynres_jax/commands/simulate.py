"""Simulator demo: a random pile pushed a few times; writes a GIF of the pushes, the final RGB and depth images, and
the final frame as a depth camera saves it (``frame/depth.png``, 16-bit millimetres; ``frame/rgb.png``;
``frame/camera.json``), which ``goal --camera`` and ``plan`` read as a real camera's:

    python -m experiments.simulate --kind coffee --pieces 100 --pushes 5 --out out/sim
"""

from __future__ import annotations

import os

import cv2
import imageio.v3 as iio
import jax
import numpy as np

from dynres_jax import progress
from dynres_jax.commands import checks
from dynres_jax.config import KINDS, CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.io import files
from dynres_jax.io.frames import save_frame
from dynres_jax.sim.camera import MAX_IMAGE, MIN_IMAGE, Observation
from dynres_jax.sim.env import make_env
from dynres_jax.sim.scene import check_room


def depth_image(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """z-depth [H, W] metres -> colour-mapped uint8 [H, W, 3] RGB (near is bright)."""
    scaled = np.clip((far - depth) / (far - near), 0, 1)
    return cv2.cvtColor(cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)


def frame(obs: Observation, scale: int = 2) -> np.ndarray:
    rgb = np.asarray(obs.rgb)
    return cv2.resize(rgb, (rgb.shape[1] * scale, rgb.shape[0] * scale), interpolation=cv2.INTER_NEAREST)


@checks.guarded("simulate")
def main(argv=None):
    parser = checks.parser("simulate", __doc__)
    parser.add_argument("--kind", nargs="+", default=["coffee"], choices=sorted(KINDS),
                        help="piece kind(s); two kinds make a Sort scene")
    parser.add_argument("--pieces", nargs="+", type=checks.count(1), default=[100], help="pieces of each kind")
    parser.add_argument("--pushes", type=checks.count(1, 10_000), default=5)
    parser.add_argument("--layout", default="blob", choices=["blob", "two_blobs", "spread"])
    parser.add_argument("--joints", default="planar", choices=["planar", "free"])
    checks.add_engine(parser)  # mujoco (C) draws the plate moving; the others show one frame per push
    parser.add_argument("--image-size", type=checks.count(MIN_IMAGE, MAX_IMAGE), default=256,
                        help="image width and height, pixels")
    parser.add_argument("--seed", type=checks.seed, default=0)
    parser.add_argument("--out", default="out/simulate")
    checks.add_fresh(parser)
    args = parser.parse_args(argv)
    pieces = args.pieces * len(args.kind) if len(args.pieces) == 1 else args.pieces
    if len(pieces) != len(args.kind) or len(args.kind) > 2:
        parser.error(f"--kind takes one or two kinds and --pieces one count, or one per kind; got {args.kind}, "
                     f"{args.pieces}")
    try:
        cfg = SimConfig(scene=SceneConfig(kinds=tuple(args.kind), pieces=tuple(pieces), joints=args.joints),
                        pile=PileConfig(layout=args.layout),
                        camera=CameraConfig(width=args.image_size, height=args.image_size))
        check_room(cfg.scene)
    except ValueError as e:
        parser.error(str(e))
    engine = checks.engine(parser, args.backend)
    checks.claim(args.out, "simulate", checks.settings(args), args.fresh)
    progress.start(checks.prog("simulate"), f"{args.pushes} push(es) of {' + '.join(map(str, pieces))} "
                   f"{' + '.join(args.kind)} pieces on {engine}, into {args.out}; building the scene")
    env = make_env(cfg, engine)
    key = jax.random.PRNGKey(args.seed)
    state = env.reset(key)
    frames, actions = [frame(state.obs)], []
    pushes = progress.bar(range(args.pushes), desc="pushes", unit="push")
    for i in pushes:
        action = np.asarray(env.sample_push(jax.random.fold_in(key, i + 1), state.pos))
        actions.append(action.tolist())
        if env.draws_pushes:  # the C engine draws the plate moving
            state, shots = env.push_frames(state, action)
            frames += [frame(o) for o in shots]
        else:
            state = env.push(state, action)
        frames.append(frame(state.obs))
        if bool(state.broken):
            pushes.write(f"push {i}: the world broke (NaN, or a piece left the bin); stopping")
            break

    files.atomic_write(os.path.join(args.out, "pushes.gif"),
                       lambda f: iio.imwrite(f, np.stack(frames), extension=".gif", duration=80, loop=0))
    files.write_image(os.path.join(args.out, "final_rgb.png"),
                      cv2.cvtColor(np.asarray(state.obs.rgb), cv2.COLOR_RGB2BGR))
    far = cfg.camera.distance
    depth = depth_image(np.asarray(state.obs.depth), far - 0.03, far)
    files.write_image(os.path.join(args.out, "final_depth.png"), cv2.cvtColor(depth, cv2.COLOR_RGB2BGR))
    files.write_json(os.path.join(args.out, "actions.json"),
                     dict(config=repr(cfg), actions=actions, broken=bool(state.broken)))
    save_frame(os.path.join(args.out, "frame"), state.obs, env.camera)
    shown = len(iio.imread(os.path.join(args.out, "pushes.gif"), index=None))  # the GIF merges repeated frames
    print(f"wrote {args.out}/pushes.gif ({shown} frames), final_rgb.png, final_depth.png, actions.json and the last "
          f"frame as a camera saves it: frame/depth.png, frame/rgb.png, frame/camera.json")


if __name__ == "__main__":
    main()
