"""The planner's flags shared by the commands that plan (``evaluate``, ``label_resolution``, ``tradeoff`` and the
task commands): the time budget and its timing table, and the options that make our planner the reference's
(``--reference-planner``, docs/reference_planner)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable

from dynres_jax import distributed
from dynres_jax.commands import checks
from dynres_jax.config import OMEGA_MAX
from dynres_jax.control import budget
from dynres_jax.control.decision import episode
from dynres_jax.control.mpc import MPCConfig, measure_timing
from dynres_jax.control.planner import REFERENCE_LR_SHARE, STARTS, PlannerConfig, planner_config, reference_lr
from dynres_jax.errors import InputError
from dynres_jax.io import files


def add_budget_args(parser: argparse.ArgumentParser) -> None:
    """--time-budget and --timing: every closed-loop command's, labelling's and evaluation's."""
    parser.add_argument("--time-budget", type=checks.time_budget, default=None, metavar="S",
                        help="seconds per decision on this device: each decision runs the Adam steps that fit, at most "
                             "--adam-steps, from a timing table measured once per resolution bucket (refined from the "
                             "decisions a single episode makes) and saved as timing.json (default: none, --adam-steps "
                             "every decision)")
    parser.add_argument("--timing", default=None, metavar="FILE",
                        help="spend the time budget by this saved timing table (timing.json of an earlier run), "
                             "unrefined, so a run's step counts are reproduced on any machine (default: measured here)")


def load_timing(parser: argparse.ArgumentParser, args) -> budget.TimingTable | None:
    """The --timing table (frozen), or None; parser.error naming a bad --timing, before any work. A run spending a
    table that prices every ω (its largest bucket OMEGA_MAX) plans at its buckets (args.buckets set to them: a table
    of older buckets reproduces its runs), and --buckets, where given, must be those; a table of a fixed-ω run (a few
    buckets) leaves the buckets as they are (``check_budget`` then says which it lacks)."""
    if args.timing is None:
        return None
    if args.time_budget is None:
        parser.error("--timing needs --time-budget (the table spends a time budget)")
    files.check_input(args.timing, "--timing")  # a FIFO would block the read; one line naming what it is
    try:
        table = budget.TimingTable.load(args.timing)
    except (OSError, ValueError, TypeError) as e:
        parser.error(f"--timing {args.timing}: {e}")
    given = getattr(args, "buckets", None)
    full = table.buckets is not None and table.buckets[-1] == OMEGA_MAX
    if full and given is not None and tuple(given) != table.buckets:
        parser.error(f"--buckets {' '.join(map(str, given))}: the timing table {args.timing} prices buckets "
                     f"{' '.join(map(str, table.buckets))}; give those, or no --buckets (the run plans at the table's)")
    preset = REFERENCE_PLANNER if getattr(args, "reference_planner", False) else PLANNER_OPTIONS
    args.buckets = table.buckets if full else given or preset["buckets"]
    return table


def check_budget(cfg: MPCConfig, table: budget.TimingTable | None, omegas, finest: int | None = None) -> None:
    """InputError naming --time-budget when it affords no Adam step at some ω of ``omegas`` by ``table`` (a chooser
    among ω passes the coarsest: a budget may leave the finest ω without steps, which is what it trades), and naming
    the table when it lacks a bucket the run may plan at (the buckets of ``omegas`` up to ``finest``'s)."""
    if cfg.time_budget is None or table is None:
        return
    if table.buckets is not None:
        low, high = min(omegas), max(omegas) if finest is None else max(max(omegas), finest)
        needed = [b for b in cfg.buckets if budget.bucket_for(low, cfg.buckets) <= b
                  <= budget.bucket_for(high, cfg.buckets)]
        missing = [b for b in needed if b not in table.buckets]
        if missing:
            raise InputError(f"the timing table ({table.device}) prices buckets {' '.join(map(str, table.buckets))}; "
                             f"this run plans at ω {low}-{high}, in buckets {' '.join(map(str, needed))}: measure a "
                             "table for it (run without --timing; an interrupted episode begun before the buckets "
                             "changed: --fresh)")
    afforded = {}
    for omega in sorted(set(omegas)):
        key = table.key(omega, cfg.buckets)
        afforded[omega] = cfg.adam_steps(omega, table)
        if afforded[omega] < 1:
            raise InputError(f"--time-budget {cfg.time_budget} s affords no Adam step at ω = {omega} on "
                             f"{table.device}: a decision's fixed part takes {table.fixed_s[key]:.3g} s and each "
                             f"step {table.step_s[key]:.3g} s; give a larger budget")
    refined = "a table read from a file stays as it is" if table.frozen else "the timing table refines this as " \
        "decisions are timed"
    print(f"--time-budget {cfg.time_budget} s on {table.device} affords "
          f"{', '.join(f'{n} Adam step(s) at ω = {w}' for w, n in afforded.items())} a decision (without a budget: "
          f"{cfg.planner.adam_steps}; {refined})", flush=True)


