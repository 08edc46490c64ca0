"""Policy variants compared episode by episode, from the folders the variants recipe wrote: per kind (Sort:
pair) and variant, or per goal character with ``--letters``, the success share (``tasks.episode_success``) with its
Wilson interval, and each variant against the first (paired: successes only here / only there with McNemar's p, final
d's mean difference with its bootstrap interval); Sort's failures by cause.

    python scripts/variants.py --runs RUNS/variants --variants base mix10 --out docs/sort/mixing/fresh.md
    python scripts/variants.py --runs RUNS/variants --task redistribute --letters F2O7 --variants s20 s40

RUNS holds VARIANT/TASK-KIND/METHOD.json or .json.gz (``--method``, default 50). Several RUNS are blocks of one
experiment run in turn (the second's SEED following on the first's episodes), read as one run, episode after episode:

    python scripts/variants.py --runs docs/sort/kind_hinge/fresh docs/sort/kind_hinge/fresh2 --variants paper kind

``--at VARIANT=T`` or ``VARIANT=T:SHARE`` reads a variant as its first T MPC steps (``tasks.first_steps``), with
the stop rule at SHARE replayed (``tasks.stopped``): one run at the most steps, without a rule, gives every shorter or
stopped setting.

    python scripts/variants.py --runs RUNS --task redistribute --variants base hinge --at base=80:0.92 hinge=90

A Sort failure is "mixing" when both kinds are at least 80 % inside their goals but 5 % or more of the pieces lie in
the other kind's goal, "short" when a kind is below 80 % with mixing under 5 %, "both" otherwise. With --letters,
episode i's character is letters[i % len] (evaluate's rule). Writes the Markdown table to --out and prints it;
--plot PNG draws each variant's mean inside share and d against the MPC step.
"""

from __future__ import annotations

import argparse
import glob
import gzip
import json
import os

import numpy as np

from dynres_jax.control.tasks import episode_success, first_steps, sort_kinds_inside, sort_mixed, stopped
from dynres_jax.io import files
from dynres_jax.stats import mcnemar, paired_bootstrap, wilson


def failures(result: dict) -> str:
    """A Sort method's results -> its failures by cause, "mixing / short / both"."""
    inside, mixed = sort_kinds_inside(result["final_kind_inside"]), sort_mixed(result["final_mixing"])
    failed = ~episode_success("sort", result)
    counts = failed & inside & mixed, failed & ~inside & ~mixed, failed & ~inside & mixed
    return " / ".join(str(int(np.sum(c))) for c in counts)


def read_results(path: str) -> dict:
    """An evaluation's METHOD.json, or its gzipped copy (METHOD.json.gz, as docs/ keeps them)."""
    with (gzip.open if path.endswith(".gz") else open)(path, "rt") as f:
        return json.load(f)


FINAL_KEYS = ("final_distance", "final_inside", "final_kind_inside", "final_mixing", "broken", "success")  # [E, ...]
STEP_KEYS = ("distance", "inside", "omega", "adam_steps", "seen_inside", "mixing", "kind_inside")  # [T, E, ...]


def joined(blocks: list[dict]) -> dict:
    """Results of one method over blocks of episodes (each a METHOD.json, the same MPC steps) -> one result, episode
    after episode: the final values [E, ...] and the per-step ones [T, E, ...] concatenated, the per-step means
    recomputed; the other fields (seconds, the model) the first block's."""
    if len(blocks) == 1:
        return blocks[0]
    steps = {len(b["distance"]) for b in blocks}
    if len(steps) > 1:
        raise ValueError(f"blocks of different MPC steps ({sorted(steps)}) cannot be read as one run")
    out = dict(blocks[0])
    for key in FINAL_KEYS + STEP_KEYS:
        if all(key in b for b in blocks):
            out[key] = np.concatenate([np.asarray(b[key]) for b in blocks], axis=int(key in STEP_KEYS)).tolist()
        else:
            out.pop(key, None)
    for key in ("distance", "inside", "mixing"):
        if key in out:
            out["mean_" + key] = np.mean(out[key], axis=1).tolist()
    out.pop("start_pieces", None), out.pop("final_pieces", None)
    return out


def groups(n: int, letters: str | None) -> dict[str, np.ndarray]:
    """The rows of a kind's table: every episode, then, with letters, each character's episodes."""
    rows = {"all": np.ones(n, bool)}
    for c in letters or "":
        rows[c] = np.arange(n) % len(letters) == letters.index(c)
    return rows


