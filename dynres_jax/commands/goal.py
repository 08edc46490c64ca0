"""Write a goal as a black-and-white PNG of a camera's size (white = goal), what ``plan`` (``--goal``) and a robot
read back with ``io.frames.load_goal``:

    python -m experiments.goal --disc 0 0 0.08 --out goal.png                        # Gather's disc: x y radius (m)
    python -m experiments.goal --letter T --height 0.15 --camera cam.json --out t.png  # Redistribute's letter
    python -m experiments.goal --mask drawing.png --camera cam.json --out goal.png      # any mask, resized

Shapes are drawn on the table plane (z = 0) through the camera (``--camera``, a JSON file as ``plan`` takes; default:
the simulator's top-down camera), so a disc of 8 cm is 8 cm on the table, and must lie inside the bin
(``--bin-half-width``) and the image. ``--mask`` takes an image of any size (white, > 127, is the goal) in the
camera's aspect ratio and resizes it to the camera's pixels.
"""

from __future__ import annotations

import json

import cv2
import numpy as np

from dynres_jax.commands import checks
from dynres_jax.config import CameraConfig
from dynres_jax.control.goals import check_within, disc_goal, text_goal
from dynres_jax.errors import InputError
from dynres_jax.io.frames import load_camera, read_mask, save_goal
from dynres_jax.perception import WORKSPACE_HALF_WIDTH
from dynres_jax.sim.camera import Camera


def mask_goal(path: str, camera: Camera) -> np.ndarray:
    """A mask image of any size (white, > 127, is the goal) resized to the camera's [H, W] bool. InputError for an
    unreadable file or one that is not a regular file (a FIFO, a device, a folder), another aspect ratio or no goal
    pixel after resizing."""
    image = read_mask(path, "--mask")  # a regular file, 8-bit, opaque, no EXIF orientation tag
    (h, w), (ch, cw) = image.shape, (camera.height, camera.width)
    if abs(h * cw - w * ch) > max(h, w):  # a pixel of slack
        raise InputError(f"--mask {path!r} is {w} x {h} pixels, not the camera's aspect ratio ({cw} x {ch})")
    mask = cv2.resize((image > 127).astype(np.uint8), (cw, ch), interpolation=cv2.INTER_NEAREST) > 0
    if not mask.any():
        raise InputError(f"--mask {path!r} has no goal pixel (white, > 127) at the camera's {cw} x {ch} pixels")
    return mask


@checks.guarded("goal")
def main(argv=None):
    parser = checks.parser("goal", __doc__)
    shape = parser.add_mutually_exclusive_group(required=True)
    shape.add_argument("--disc", nargs=3, type=checks.number(-1.0, 1.0), metavar=("X", "Y", "RADIUS"),
                       help="a disc centred at (X, Y) m of RADIUS m")
    shape.add_argument("--letter", type=checks.text, help="characters OpenCV draws (Redistribute's J, T, U)")
    shape.add_argument("--mask", help="an image of any size in the camera's aspect ratio (white = goal)")
    parser.add_argument("--height", type=checks.number(0.005, 1.0), default=None,
                        help="--letter: ink height, m (default 0.15)")
    parser.add_argument("--centre", nargs=2, type=checks.number(-1.0, 1.0), default=None, metavar=("X", "Y"),
                        help="--letter: the centre of its ink, m (default 0 0)")
    parser.add_argument("--camera", default=None, help="camera JSON (default: the simulator's top-down camera)")
    parser.add_argument("--bin-half-width", type=checks.number(0.01, 1.0), default=WORKSPACE_HALF_WIDTH,
                        help="shapes must lie within ±this of the bin's centre, m (default: the workspace plan, "
                             "robot and the exported decision accept, the bin's inner faces less 1 mm)")
    parser.add_argument("--out", required=True, help="the goal PNG to write")
    args = parser.parse_args(argv)
    for flag, value in (("--height", args.height), ("--centre", args.centre)):
        if value is not None and not args.letter:
            where = "--disc X Y RADIUS places a disc" if args.disc else "a --mask is drawn where it is"
            parser.error(f"{flag} is --letter's; {where}")
    args.height, args.centre = args.height or 0.15, args.centre or (0.0, 0.0)
    checks.out_file(args.out, (".png",), inputs={"--mask": args.mask, "--camera": args.camera})
    camera = load_camera(args.camera) if args.camera else Camera.top_down(CameraConfig())
    try:
        if args.disc:
            mask = disc_goal(camera, args.disc[:2], args.disc[2], bin_half_width=args.bin_half_width)
        elif args.letter:
            mask = text_goal(camera, args.letter, args.centre, args.height, bin_half_width=args.bin_half_width)
        else:
            mask = mask_goal(args.mask, camera)
            check_within(mask, camera, args.bin_half_width)  # as discs and letters are
    except ValueError as e:
        parser.error(f"--mask: {e}" if args.mask else str(e))
    save_goal(args.out, mask)
    out = dict(goal=args.out, width=camera.width, height=camera.height, pixels=int(mask.sum()))
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
