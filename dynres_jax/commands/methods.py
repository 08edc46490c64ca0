"""The ways of choosing ω (and the push) that the command line names, in one table: ``evaluate --methods`` takes every
one, a task command's and ``robot``'s ``--resolution`` those whose orders keep by the model (no simulator, no second
checkpoint of their own). A new chooser is one class (``control.choosers``) and one row here.

A name is a fixed ω ("50"), a row's key ("adaptive", "probe", "oracle", "cnn", "judge") or a rung of the ladder
("bestK", "sim", "rerank": docs/ladder).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dynres_jax.config import OMEGA_MAX, OMEGA_MIN
from dynres_jax.control.choosers import (
    ORACLE_OMEGAS,
    PROBE_OMEGAS,
    AdaptiveOmega,
    Chooser,
    FixedOmega,
    OracleOmega,
    ProbeOmega,
    best_of,
    climb,
    on_ladder,
)
from dynres_jax.control.judge import JudgeScored
from dynres_jax.resolution.regressor import load_regressor


@dataclass(frozen=True)
class Method:
    """A row: chooser(name, goals [B], args, camera, judge) -> the Chooser (args: the command's flags; judge: radius
    -> --judge's model, or None); omega(name, args): the one ω it plans at, None when it chooses among ω; finest(name,
    args): the finest ω it may plan at; label(name, omegas): its name in plots (omegas: the ω it planned at);
    simulator: its orders need the simulator's worlds (evaluate only); sort: Sort can run it (one ω a step); needs:
    the flag of a model it reads beside the dynamics ("--regressor", "--judge", "--cnn-ckpt"), or None."""

    chooser: Callable[..., Chooser]
    omega: Callable[[str, argparse.Namespace], int | None]
    label: Callable[[str, np.ndarray], str]
    finest: Callable[[str, argparse.Namespace], int] | None = None
    simulator: bool = False
    sort: bool = False
    needs: str | None = None


def _mean(omegas) -> int:
    return round(float(np.mean(omegas)))


FIXED = Method(chooser=lambda name, goals, args, camera, judge: FixedOmega(goals, int(name)),
               omega=lambda name, args: int(name), label=lambda name, omegas: f"ω = {name}", sort=True)
LADDER = Method(chooser=lambda name, goals, args, camera, judge: climb(FixedOmega(goals, args.best_omega), name),
                omega=lambda name, args: args.best_omega, simulator=True, sort=True,
                label=lambda name, omegas: (f"best of {best_of(name)}, ω = {_mean(omegas)}" if best_of(name) else
                                            {"sim": "simulator chooses among samples",
                                             "rerank": "simulator ranks the model's plans"}[name]))
METHODS: dict[str, Method] = {
    "adaptive": Method(lambda name, goals, args, camera, judge: AdaptiveOmega(goals, load_regressor(
        args.regressor, camera)), omega=lambda name, args: None, label=lambda name, omegas: "adaptive",
        needs="--regressor"),
    "probe": Method(lambda name, goals, args, camera, judge: ProbeOmega(goals), omega=lambda name, args: None,
                    finest=lambda name, args: max(PROBE_OMEGAS), label=lambda name, omegas: "probe"),
    "oracle": Method(lambda name, goals, args, camera, judge: OracleOmega(goals, ORACLE_OMEGAS),
                     omega=lambda name, args: None, finest=lambda name, args: max(ORACLE_OMEGAS),
                     label=lambda name, omegas: "oracle", simulator=True),
    "cnn": Method(lambda name, goals, args, camera, judge: FixedOmega(goals, args.cnn_omega),
                  omega=lambda name, args: args.cnn_omega, label=lambda name, omegas: f"CNN, ω = {_mean(omegas)}",
                  needs="--cnn-ckpt"),
    "judge": Method(lambda name, goals, args, camera, judge: JudgeScored(FixedOmega(goals, args.best_omega), judge),
                    omega=lambda name, args: args.best_omega, needs="--judge",
                    label=lambda name, omegas: "judge ranks the model's plans"),
}
NAMES = f"{', '.join(repr(n) for n in METHODS)}, 'sim', 'rerank', 'bestK' (K >= 1) or an integer in [{OMEGA_MIN}, " \
        f"{OMEGA_MAX}]"


def method(name: str) -> Method | None:
    """The row of a method's name ("050" reads as ω = 50), or None for a name no row takes."""
    if name.isdigit():
        return FIXED if OMEGA_MIN <= int(name) <= OMEGA_MAX else None
    return LADDER if on_ladder(name) else METHODS.get(name)


def coarsest(name: str, args) -> int:
    """The ω at which method ``name`` must afford an Adam step under a budget: its one ω, else the coarsest."""
    omega = method(name).omega(name, args)
    return OMEGA_MIN if omega is None else omega


def finest(name: str, args) -> int:
    """The finest ω method ``name`` may plan at: the largest of the ω it chooses among, else ``coarsest`` (its one
    ω; adaptive: at least OMEGA_MIN)."""
    row = method(name)
    return coarsest(name, args) if row.finest is None else row.finest(name, args)


def reach(name: str, args) -> int:
    """The finest ω method ``name`` may ever plan at: ``finest``'s, but OMEGA_MAX for one that may choose any ω (the
    regressor's adaptive): what a timing table must price (``planner_args.check_budget``)."""
    row = method(name)
    return OMEGA_MAX if row.omega(name, args) is None and row.finest is None else finest(name, args)


def by_model(name: str) -> bool:
    """Whether ``name`` is a method a task command or the robot can run: its orders need no simulator and it reads no
    model of its own beyond the regressor (``--resolution``'s choices)."""
    row = method(name)
    return row is not None and not row.simulator and row.needs in (None, "--regressor")


def resolution_arg(text: str) -> str:
    """``--resolution``: an integer ω in [OMEGA_MIN, OMEGA_MAX] or a method the model keeps by ("adaptive",
    "probe"), as its canonical name ("050" -> "50")."""
    name = str(int(text)) if text.strip().isdigit() else text.strip()
    if not by_model(name):
        choices = [n for n in METHODS if by_model(n)]
        raise argparse.ArgumentTypeError(f"expected an integer in [{OMEGA_MIN}, {OMEGA_MAX}] or one of "
                                         f"{', '.join(choices)}, got {text!r}")
    return name
