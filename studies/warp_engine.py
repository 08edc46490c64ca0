"""Does MuJoCo Warp simulate the C scene? ``python -m studies.warp_engine --out DIR`` (issue 36, docs/warp).

Two checks, every piece kind at its default piece count:

- ``first_call`` (``--first-call``): a fresh process per kind builds a ``SizedPool``, resets 64 piles and pushes them
  once, so Warp compiles and loads its kernels in that process; on a fresh machine this is where CUDA graph capture
  failed (``sim.physics.warp.warm_up``). Reports per kind: ok, seconds, the error if any.
- ``agreement``: ``--worlds`` piles settled by C MuJoCo, one random push each (``PileEnv.sample_push``), executed by
  C MuJoCo and by MuJoCo Warp from the same state; per piece, the distance between where the two engines leave it
  (median, 90th percentile, mean; mm), broken worlds of each, and the pieces' mean travel. Beside it the chaos
  reference: C against C with every piece first moved by N(0, σ²), σ = 0.01 mm (``studies.noise_floor.perturb``):
  what two runs of the same engine differ by when the state is known to a hundredth of a millimetre.

Results: ``DIR/warp_engine.json`` and ``DIR/warp_engine.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import DEFAULT_PIECES, KINDS, SceneConfig, SimConfig, replace
from dynres_jax.io.files import write_json, write_text
from dynres_jax.sim.pool import SizedPool, WorldPool, process_pool
from studies.noise_floor import perturb

CHAOS_SIGMA = 1e-5  # m: the C-against-C reference's perturbation (0.01 mm)


def kind_config(kind: str) -> SimConfig:
    """The scene of one kind at its default piece count."""
    return SimConfig(scene=replace(SceneConfig(), kinds=(kind,), pieces=(DEFAULT_PIECES[kind],)))


def first_call(kind: str, worlds: int = 64) -> dict:
    """In this process: a Warp SizedPool of ``kind``, a reset of ``worlds`` piles and one push. {kind, ok, seconds,
    error}."""
    t0 = time.perf_counter()
    try:
        pool = SizedPool(kind_config(kind))
        keys = jax.random.split(jax.random.PRNGKey(0), worlds)
        states = pool.reset(keys)
        actions = jax.vmap(pool.env.sample_push)(keys, states.pos)
        jax.block_until_ready(pool.push(states, np.asarray(actions)).pos)
        return dict(kind=kind, ok=True, seconds=time.perf_counter() - t0, error=None)
    except Exception as e:  # noqa: BLE001 - the check reports whatever the first call raised
        return dict(kind=kind, ok=False, seconds=time.perf_counter() - t0, error=f"{type(e).__name__}: {e}"[:2000])


def piece_distances(a, b, broken) -> np.ndarray:
    """Distances (mm) between pieces' centres a, b [W, N, 3] over worlds not broken [W] in either run."""
    d = np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=-1) * 1000
    return d[~np.asarray(broken)].ravel()


def summary(d: np.ndarray) -> dict:
    return dict(median_mm=float(np.median(d)), p90_mm=float(np.percentile(d, 90)), mean_mm=float(d.mean()))


def agreement(kind: str, worlds: int, processes, seed: int = 0) -> dict:
    """One push per world in C and in Warp from the same C-settled piles, and the C-against-C chaos reference."""
    cfg = kind_config(kind)
    c_pool, w_pool = WorldPool(cfg, processes), SizedPool(cfg)
    keys = jax.random.split(jax.random.PRNGKey(seed), worlds)
    start = c_pool.reset(keys)
    actions = np.asarray(jax.vmap(c_pool.env.sample_push)(jax.random.split(jax.random.PRNGKey(seed + 1), worlds),
                                                        start.pos))
    c = c_pool.push(start, actions)
    t0 = time.perf_counter()
    w = w_pool.push(start._replace(overflow=jnp.zeros(worlds, jnp.int32)), actions)
    jax.block_until_ready(w.pos)
    w_seconds = time.perf_counter() - t0
    twin, _ = perturb(start, c_pool.scene.qpos_adr, CHAOS_SIGMA, jax.random.PRNGKey(seed + 2))
    c2 = c_pool.push(twin, actions)
    c_broken, w_broken, c2_broken = (np.asarray(s.broken) for s in (c, w, c2))
    return dict(kind=kind, pieces=int(c_pool.scene.n_pieces), worlds=worlds,
                warp_vs_c=summary(piece_distances(w.pos, c.pos, c_broken | w_broken)),
                c_vs_c_perturbed=summary(piece_distances(c2.pos, c.pos, c_broken | c2_broken)),
                travel_mm=float(piece_distances(c.pos, start.pos, c_broken).mean()),
                broken=dict(c=int(c_broken.sum()), warp=int(w_broken.sum()), c_perturbed=int(c2_broken.sum())),
                warp_push_seconds_with_compile=w_seconds)


