"""Simulator demo: a random pile pushed a few times; writes a GIF of the pushes and the final RGB and depth images.

    python -m experiments.simulate --kind coffee --pieces 100 --pushes 5 --out out/sim
"""

from __future__ import annotations

import argparse
import json
import os

import cv2
import imageio.v3 as iio
import jax
import numpy as np
from tqdm import tqdm

from dynres_jax.config import KINDS, CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.io import files
from dynres_jax.sim.camera import Observation
from dynres_jax.sim.env import PileEnv


def depth_image(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """z-depth [H, W] metres -> colour-mapped uint8 [H, W, 3] RGB (near is bright)."""
    scaled = np.clip((far - depth) / (far - near), 0, 1)
    return cv2.cvtColor(cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)


def frame(obs: Observation, scale: int = 2) -> np.ndarray:
    rgb = np.asarray(obs.rgb)
    return cv2.resize(rgb, (rgb.shape[1] * scale, rgb.shape[0] * scale), interpolation=cv2.INTER_NEAREST)


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m experiments.simulate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kind", nargs="+", default=["coffee"], choices=sorted(KINDS),
                        help="piece kind(s); two kinds make a Sort scene")
    parser.add_argument("--pieces", nargs="+", type=int, default=[100], help="pieces of each kind")
    parser.add_argument("--pushes", type=int, default=5)
    parser.add_argument("--layout", default="blob", choices=["blob", "two_blobs", "spread"])
    parser.add_argument("--joints", default="planar", choices=["planar", "free"])
    parser.add_argument("--backend", default="mujoco", choices=["mujoco", "mjx"],
                        help="mujoco (C, one world) draws the plate moving; mjx shows one frame per push")
    parser.add_argument("--resolution", type=int, default=256, help="image width and height, pixels")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="out/simulate")
    args = parser.parse_args(argv)
    pieces = args.pieces * len(args.kind) if len(args.pieces) == 1 else args.pieces
    if len(pieces) != len(args.kind):
        parser.error(f"--pieces needs one count, or one per kind ({len(args.kind)})")

    cfg = SimConfig(scene=SceneConfig(kinds=tuple(args.kind), pieces=tuple(pieces), joints=args.joints),
                    pile=PileConfig(layout=args.layout),
                    camera=CameraConfig(width=args.resolution, height=args.resolution))
    env = PileEnv(cfg, backend=args.backend)
    key = jax.random.PRNGKey(args.seed)
    state = env.reset(key)
    frames, actions = [frame(state.obs)], []
    for i in tqdm(range(args.pushes), desc="pushes"):
        action = np.asarray(env.sample_push(jax.random.fold_in(key, i + 1), state.pos))
        actions.append(action.tolist())
        if args.backend == "mujoco":
            state, shots = env.push_frames(state, action)
            frames += [frame(o) for o in shots]
        else:
            state = env.push(state, action)
        frames.append(frame(state.obs))
        if bool(state.broken):
            tqdm.write(f"push {i}: the world broke (NaN, or a piece left the bin); stopping")
            break

    os.makedirs(args.out, exist_ok=True)
    iio.imwrite(os.path.join(args.out, "pushes.gif"), np.stack(frames), duration=80, loop=0)
    files.write_image(os.path.join(args.out, "final_rgb.png"),
                      cv2.cvtColor(np.asarray(state.obs.rgb), cv2.COLOR_RGB2BGR))
    far = cfg.camera.distance
    depth = depth_image(np.asarray(state.obs.depth), far - 0.03, far)
    files.write_image(os.path.join(args.out, "final_depth.png"), cv2.cvtColor(depth, cv2.COLOR_RGB2BGR))
    with open(os.path.join(args.out, "actions.json"), "w") as f:
        json.dump(dict(config=repr(cfg), actions=actions, broken=bool(state.broken)), f, indent=1)
    print(f"wrote {len(frames)} frames to {args.out}/pushes.gif, final_rgb.png, final_depth.png, actions.json")


if __name__ == "__main__":
    main()
