"""Benchmarks: ``python -m experiments.benchmark {sim,perception,planner} --json FILE [--quick]``.

Every figure is taken on whatever device JAX sees (named in the output) against a peer measured in the same run.
"""

from __future__ import annotations

import argparse
import json

from dynres_jax.files import write_json


def sim_table(result: dict) -> str:
    """Markdown table of a sim benchmark result."""
    lines = [f"Device: {result['device']}; C MuJoCo on {result['host_cores']} host cores; {result['pieces']} pieces.",
             "", "| variant | worlds | MJX world-steps/s | MJX pushes/s | C MuJoCo pushes/s | MJX / C |",
             "|---|---:|---:|---:|---:|---:|"]
    for name, v in result["variants"].items():
        c = v["c_mujoco"]["pushes_per_s"]
        for r in v["mjx"]["rows"]:
            lines.append(f"| {name} | {r['worlds']} | {r['world_steps_per_s']:,.0f} | {r['pushes_per_s']:,.1f} | "
                         f"{c:,.1f} | {r['pushes_per_s'] / c:.2f}x |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m experiments.benchmark", description=__doc__)
    parser.add_argument("what", choices=["sim", "perception", "planner"])
    parser.add_argument("--json", help="write the results here (atomically)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes: checks the benchmark runs, in seconds")
    parser.add_argument("--variants", nargs="*", help="sim: scene variants (default: all)")
    parser.add_argument("--worlds", nargs="*", type=int, help="sim: world counts (default 1 16 256 1024 4096)")
    parser.add_argument("--full-sweep", nargs="*", help="sim: variants timed at every world count")
    parser.add_argument("--pieces", type=int, default=100)
    args = parser.parse_args(argv)
    if args.what == "sim":
        from experiments import bench_sim

        result = bench_sim.run(args.quick, args.pieces, args.variants, args.worlds, args.full_sweep)
        print(sim_table(result))
    else:
        import importlib

        result = importlib.import_module(f"experiments.bench_{args.what}").run(args.quick)
        print(json.dumps(result, indent=1))
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