def table(result: dict) -> str:
    lines = [f"Device: {result['device']}; {result['worlds']} worlds a kind, one push each from C-settled piles; "
             "distances per piece, mm.", "",
             "| kind | pieces | Warp vs C: median | p90 | mean | C vs C (σ = 0.01 mm): median | p90 | mean | "
             "travel | broken C / Warp |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["agreement"]:
        w, c = r["warp_vs_c"], r["c_vs_c_perturbed"]
        lines.append(f"| {r['kind']} | {r['pieces']} | {w['median_mm']:.2f} | {w['p90_mm']:.2f} | {w['mean_mm']:.2f} "
                     f"| {c['median_mm']:.2f} | {c['p90_mm']:.2f} | {c['mean_mm']:.2f} | {r['travel_mm']:.1f} | "
                     f"{r['broken']['c']} / {r['broken']['warp']} |")
    if result.get("first_call"):
        lines += ["", "First call in a fresh process (SizedPool, reset of 64 piles, one push):", "",
                  "| kind | ok | seconds | error |", "|---|---|---:|---|"]
        lines += [f"| {r['kind']} | {r['ok']} | {r['seconds']:.1f} | {r['error'] or ''} |"
                  for r in result["first_call"]]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m studies.warp_engine", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="folder for warp_engine.json and .md")
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=list(KINDS))
    ap.add_argument("--worlds", type=int, default=256, help="worlds per kind in the agreement check")
    ap.add_argument("--workers", type=int, default=None, help="C worker processes (default every core)")
    ap.add_argument("--first-call", action="store_true", help="also run the first-call check, a process per kind")
    ap.add_argument("--one-first-call", metavar="KIND", help=argparse.SUPPRESS)  # the child process of --first-call
    args = ap.parse_args(argv)
    if args.one_first_call:
        print(json.dumps(first_call(args.one_first_call)))
        return
    os.makedirs(args.out, exist_ok=True)
    result = dict(device=jax.devices()[0].device_kind, worlds=args.worlds, agreement=[], first_call=[])
    if args.first_call:
        for kind in args.kinds:
            run = subprocess.run([sys.executable, "-m", "studies.warp_engine", "--out", args.out,
                                  "--one-first-call", kind], capture_output=True, text=True)
            lines = [ln for ln in run.stdout.splitlines() if ln.startswith("{")]
            row = json.loads(lines[-1]) if lines else dict(kind=kind, ok=False, seconds=0.0,
                                                           error=f"exit {run.returncode}: {run.stderr[-1500:]}")
            result["first_call"].append(row)
            print(f"first call {kind}: ok={row['ok']} {row['seconds']:.1f} s {row['error'] or ''}", flush=True)
    with process_pool(args.workers) as processes:
        for kind in args.kinds:
            row = agreement(kind, args.worlds, processes)
            result["agreement"].append(row)
            print(f"{kind}: Warp vs C median {row['warp_vs_c']['median_mm']:.2f} mm, p90 "
                  f"{row['warp_vs_c']['p90_mm']:.2f}; C vs C {row['c_vs_c_perturbed']['median_mm']:.2f}; broken "
                  f"{row['broken']}", flush=True)
            write_json(os.path.join(args.out, "warp_engine.json"), result)
    write_text(os.path.join(args.out, "warp_engine.md"), table(result) + "\n")
    print(table(result))


if __name__ == "__main__":
    main()
