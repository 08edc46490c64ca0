"""The paper's Fig. 4 from Bayesian-optimisation labels (experiments.label_resolution): c+(ω) for the same pile
with a disc vs a letter goal, and for the same goal with a spread vs a gathered pile, and how often each claim holds.

    python -m experiments.tradeoff --labels runs/labels --out runs/tradeoff

Claims (paper Sec. V-B): the best ω is higher for a letter than for a disc on the same pile, and higher for a
gathered pile (one blob) than for a spread one with the same goal. Reported: the share of pairs where the label is
higher, lower or equal, with 95 % Wilson intervals, and ``tradeoff.png`` with the GP mean of c+ for example pairs.
"""

from __future__ import annotations

import argparse
import glob
import os

import numpy as np

from dynres_jax import files
from dynres_jax.resolution import CANDIDATES
from experiments.evaluate import wilson


def compare(high: np.ndarray, low: np.ndarray) -> dict:
    """Share of pairs whose first label is higher, lower, equal (with a Wilson interval on 'higher')."""
    n = len(high)
    k = int(np.sum(high > low))
    return dict(pairs=n, higher=k / n, lower=float(np.mean(high < low)), equal=float(np.mean(high == low)),
                higher_ci95=wilson(k, n), mean_first=float(high.mean()), mean_second=float(low.mean()))


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m experiments.tradeoff", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--labels", required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    shards = {int(z["shard"]): dict(z) for z in map(np.load, sorted(glob.glob(os.path.join(args.labels,
                                                                                          "shard_*.npz"))))}
    if not shards:
        parser.error(f"no label shards in {args.labels}")
    letter_vs_disc, blob_vs_spread, examples = [], [], {}
    for s, z in shards.items():
        letter_vs_disc.append((z["label"][1::2], z["label"][0::2]))  # scenes 2j + 1 (letter) vs 2j (disc)
        examples.setdefault("goal", (z, 0, 1))
        if s % 2 == 0 and s + 1 in shards:  # shard s spread, s + 1 one blob, same goals
            blob_vs_spread.append((shards[s + 1]["label"], z["label"]))
            examples.setdefault("pile", (z, shards[s + 1]))
    ld = [np.concatenate(x) for x in zip(*letter_vs_disc, strict=True)]
    result = dict(letter_vs_disc=compare(*ld))
    if blob_vs_spread:
        result["gathered_vs_spread"] = compare(*[np.concatenate(x) for x in zip(*blob_vs_spread, strict=True)])
    os.makedirs(args.out, exist_ok=True)
    files.write_json(os.path.join(args.out, "tradeoff.json"), result)
    _plot(examples, os.path.join(args.out, "tradeoff.png"))
    print(result)
    return result


def _plot(examples: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    z, a, b = examples["goal"]
    curves = [(axes[0], z, a, "disc goal"), (axes[0], z, b, "letter goal")]
    if "pile" in examples:
        spread, blob = examples["pile"]
        curves += [(axes[1], spread, 0, "spread pile"), (axes[1], blob, 0, "gathered pile")]
    for ax, shard, i, name in curves:
        (line,) = ax.plot(CANDIDATES, shard["gp_mean"][i], label=f"{name}: best ω = {int(shard['label'][i])}")
        ax.scatter(shard["omega"][i], shard["c_plus"][i], color=line.get_color(), s=12)
    axes[0].set(title="same pile, two goals", xlabel="ω", ylabel="c+(ω) (GP mean, points observed)")
    axes[1].set(title="same goal, two piles", xlabel="ω")
    for ax in axes:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
