"""The stop rule replayed on an evaluation made without it (``tasks.stopped``): for each stop share, the success an
episode that holds from the first frame meeting it would have had, against no rule on the same episodes (successes
only with the rule / only without, McNemar's p; final d's mean difference with its bootstrap interval), the mean step
it stopped at and, with --letters, per goal character. The rule is chosen on tuning seeds (--choose: the highest
success, ties to the larger share) and measured once on fresh ones (--shares S). With --steps, the same for the
first T MPC steps of each episode (an MPC step's keys depend on the step alone, so the first T steps of a longer run
are the T-step run), and --choose picks (T, share) by the highest success, ties to fewer steps, then the larger share.
Sort's seen share is the lower kind's perceived share inside its goal (runs before 2026-11-29 record none: their
table has no rule, only the steps). Several --run files (blocks of seeds) are read as one run, episodes in turn.

    python scripts/stop_rule.py --run RUNS/r_tune/50.json --task redistribute --choose
    python scripts/stop_rule.py --run RUNS/r_fresh/50.json --task redistribute --shares 0.95 --letters BDGPQV345689
    python scripts/stop_rule.py --run RUNS/r_tune/50.json --task redistribute --steps 60 80 100 --choose

Writes the Markdown table to --out and prints it.
"""

from __future__ import annotations

import argparse

import numpy as np

from dynres_jax.control.tasks import PER_STEP, episode_success, first_steps, step_success, stopped
from dynres_jax.io import files
from dynres_jax.stats import mcnemar, paired_bootstrap, wilson
from scripts.variants import groups, read_results

SHARES = tuple(np.round(np.arange(0.85, 1.0001, 0.01), 2))
def rows(results: dict, task: str, shares, letters: str | None) -> tuple[list[str], tuple[int, float]]:
    """The table's rows (goal, stop share) and (successes, share) of the share --choose keeps (over every episode;
    inf for no rule, the largest share: it never stops)."""
    base = episode_success(task, results)
    reached = step_success(task, results).any(axis=0)
    lines, best = [], (-1, 0.0)
    shares = shares if "seen_inside" in results else ()
    runs = {share: results if share is None else stopped(results, share) for share in (None, *shares)}
    for goal, pick in groups(len(base), letters).items():
        for share, run in runs.items():
            ok = episode_success(task, run)
            k, n = int(ok[pick].sum()), int(pick.sum())
            lo, hi = wilson(k, n)
            line = (f"| {goal} | {'none' if share is None else f'{share:.2f}'} | {k / n:.0%} ({lo:.0%}-{hi:.0%}) | "
                    f"{int(reached[pick].sum())} |")
            if share is None:
                lines.append(line + " | | |")
                if goal == "all":
                    best = max(best, (k, np.inf))
                continue
            stop = np.asarray(run["stopped_at"])[pick]
            test = mcnemar(ok[pick], base[pick])
            d = paired_bootstrap(np.asarray(run["final_distance"])[pick], np.asarray(results["final_distance"])[pick]) \
                if n > 1 else dict(mean=np.nan, ci95=(np.nan, np.nan))
            lines.append(line + f" {np.mean(stop):.1f} ({np.mean(stop < len(results['seen_inside'])):.0%} stop) | "
                         f"{test['first_only']} / {test['second_only']} (p = {test['p']:.3f}) | "
                         f"{d['mean']:+.2f} [{d['ci95'][0]:+.2f}, {d['ci95'][1]:+.2f}] |")
            if goal == "all":
                best = max(best, (k, share))
    return lines, best


PER_EPISODE = ("broken", "success", "start_pieces", "final_pieces")  # [E] beside the finals (final_*)


def join(runs: list[dict]) -> dict:
    """Evaluations of one method on blocks of seeds -> one evaluation, the blocks' episodes in turn: the per-step
    records [T][E] (``tasks.PER_STEP``) joined on the episode axis, the per-episode ones [E] on the first, the means
    per step recomputed; the rest (device, dynamics) as the first block's."""
    out = dict(runs[0])
    for key in runs[0]:
        if key in PER_STEP:
            out[key] = np.concatenate([np.asarray(r[key]) for r in runs], axis=1).tolist()
        elif key in PER_EPISODE or key.startswith("final_"):
            out[key] = np.concatenate([np.asarray(r[key]) for r in runs]).tolist()
        elif key.startswith("mean_"):
            out[key] = np.concatenate([np.asarray(r[key[5:]]) for r in runs], axis=1).mean(axis=1).tolist()
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, nargs="+",
                        help="an evaluation's METHOD.json (or .json.gz) made without the rule; several: one run")
    parser.add_argument("--task", default="redistribute")
    parser.add_argument("--shares", type=float, nargs="+", default=SHARES)
    parser.add_argument("--letters", default=None, help="per goal character too (episode i's: letters[i % len])")
    parser.add_argument("--steps", type=int, nargs="+", default=None, help="tables for the first T MPC steps too")
    parser.add_argument("--choose", action="store_true", help="print the share (and T) with the highest success")
    parser.add_argument("--out", default=None, help="write the Markdown table here")
    args = parser.parse_args(argv)
    results = join([read_results(path) for path in args.run])
    text, best = "", (-1, 0, 0.0)
    for steps in args.steps or [len(results["inside"])]:
        lines, (k, share) = rows(first_steps(results, steps), args.task, args.shares, args.letters)
        best = max(best, (k, -steps, share))
        text += "\n".join([f"{steps} MPC steps:", "",
                           "| goal | stop share | success (95 % CI) | reached success at some step | mean stop step | "
                           "against none: only here / only there | Δ final d (95 % CI) |",
                           "|---|---:|---:|---:|---:|---:|---:|", *lines]) + "\n\n"
    print(text)
    if args.choose:
        k, steps, share = best
        print(f"chosen (the highest success, ties to fewer steps, then the larger share): {-steps} MPC steps, "
              f"stop share {'none' if share == np.inf else f'{share:.2f}'}, {k} successes")
    if args.out:
        files.write_text(args.out, text)


if __name__ == "__main__":
    main()