def at(text: str) -> tuple[str, tuple[int, float | None]]:
    """--at's VARIANT=T[:SHARE] -> (variant, (T, share or None))."""
    try:
        name, setting = text.split("=", 1)
        steps, _, share = setting.partition(":")
        return name, (int(steps), float(share) if share else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--at takes VARIANT=T or VARIANT=T:SHARE, got {text!r}") from None


def cut(results: dict, setting: tuple[int, float | None] | None) -> dict:
    """A variant's results at its --at setting (T steps, the stop rule at SHARE), or as they are (None)."""
    if setting is None:
        return results
    steps, share = setting
    results = first_steps(results, steps)
    return results if share is None else stopped(results, share)


def table(runs: list[str], task: str, variants: list[str], method: str, letters: str | None = None,
          settings: dict | None = None) -> str:
    """The Markdown table: rows (kind, goal character, variant); settings: {variant: (T, share)} (``cut``)."""
    sort = task == "sort"
    lines = ["| kind | goal | variant | success (95 % CI) |" + (" failures: mixing / short / both |" if sort else "")
             + f" against {variants[0]}: only here / only there (McNemar p) | Δ final d (95 % CI) |",
             "|---|---|---|---:|" + ("---:|" if sort else "") + "---:|---:|"]
    kinds = sorted({os.path.basename(p)[len(task) + 1:] for p in glob.glob(os.path.join(runs[0], "*", f"{task}-*"))
                    if os.path.isdir(p)})
    for kind in kinds:
        results = {}
        for v in variants:
            blocks = [read_method(block, v, task, kind, method) for block in runs]
            if all(b is not None for b in blocks):
                results[v] = cut(joined(blocks), (settings or {}).get(v))
            elif any(b is not None for b in blocks):
                missing = [block for block, b in zip(runs, blocks, strict=True) if b is None]
                raise SystemExit(f"variants.py: {v}/{task}-{kind}/{method}.json is missing from {', '.join(missing)}")
        if variants[0] not in results:
            continue
        first = results[variants[0]]
        n = min(len(r["final_distance"]) for r in results.values())  # a shorter run pairs on its first episodes
        success = {v: episode_success(task, r)[:n] for v, r in results.items()}
        base = success[variants[0]]
        for name, rows in groups(n, letters).items():
            for v, r in results.items():
                ok = success[v][rows]
                lo, hi = (max(0.0, x) for x in wilson(int(ok.sum()), len(ok)))  # no "-0 %"
                row = f"| {kind} | {name} | {v} | {ok.mean():.0%} ({lo:.0%}-{hi:.0%}), {ok.sum()} of {len(ok)} |"
                if sort:
                    row += f" {failures(r) if name == 'all' else ''} |"
                if v == variants[0]:
                    lines.append(row + " | |")
                    continue
                test = mcnemar(ok, base[rows])
                p = "p < 0.001" if test["p"] < 0.001 else f"p = {test['p']:.3f}"
                row += f" {test['first_only']} / {test['second_only']} ({p}) |"
                if rows.sum() < 2:  # no interval from one episode
                    lines.append(row + " |")
                    continue
                delta = paired_bootstrap(np.asarray(r["final_distance"])[:n][rows],
                                         np.asarray(first["final_distance"])[:n][rows])
                lines.append(row + f" {delta['mean']:+.2f} [{delta['ci95'][0]:+.2f}, {delta['ci95'][1]:+.2f}] |")
    return "\n".join(lines) + "\n"


def read_method(runs: str, variant: str, task: str, kind: str, method: str) -> dict | None:
    """RUNS/VARIANT/TASK-KIND/METHOD.json (or .json.gz), or None where there is none."""
    path = os.path.join(runs, variant, f"{task}-{kind}", f"{method}.json")
    for name in (path, path + ".gz"):
        if os.path.exists(name):
            return read_results(name)
    return None


def plot(runs: str, task: str, variants: list[str], method: str, path: str) -> None:
    """Each variant's (and kind's) mean inside share and mean d over its MPC steps, as a PNG at path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (inside, distance) = plt.subplots(1, 2, figsize=(10, 3.6))
    for v in variants:
        for p in sorted(glob.glob(os.path.join(runs, v, f"{task}-*", f"{method}.json"))):
            with open(p) as f:
                r = json.load(f)
            label = f"{v} ({os.path.basename(os.path.dirname(p))[len(task) + 1:]})"
            steps = np.arange(1, len(r["mean_inside"]) + 1)
            inside.plot(steps, np.asarray(r["mean_inside"]) * 100, label=label)
            distance.plot(steps, r["mean_distance"], label=label)
    inside.set(xlabel="MPC step", ylabel="pieces inside the goal (%, mean)")
    distance.set(xlabel="MPC step", ylabel="d (px, mean)")
    inside.legend(fontsize=8)
    for ax in (inside, distance):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    files.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", required=True, nargs="+",
                        help="the variants folder of the variants recipe; several: blocks of episodes read in turn")
    parser.add_argument("--variants", nargs="+", required=True, help="variant folders; the first is the reference")
    parser.add_argument("--task", default="sort", choices=("gather", "redistribute", "sort"))
    parser.add_argument("--method", default="50")
    parser.add_argument("--letters", default=None, help="Redistribute: rows per goal character (evaluate's --letters)")
    parser.add_argument("--at", type=at, nargs="+", default=[], metavar="VARIANT=T[:SHARE]",
                        help="read a variant as its first T MPC steps, with the stop rule at SHARE replayed")
    parser.add_argument("--out", default=None, help="write the table here (Markdown)")
    parser.add_argument("--plot", default=None, metavar="PNG", help="draw the variants' means over the MPC steps here")
    args = parser.parse_args(argv)
    real = [os.path.realpath(r) for r in args.runs]
    if len(set(real)) < len(real):
        parser.error(f"--runs names a folder twice (through a link too): {' '.join(args.runs)}")
    if args.plot and len(args.runs) > 1:
        parser.error("--plot draws one folder's runs; give one --runs folder")
    text = table(args.runs, args.task, args.variants, args.method, args.letters, dict(args.at))
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        files.write_text(args.out, text)
    if args.plot:
        plot(args.runs[0], args.task, args.variants, args.method, args.plot)
    print(text)


if __name__ == "__main__":
    main()
