"""Kernel profile of MJX pushes: GPU time per simulator step of every kernel XLA launches for a scene variant of
``benchmarks.bench_sim`` (CUPTI trace through ``torch.profiler``), with the optimised HLO that names each fusion and
the MJX function each fusion comes from. README, "Speed".

    python scripts/profile_sim.py OUT_DIR --variants fast [--worlds 4096] [--steps 50]

Writes OUT_DIR/kernels_VARIANT.json ([name, µs per step, launches per step, source], slowest first) and
OUT_DIR/sim_VARIANT.hlo.txt; prints the 30 slowest kernels.
"""

import argparse
import json
import os
import re
import time

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # torch and JAX share the GPU

import jax  # noqa: E402

from benchmarks.bench_sim import _batch, variant  # noqa: E402
from dynres_jax.sim.env import PileEnv  # noqa: E402


def _sources(hlo: str) -> dict[str, str]:
    """kernel name (an HLO instruction's, dots as underscores) -> the op_name of its metadata from MJX's ``step``
    on (which function of MJX it computes: forward/collision, forward/solve, ...)."""
    out = {}
    for name, op in re.findall(r'%([\w.\-]+) = [^\n]*?metadata=\{op_name="([^"]*)"', hlo):
        out[name] = out[name.replace(".", "_")] = op.split("/step/", 1)[-1].replace("closed_call/", "")
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out")
    parser.add_argument("--variants", nargs="+", default=["fast"])
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args()
    from torch.profiler import ProfilerActivity, profile

    os.makedirs(args.out, exist_ok=True)
    for name in args.variants:
        cfg, jacobian = variant(name)
        env = PileEnv(cfg, backend="mjx", render=False, contact_jacobian=jacobian)
        states, actions = _batch(env, args.worlds)
        pos, quat = jax.vmap(env.plate_trajectory)(actions)
        pos, quat = pos[:, :args.steps], quat[:, :args.steps]
        sim = jax.jit(jax.vmap(env.simulate))

        def run(sim=sim, states=states, pos=pos, quat=quat):
            return jax.block_until_ready(sim(states, pos, quat))

        run()
        t0 = time.perf_counter()
        run()
        wall = time.perf_counter() - t0
        hlo = sim.lower(states, pos, quat).compile().as_text()
        with open(os.path.join(args.out, f"sim_{name}.hlo.txt"), "w") as f:
            f.write(hlo)
        src = _sources(hlo)
        with profile(activities=[ProfilerActivity.CUDA]) as trace:
            run()
        rows = sorted(((e.key, e.device_time_total / args.steps, e.count / args.steps, src.get(e.key, ""))
                       for e in trace.key_averages()), key=lambda r: -r[1])
        with open(os.path.join(args.out, f"kernels_{name}.json"), "w") as f:
            json.dump(rows, f, indent=0)
        print(f"{name}: {1e3 * wall / args.steps:.3f} ms per step of {args.worlds} worlds (wall), kernels "
              f"{sum(r[1] for r in rows) / 1e3:.3f} ms per step; {args.worlds * args.steps / wall:,.0f} world-steps/s")
        for kernel, us, count, where in rows[:30]:
            print(f"  {us:8.1f} µs {count:4.0f}x  {kernel[:60]:60s} {where[:110]}")


if __name__ == "__main__":
    main()
