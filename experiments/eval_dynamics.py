"""Evaluate a dynamics checkpoint on held-out episodes: one-step and multi-step particle position error (mm) at
several resolutions ω, against two baselines measured the same way: "nothing moves" and the sweep heuristic alone.
A model trained on the full state (``--state pieces``) is measured on every piece's centre instead, one row "pieces".

    python -m experiments.eval_dynamics --ckpt runs/dynamics/ckpt --data data/piles --out runs/dynamics/eval
"""

from __future__ import annotations

import argparse
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from dynres_jax import ckpt, data, files, train
from dynres_jax.dynamics import resolution_code, rollout
from dynres_jax.graph import sweep_rollout
from dynres_jax.train import build_model

METHODS = ("model", "nothing moves", "sweep heuristic")


def errors(graphdef, state, samples: data.Sample, plate_half_width) -> dict:
    """Mean particle position error (mm) after each push, per method: {method: [horizon]}; and "per_kind": {kind:
    {method: one-step error (mm), "particles": how many particle-windows it averages}} over each kind's particles."""

    def one(s):
        preds = {"model": rollout(graphdef, state, s.positions[0], s.mask, s.action, resolution_code(s.radius)),
                 "nothing moves": jnp.broadcast_to(s.positions[0], s.positions[1:].shape),
                 "sweep heuristic": sweep_rollout(s.positions[0], s.mask, s.action, plate_half_width)}
        w = s.mask & (s.error == 0)
        return {m: jnp.where(w[None], jnp.linalg.norm(p - s.positions[1:], axis=-1), 0.0) for m, p in preds.items()}

    per = jax.vmap(one)(samples)  # {method: [B, horizon, n_max]}
    valid = np.asarray(samples.mask & (samples.error == 0)[:, None])
    out = {m: (np.asarray(e).sum((0, 2)) / max(valid.sum(), 1) * 1000).tolist() for m, e in per.items()}
    kinds = np.asarray(samples.kind)
    out["per_kind"] = {data.KIND_NAMES[k]: {**{m: float(np.asarray(e)[:, 0][valid & (kinds == k)].mean() * 1000)
                                               for m, e in per.items()},
                                            "particles": int((valid & (kinds == k)).sum())}
                       for k in np.unique(kinds[valid])}
    return out


def table(result: dict) -> str:
    """Markdown: errors per ω and method, then one-step errors per piece kind, kinds held out of training marked."""
    h = result["horizon"]
    lines = [f"| ω | {' | '.join(f'{m}: 1 step / {h} steps (mm)' for m in METHODS)} |",
             "|---:|" + "---:|" * len(METHODS)]
    for omega, r in result["omegas"].items():
        lines.append(f"| {omega} | " + " | ".join(f"{r[m][0]:.2f} / {r[m][-1]:.2f}" for m in METHODS) + " |")
    held_out = set(result["held_out_kinds"])
    lines += ["", "One step, per piece kind (all ω together):", "",
              f"| kind | {' | '.join(METHODS)} | model / heuristic |", "|---|" + "---:|" * (len(METHODS) + 1)]
    kinds = {}
    for r in result["omegas"].values():
        for kind, e in r["per_kind"].items():
            kinds.setdefault(kind, []).append(e)
    for kind, per_omega in kinds.items():
        weights = np.array([e["particles"] for e in per_omega], float)
        mean = {m: float(np.average([e[m] for e in per_omega], weights=weights)) for m in METHODS}
        name = f"{kind} (held out)" if kind in held_out else kind
        lines.append(f"| {name} | " + " | ".join(f"{mean[m]:.2f}" for m in METHODS) +
                     f" | {mean['model'] / mean['sweep heuristic']:.2f} |")
    return "\n".join(lines)


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


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m experiments.eval_dynamics", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True, help="checkpoint folder (runs/NAME/ckpt)")
    parser.add_argument("--data", required=True, help="shards; their held-out episodes are used")
    parser.add_argument("--out", required=True)
    parser.add_argument("--omegas", nargs="+", type=int, default=[10, 25, 50, 100])
    parser.add_argument("--windows", type=int, default=256, help="held-out windows per ω")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    model, meta, _ = ckpt.load_module(args.ckpt, build_model)
    tcfg = meta["train"]
    if tcfg.get("state", "particles") == "particles" and max(args.omegas) > tcfg["n_max"]:
        parser.error(f"--omegas must be at most the model's n_max = {tcfg['n_max']}")
    val = data.load_shards(args.data, "val")
    graphdef, state = nnx.split(model)
    rng = np.random.default_rng(args.seed)
    windows = data.random_windows(val, rng, args.windows, tcfg["horizon"])
    cfg = train.TrainConfig(**{k: v for k, v in tcfg.items() if k in ("n_max", "max_points", "state")})
    make = jax.jit(jax.vmap(functools.partial(train.make_sample, camera=val.camera, cfg=cfg), in_axes=(0, None, 0)))
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.windows)
    hw = meta["dynamics"]["plate_half_width"]
    result = {"horizon": tcfg["horizon"], "windows": args.windows, "step": meta.get("step"),
              "held_out_kinds": list(tcfg.get("held_out_kinds", ())), "omegas": {}}
    for omega in args.omegas if cfg.state == "particles" else ["pieces"]:  # the full state has no ω
        result["omegas"][str(omega)] = errors(graphdef, state, make(windows, 0 if omega == "pieces" else omega, keys),
                                              hw)
    os.makedirs(args.out, exist_ok=True)
    files.write_json(os.path.join(args.out, "eval.json"), result)
    plot(result, os.path.join(args.out, "eval.png"))
    text = table(result)
    files.write_text(os.path.join(args.out, "eval.md"), text)
    print(text)
    return result


if __name__ == "__main__":
    main()
