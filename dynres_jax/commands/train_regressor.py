"""Train the resolution regressor g(y_0, y_g) -> ω on Bayesian-optimisation labels (experiments.label_resolution).

    python -m experiments.train_regressor --labels runs/labels [more label folders] --out runs/regressor

Held out: every tenth pile (both of its goals), so no held-out pile was seen in training. Of the rest, every tenth pile
(at least one) is a validation set: every ``--val-every`` steps the model is scored on it and the best is kept (early
stopping; the held-out piles are never used to choose). Loss: squared error of ω scaled to [0, 1]. Augmentation: every
training sample goes through one of the 8 rotations and reflections of the square grid, which leave the label
unchanged (all six channels are images of a square bin seen from above). Reports the held-out mean absolute error in
ω against predicting the training labels' mean, and writes an orbax checkpoint (``dynres_jax.io.ckpt``) with a card,
``metrics.json`` and a scatter plot. Data-parallel over every device of every process (jax.distributed: a launcher, or
--coordinator, --num-processes, --process-id); process 0 writes.
"""

from __future__ import annotations

import json
import os

from dynres_jax import distributed
from dynres_jax.commands import checks
from dynres_jax.config import OMEGA_MAX, OMEGA_MIN
from dynres_jax.io import ckpt, files
from dynres_jax.learn.regressor import load_labels, train_regressor


@checks.guarded("train_regressor")
def main(argv=None):
    parser = checks.parser("train_regressor", __doc__)
    parser.add_argument("--labels", nargs="+", required=True, help="label folders, pooled")
    parser.add_argument("--out", required=True)
    checks.add_fresh(parser)
    parser.add_argument("--steps", type=checks.count(1), default=3000)
    parser.add_argument("--batch", type=checks.count(1), default=64)
    parser.add_argument("--lr", type=checks.lr, default=1e-3)
    parser.add_argument("--width", type=checks.count(1), default=16)
    parser.add_argument("--val-every", type=checks.count(1), default=100, help="steps between validation scores")
    parser.add_argument("--seed", type=checks.seed, default=0)
    distributed.add_args(parser)
    args = parser.parse_args(argv)
    distributed.from_args(parser, args)
    try:
        distributed.check_batch(args.batch, distributed.batch_mesh())
    except ValueError as e:
        parser.error(str(e))
    if len({os.path.realpath(folder) for folder in args.labels}) < len(args.labels):  # links too
        parser.error(f"--labels names a folder twice: {' '.join(args.labels)}")
    labels = load_labels(args.labels)
    checks.claim(args.out, "train_regressor", checks.settings(args), args.fresh, {"--labels": args.labels})
    params, metrics, truth, pred = train_regressor(labels, steps=args.steps, batch=args.batch,
                                                   lr=args.lr, width=args.width, val_every=args.val_every,
                                                   seed=args.seed)
    if not distributed.is_writer():
        return metrics
    ckpt.save(os.path.join(args.out, "ckpt"), args.steps, {"module": params}, dict(width=args.width, **metrics))
    files.write_json(os.path.join(args.out, "metrics.json"), metrics)
    _scatter(truth, pred, os.path.join(args.out, "heldout.png"))
    print(json.dumps(metrics))  # JSON, as every command prints a record
    return metrics


def _scatter(truth, pred, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4, 4))
    ax.scatter(truth, pred, s=8, alpha=0.6)
    ax.plot([OMEGA_MIN, OMEGA_MAX], [OMEGA_MIN, OMEGA_MAX], "k--", lw=1)
    ax.set(xlabel="BO label ω", ylabel="regressor ω", title="held-out scenes")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
