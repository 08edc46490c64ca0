"""Evaluate a dynamics checkpoint on held-out episodes: one-step and multi-step particle position error (mm) at
several resolutions ω, against two baselines measured the same way: "nothing moves" and the sweep heuristic alone.

    python -m experiments.eval_dynamics --ckpt runs/dynamics/ckpt --data data/piles --out runs/dynamics/eval
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from dynres_jax.commands import checks
from dynres_jax.io import ckpt, files
from dynres_jax.learn import data, targets, train
from dynres_jax.models.dynamics import resolution_code, rollout
from dynres_jax.models.graph import SWEEP_REGIONS, sweep_region, sweep_rollout
from dynres_jax.models.registry import build_model, trained_n_max

METHODS = ("model", "nothing moves", "sweep heuristic")


def errors(graphdef, state, samples: targets.Sample, plate_half_width) -> dict:
    """Mean particle position error (mm) after each push, per method: {method: [horizon]}; and one-step errors over
    subsets of the particles, {name: {method: mm, "particles": how many particle-windows it averages}}: "per_kind"
    by piece kind, "per_region" by where the particle lies relative to the first push (``graph.sweep_region``)."""

    def one(s):
        preds = {"model": rollout(graphdef, state, s.positions[0], s.mask, s.action, resolution_code(s.radius)),
                 "nothing moves": jnp.broadcast_to(s.positions[0], s.positions[1:].shape),
                 "sweep heuristic": sweep_rollout(s.positions[0], s.mask, s.action, plate_half_width)}
        w = s.mask & (s.error == 0)
        err = {m: jnp.where(w[None], jnp.linalg.norm(p - s.positions[1:], axis=-1), 0.0) for m, p in preds.items()}
        return err, sweep_region(s.positions[0], s.action[0], plate_half_width)

    per, region = jax.vmap(one)(samples)  # {method: [B, horizon, n_max]}, [B, n_max]
    per = {m: np.asarray(e) for m, e in per.items()}
    valid = np.asarray(samples.mask & (samples.error == 0)[:, None])
    out = {m: (e.sum((0, 2)) / max(valid.sum(), 1) * 1000).tolist() for m, e in per.items()}

    def one_step(names, labels):
        labels = np.asarray(labels)
        return {names[k]: {**{m: float(e[:, 0][valid & (labels == k)].mean() * 1000) for m, e in per.items()},
                           "particles": int((valid & (labels == k)).sum())}
                for k in np.unique(labels[valid])}

    out["per_kind"] = one_step(data.KIND_NAMES, samples.kind)
    out["per_region"] = one_step(SWEEP_REGIONS, region)
    return out


def table(result: dict) -> str:
    """Markdown: errors per ω and method, then one-step errors per piece kind (kinds held out of training marked) and
    per sweep region, each subset with its share of the particles and of the model's error, all ω together."""
    h = result["horizon"]
    lines = [f"| ω | {' | '.join(f'{m}: 1 step / {h} steps (mm)' for m in METHODS)} |",
             "|---:|" + "---:|" * len(METHODS)]
    for omega, r in result["omegas"].items():
        lines.append(f"| {omega} | " + " | ".join(f"{r[m][0]:.2f} / {r[m][-1]:.2f}" for m in METHODS) + " |")
    held_out = set(result["held_out_kinds"])
    lines += subset_table(result, "per_kind", "piece kind", "kind", lambda k: f"{k} (held out)" if k in held_out else k)
    lines += subset_table(result, "per_region", "place relative to the push (`graph.sweep_region`)", "where", str)
    return "\n".join(lines)


def subset_table(result: dict, key: str, what: str, column: str, name) -> list[str]:
    """Markdown lines for one-step errors over the subsets ``result["omegas"][ω][key]``: each subset's ω rows averaged
    weighted by their particle counts, with its share of all particles and of the model's summed error; name(subset)
    is the row's label under the column heading ``column``. No lines when the result has no such subsets."""
    subsets = {}
    for r in result["omegas"].values():
        for subset, e in r.get(key, {}).items():
            subsets.setdefault(subset, []).append(e)
    if not subsets:
        return []
    rows = {}
    for subset, per_omega in subsets.items():
        weights = np.array([e["particles"] for e in per_omega], float)
        rows[subset] = ({m: float(np.average([e[m] for e in per_omega], weights=weights)) for m in METHODS},
                        weights.sum())
    particles = sum(n for _, n in rows.values())
    error = max(sum(mean["model"] * n for mean, n in rows.values()), 1e-12)
    lines = ["", f"One step, per {what}, all ω together:", "",
             f"| {column} | particles | model's error | {' | '.join(METHODS)} | model / heuristic |",
             "|---|" + "---:|" * (len(METHODS) + 3)]
    for subset, (mean, n) in rows.items():
        heuristic = mean["sweep heuristic"]
        ratio = f"{mean['model'] / heuristic:.2f}" if heuristic > 0 else "-"  # nothing moved, heuristic exact
        lines.append(f"| {name(subset)} | {n / particles:.0%} | {mean['model'] * n / error:.0%} | " +
                     " | ".join(f"{mean[m]:.2f}" for m in METHODS) + f" | {ratio} |")
    return lines


