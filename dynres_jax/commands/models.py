"""The models a command plans with, as flags: ``--ckpt`` / ``--dynamics`` (``load_model``) and ``--judge``, a second
model that chooses among the planner's refined candidates (``add_judge_arg``, ``load_judge``, ``judged``). Every
checkpoint is read, or refused in one line by ``parser.error``, before any work."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable

from dynres_jax.commands import methods
from dynres_jax.control.choosers import Chooser
from dynres_jax.control.judge import JudgeScored
from dynres_jax.io.ckpt import CheckpointError
from dynres_jax.models.registry import SHIPPED_DYNAMICS, LoadedDynamics, load_dynamics


def load_model(parser: argparse.ArgumentParser, choice: str, ckpt_dir: str, plate_half_width: float,
               shipped: str = SHIPPED_DYNAMICS, flag: str = "--ckpt") -> LoadedDynamics:
    """``registry.load_dynamics`` of ``ckpt_dir`` (None: ``shipped``; "" is no checkpoint, not the default), with a
    missing or damaged checkpoint named by ``parser.error`` (as ``flag``) before any work."""
    if choice == "sweep" and ckpt_dir is not None and os.path.abspath(ckpt_dir) != shipped:
        parser.error(f"{flag} {ckpt_dir} is given but --dynamics sweep plans without a checkpoint; drop one of them")
    try:
        return load_dynamics(choice, shipped if ckpt_dir is None else ckpt_dir, plate_half_width)
    except (CheckpointError, FileNotFoundError) as e:
        parser.error(f"{flag}: {e}")


def add_judge_arg(parser: argparse.ArgumentParser) -> None:
    """--judge: a second dynamics checkpoint that chooses among the planner's refined candidates."""
    parser.add_argument("--judge", default=None, metavar="CKPT",
                        help="a second dynamics checkpoint that chooses among the planner's refined candidates "
                             "(control/judge.py); default: none, the planner's own best plan is pushed")


def load_judge(parser: argparse.ArgumentParser, args, plate_half_width: float, inputs: dict) -> LoadedDynamics | None:
    """--judge's model (None without one), refused by parser.error where it cannot be read or cannot hold the finest
    ω --resolution plans at, before any work; its path goes to ``inputs`` (``checks.claim``'s)."""
    if args.judge is None:
        return None
    judge = load_model(parser, "learned", args.judge, plate_half_width, flag="--judge")
    if methods.finest(str(args.resolution), args) > judge.n_max:
        parser.error(f"--resolution {args.resolution} exceeds the judge's n_max = {judge.n_max}")
    inputs["--judge"] = args.judge
    return judge


def judged(choose: Callable[..., Chooser], judge: LoadedDynamics | None) -> Callable[..., Chooser]:
    """A chooser factory (goals [B] -> Chooser) with the judge's choice on top (``JudgeScored``), or as it is."""
    return choose if judge is None else lambda goals: JudgeScored(choose(goals), judge.dynamics)