PLANNER_OPTIONS = dict(starts=PlannerConfig.starts, resamples=PlannerConfig.resamples, vote=PlannerConfig.vote,
                       warm_start=MPCConfig.warm_start, lr=PlannerConfig.lr, buckets=budget.BUCKETS,
                       pricing="measured")  # ours: the configs' defaults
REFERENCE_PLANNER = dict(starts="fixed", resamples=30, vote=True, warm_start=False, lr="reference",
                         buckets=(25, 50, 75, 100), pricing="reference")  # the authors' code's (issue 51)


def add_reference_planner_args(parser) -> None:
    """The options that make our planner the reference's, one flag each (evaluate, label_resolution, tradeoff)."""
    g = parser.add_argument_group("the reference's planner: --reference-planner sets every option below as the "
                                  "authors' code does; a flag given beside it wins")
    g.add_argument("--reference-planner", action="store_true",
                   help="--starts fixed --resamples 30 --vote --no-warm-start --lr reference --buckets 25 50 75 100 "
                        "--pricing reference")
    g.add_argument("--starts", choices=STARTS, default=None, help="the first pushes: pile (through the particles; "
                   "default), workspace (anywhere, drawn every step) or fixed (one set over the workspace)")
    g.add_argument("--resamples", type=checks.count(1, 64), default=None,
                   help="re-samplings of the particles each push is scored on (default 1)")
    g.add_argument("--vote", action=argparse.BooleanOptionalAction, default=None,
                   help="with --resamples: each re-sampling votes for its best push (default: their mean cost)")
    g.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=None,
                   help="start each plan from the last one, shifted (default on)")
    g.add_argument("--lr", default=None, help="the Adam step, m, or 'reference' (the authors' step relative to the "
                   f"action range, {REFERENCE_LR_SHARE} of its width); default {PlannerConfig.lr}")
    g.add_argument("--buckets", type=checks.count(1, OMEGA_MAX), nargs="+", default=None,
                   help=f"resolution buckets (default {' '.join(map(str, budget.BUCKETS))}; with --timing, the "
                        "table's): each ω is priced as the smallest bucket holding it")
    g.add_argument("--pricing", choices=["measured", "reference"], default=None,
                   help="the price of an Adam step under --time-budget: a timing table measured here (default), or "
                        "the authors' fitted step time at each ω, whatever its bucket (no measuring)")


def resolve_planner_args(parser: argparse.ArgumentParser, args) -> None:
    """Fill the reference-planner options left unset from --reference-planner's values, else ours (the buckets, with
    --timing, from its table: ``load_timing``); parser.error naming a bad combination, before any work."""
    preset = REFERENCE_PLANNER if args.reference_planner else PLANNER_OPTIONS
    vote_given = args.vote is not None
    if args.pricing is not None and getattr(args, "time_budget", "") is None:  # a command with a budget, none given
        parser.error(f"--pricing {args.pricing} prices the Adam steps of a --time-budget; without one every decision "
                     "runs --adam-steps: give --time-budget S or leave --pricing out")
    for name, value in preset.items():
        if getattr(args, name) is None and not (name == "buckets" and getattr(args, "timing", None)):
            setattr(args, name, value)  # a --timing table's buckets are the run's (``load_timing``)
    if args.vote and args.resamples < 2:
        if vote_given:
            parser.error(f"--vote needs --resamples of 2 or more, got {args.resamples}")
        args.vote = False  # the preset's vote over one re-sampling is the plain plan
    if args.lr != "reference":
        try:
            args.lr = checks.lr(args.lr)
        except argparse.ArgumentTypeError as e:
            parser.error(f"--lr: {e} (or 'reference')")
    try:
        args.buckets = None if args.buckets is None else budget.check_buckets(args.buckets)
    except ValueError as e:
        parser.error(f"--buckets: {e}")
    if args.pricing == "reference" and getattr(args, "timing", None):
        parser.error("--timing and --pricing reference both price the Adam steps: give one")