def plot(result: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    omegas = list(result["omegas"])
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5), sharey=True)
    for ax, step, title in ((axes[0], 0, "one step"), (axes[1], -1, f"{result['horizon']} steps")):
        for i, m in enumerate(METHODS):
            ax.bar(np.arange(len(omegas)) + (i - 1) * 0.27, [result["omegas"][o][m][step] for o in omegas], 0.27,
                   label=m)
        ax.set(xticks=range(len(omegas)), xticklabels=omegas, xlabel="ω", title=title)
    axes[0].set_ylabel("mean particle error (mm)")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


OMEGAS = (10, 25, 50, 100)  # the default ω of the error tables


@checks.guarded("eval_dynamics")
def main(argv=None):
    parser = checks.parser("eval_dynamics", __doc__)
    parser.add_argument("--ckpt", required=True, help="checkpoint folder (runs/NAME/ckpt)")
    parser.add_argument("--data", required=True, help="shards; their held-out episodes are used")
    parser.add_argument("--out", required=True)
    checks.add_fresh(parser)
    parser.add_argument("--omegas", nargs="+", type=checks.omega, default=None,
                        help=f"the resolutions ω to measure at (default {' '.join(map(str, OMEGAS))}, those up to the "
                             "model's n_max, or n_max alone when none is)")
    parser.add_argument("--windows", type=checks.count(1), default=256,
                        help="different held-out windows per ω, at most what the held-out episodes hold (all of "
                             "them where they hold fewer, said in a line)")
    parser.add_argument("--seed", type=checks.seed, default=0)
    args = parser.parse_args(argv)
    try:
        model, meta, _ = ckpt.load_module(args.ckpt, build_model)
        n_max = trained_n_max(meta, args.ckpt)
    except ckpt.CheckpointError as e:
        parser.error(f"--ckpt: {e}")
    tcfg = meta["train"]
    if args.omegas is None:  # a quick model (n_max 8) is measured at its own ω, not refused for 10
        args.omegas = [w for w in OMEGAS if w <= n_max] or [n_max]
    if max(args.omegas) > n_max:
        parser.error(f"--omegas must be at most the model's n_max = {n_max}")
    if len(set(args.omegas)) < len(args.omegas):
        parser.error(f"--omegas names an ω twice: {args.omegas}")
    val = targets.load_shards(args.data, "val")
    rng = np.random.default_rng(args.seed)
    available = targets.window_count(val, tcfg["horizon"])
    if available == 0:
        parser.error(f"--data {args.data}: its held-out episodes hold no window of {tcfg['horizon']} pushes")
    count = min(args.windows, available)
    if count < args.windows:
        print(f"the held-out episodes of {args.data} hold {available} different windows of {tcfg['horizon']} pushes: "
              f"measuring all {available} (--windows {args.windows})")
    windows = targets.random_windows(val, rng, count, tcfg["horizon"])
    checks.claim(args.out, "eval_dynamics", checks.settings(args), args.fresh,
                 {"--ckpt": args.ckpt, "--data": args.data})
    graphdef, state = nnx.split(model)
    cfg = train.TrainConfig(**{k: v for k, v in tcfg.items() if k in ("n_max", "max_points")})
    make = jax.jit(jax.vmap(functools.partial(train.make_sample, camera=val.camera, cfg=cfg), in_axes=(0, None, 0)))
    keys = jax.random.split(jax.random.PRNGKey(args.seed), count)
    hw = meta["dynamics"]["plate_half_width"]
    result = {"horizon": tcfg["horizon"], "windows": count, "step": meta.get("step"),
              "held_out_kinds": list(tcfg.get("held_out_kinds", ())), "omegas": {}}
    for omega in args.omegas:
        result["omegas"][str(omega)] = errors(graphdef, state, make(windows, omega, keys), hw)
    files.write_json(os.path.join(args.out, "eval.json"), result)
    plot(result, os.path.join(args.out, "eval.png"))
    text = table(result)
    files.write_text(os.path.join(args.out, "eval.md"), text)
    print(f"one-step and multi-step errors of {args.ckpt} (step {result['step']}) on {count} held-out windows "
          f"of {result['horizon']} pushes, mm:\n{text}")
    print(f"wrote {', '.join(os.path.join(args.out, n) for n in ('eval.json', 'eval.md', 'eval.png'))}")
    return result


if __name__ == "__main__":
    main()
