"""Kernel profile of the planner at the benchmark's batch (50 pushes x 30 re-samplings x 100 particles, the
reference architecture): GPU time per Adam step of every kernel XLA launches, from a CUPTI trace taken through
``torch.profiler`` (PyTorch is on the GPU machine; JAX's own traces need TensorBoard to read), and the optimised HLO
that names each fusion. README, "Planner speed".

    python scripts/profile_planner.py OUT_DIR [--steps 50]

Writes OUT_DIR/kernels_{float32,bfloat16}.json ([name, µs per step, launches per step], slowest first) and
OUT_DIR/plan_{float32,bfloat16}.hlo.txt; prints the 40 slowest kernels.
"""

import argparse
import json
import os
import time

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # torch and JAX share the GPU

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from benchmarks.bench_planner import FULL, PARTICLE_RADIUS, _piles, _timed_model_and_cost  # noqa: E402
from dynres_jax.control.planner import PlannerConfig, _as_pytree_fn, _plan_jit, _traced, plan  # noqa: E402
from dynres_jax.models.registry import EDGE_DTYPES, learned_dynamics  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out")
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args()
    from torch.profiler import ProfilerActivity, profile

    os.makedirs(args.out, exist_ok=True)
    model, cost = _timed_model_and_cost()
    pile = jnp.asarray(_piles(FULL["particles"], FULL["resamples"]))
    mask = jnp.ones(pile.shape[:2], bool)
    config = PlannerConfig(samples=FULL["samples"], resamples=FULL["resamples"])
    key = jax.random.PRNGKey(0)
    for edge_dtype in EDGE_DTYPES:
        dynamics = learned_dynamics(model, edge_dtype)(PARTICLE_RADIUS)

        def run(dynamics=dynamics):
            return jax.block_until_ready(plan(dynamics, cost, pile, mask, key, config, adam_steps=args.steps))

        run()
        t0 = time.perf_counter()
        run()
        wall = time.perf_counter() - t0
        hlo = _plan_jit.lower(_as_pytree_fn(dynamics), _as_pytree_fn(cost), pile, mask, key, None, None,
                              config=_traced(config), steps=args.steps).compile().as_text()
        with open(os.path.join(args.out, f"plan_{edge_dtype}.hlo.txt"), "w") as f:
            f.write(hlo)
        with profile(activities=[ProfilerActivity.CUDA]) as trace:
            run()
        rows = sorted(((e.key, e.device_time_total / args.steps, e.count / args.steps) for e in trace.key_averages()),
                      key=lambda r: -r[1])
        with open(os.path.join(args.out, f"kernels_{edge_dtype}.json"), "w") as f:
            json.dump(rows, f, indent=0)
        print(f"{edge_dtype}: {1e3 * wall / args.steps:.2f} ms per step (wall, fixed costs included), kernels "
              f"{sum(r[1] for r in rows) / 1e3:.3f} ms per step")
        for name, us, count in rows[:40]:
            print(f"  {us:8.1f} µs {count:4.0f}x  {name[:100]}")


if __name__ == "__main__":
    main()