def planner_options(args, env) -> dict:
    """PlannerConfig's settings from the resolved options (``resolve_planner_args``) for pushes in ``env``."""
    lr = reference_lr(env.action_bound) if args.lr == "reference" else args.lr
    return dict(starts=args.starts, resamples=args.resamples, vote=args.vote, lr=lr)


def priced(args, cfg: MPCConfig, measure: Callable[[], budget.TimingTable]) -> budget.TimingTable:
    """The timing table a --time-budget spends by, as --pricing says: the reference's fitted step prices for cfg's
    buckets and planner batch, else ``measure()`` (a table measured here, or read from a file)."""
    if args.pricing == "reference":
        return budget.reference_table(cfg.buckets, cfg.planner.samples, cfg.planner.horizon)
    return measure()


def add_planner_args(parser) -> None:
    """The planner flags of ``experiments.evaluate`` and ``experiments.label_resolution``."""
    add_budget_args(parser)
    add_reference_planner_args(parser)
    parser.add_argument("--samples", type=checks.samples, default=20, help="action sequences per plan (paper M = 20)")
    parser.add_argument("--adam-steps", type=checks.adam_steps, default=100,
                        help="Adam steps per plan (the most, under a budget)")
    parser.add_argument("--horizon", type=checks.count(1, 10), default=1,
                        help="pushes per planned sequence (paper T = 1)")


def mpc_config(env, args, mpc_steps: int = 1, real_depth: bool = False, stop_share: float | None = None
               ) -> MPCConfig:
    """The MPC settings the planner flags ask for (evaluate and label_resolution): mpc_steps per episode (1: a
    single decision, as a label's plan), stop_share (``MPCConfig``)."""
    planner = planner_config(env, samples=args.samples, adam_steps=args.adam_steps, horizon=args.horizon,
                             **planner_options(args, env))
    return MPCConfig(mpc_steps=mpc_steps, planner=planner, max_points=1024 if args.quick else 4096,
                     time_budget=args.time_budget, real_depth=real_depth, warm_start=args.warm_start,
                     buckets=args.buckets, stop_share=stop_share)


def timing_table(args, out_dir: str, obs, goal, dynamics, cfg: MPCConfig, camera, omegas
                 ) -> budget.TimingTable | None:
    """The run's timing table: ``--timing``'s, else the one an earlier run in ``out_dir`` saved (so a resumed run
    spends the budget as it began), else measured here on one observation and goal (unbatched) and saved there as
    ``timing.json``. In a job of several processes, process 0 makes the table and every process spends by it. None
    without a time budget; InputError (``check_budget``) when it affords no Adam step at one of ``omegas``."""
    if cfg.time_budget is None:
        return None
    saved = os.path.join(out_dir, "timing.json")

    def make() -> budget.TimingTable:
        path = args.timing or (saved if os.path.exists(saved) else None)
        table = priced(args, cfg, lambda: budget.TimingTable.load(path) if path is not None else
                       measure_timing(episode(obs), episode(goal), dynamics, cfg, camera))
        table.save(saved)
        if args.pricing == "reference":
            source = ""  # the table's device already names the reference's prices
        else:
            source = f", from {path}" if path else ", measured"
        print(f"timing table ({table.device}{source}): Adam steps in "
              f"{cfg.time_budget} s: " + ", ".join(f"bucket {b}: {cfg.adam_steps(b, table)}" for b in cfg.buckets))
        return table

    if distributed.part()[1] == 1:
        table = make()
    else:
        if distributed.is_writer():
            make()
        distributed.barrier(f"timing {os.path.abspath(saved)}")
        table = budget.TimingTable.load(saved)
    check_budget(cfg, table, omegas)
    return table
