"""Benchmarks: ``python -m experiments.benchmark {sim,warp,perception,planner,resolution,all} --json FILE [--quick]``.

Every figure is taken on whatever device JAX sees (named in the output) against a peer measured in the same run.
``all`` runs the three in turn and writes one Markdown table (printed, and beside the JSON as ``FILE.md``) with a
row per figure: ours, the peer, and the ratio.
"""

from __future__ import annotations

import json

from dynres_jax.commands import checks
from dynres_jax.io.files import write_json, write_text


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
        if "whole_push" in v["mjx"]:
            w = v["mjx"]["whole_push"]
            lines.append(f"| {name}, whole pushes | {w['worlds']} | - | {w['pushes_per_s']:,.1f} | {c:,.1f} | "
                         f"{w['pushes_per_s'] / c:.2f}x |")
    return "\n".join(lines)


def _row(what: str, ours: str, peer: str, ratio: float | None) -> str:
    return f"| {what} | {ours} | {peer} | {'-' if ratio is None else f'{ratio:,.1f}x'} |"


def report_table(results: dict) -> str:
    """One Markdown table of ``benchmark all``'s results: {"sim": ..., "perception": ..., "planner": ...}."""
    from benchmarks.bench_sim import compared_rate

    sim, per, pl = results["sim"], results["perception"], results["planner"]
    j = pl["jax"]
    lines = [f"Device: {j['device']} (JAX {j['jax_version']}); host: {sim['host_cores']} cores"
             f"{' (quick sizes: checks only)' if results.get('quick') else ''}.", "",
             "| benchmark | ours | peer, measured in the same run | ours, times faster |", "|---|---|---|---:|"]
    for name, v in sim["variants"].items():
        best = compared_rate(v["mjx"])
        c = v["c_mujoco"]
        how = "whole pushes" if "whole_push" in v["mjx"] else "from the first steps"
        lines.append(_row(f"simulator `{name}`, {sim['pieces']} pieces: pushes/s",
                          f"MJX, {best['worlds']:,} worlds ({how}): {best['pushes_per_s']:,.1f}",
                          f"C MuJoCo, {c['cores']} cores: {c['pushes_per_s']:,.1f}",
                          best["pushes_per_s"] / c["pushes_per_s"]))
    f, npy = per["fps"], per["fps_numpy"]
    lines.append(_row(f"FPS, {f['clouds']:,} clouds x {f['points']:,} points -> {f['n']}: ms per batch",
                      f"JAX vmap: {f['median_ms']:,.1f}", f"NumPy loop: {npy['batch_ms_scaled']:,.0f}",
                      npy["batch_ms_scaled"] / f["median_ms"]))
    h, packed = per["h"], per["h_max_points"]
    lines.append(_row(f"h (ω = {h['omega']}), {h['observations']:,} observations of {h['image']}² px: ms per batch",
                      f"foreground packed into {packed['max_points']:,} slots: {packed['median_ms']:,.1f}",
                      f"every pixel a candidate: {h['median_ms']:,.1f}", h["median_ms"] / packed["median_ms"]))
    batch = f"{pl['batch']:,} pushes x {pl['particles']} particles"
    t, b = pl["torch"], pl["jax_bf16"]
    torch_cell = f"PyTorch reference (PropNet + c): {t['ms_per_step']:.2f}" if "ms_per_step" in t else t["skipped"]
    lines.append(_row(f"planner, one Adam step over {batch}: ms", f"JAX: {j['ms_per_step']:.2f}", torch_cell,
                      pl.get("speedup")))
    lines.append(_row(f"planner, one Adam step over {batch}, bfloat16 edges (vs float32, {b['quality_model']}: "
                      f"predictions {b['prediction_mean_mm']:.2f} mm mean, {b['prediction_max_mm']:.2f} mm max; "
                      f"best plan cost {b['best_cost_in_float32']:.2f} vs {b['float32_best_cost']:.2f} px): ms",
                      f"JAX: {b['ms_per_step']:.2f}", torch_cell, pl.get("speedup_bf16")))
    plans = [("", j), (", bfloat16 edges", b)]
    if "jax_shipped" in pl:  # the shipped checkpoint's architecture, when it differs from the reference's
        shipped = pl["jax_shipped"]
        lines.append(_row(f"planner, one Adam step over {batch}, {shipped['model']}: ms",
                          f"JAX: {shipped['ms_per_step']:.2f}", torch_cell, pl.get("speedup_shipped")))
        plans.append((f", {shipped['model']}", shipped))
    for name, x in plans:
        lines.append(_row(f"planner, a {pl['steps']}-step plan over {batch}{name}: s (compile {x['compile_s']:.1f} s)",
                          f"JAX: {x['plan_s']:.2f}", f"goal: {pl['plan_goal_s']:.1f}", pl["plan_goal_s"] / x["plan_s"]))
    return "\n".join(lines)


USES = dict(variants=("sim", "all"), worlds=("sim", "warp", "all"), graph_modes=("warp",), full_sweep=("sim", "all"),
            pieces=("sim", "warp", "all"), batch=("resolution",))  # which benchmarks read each option


def check_flags(parser, args) -> None:
    """parser.error, before any timing, for an option the chosen benchmark does not read, or a scene variant it does
    not have (--variants, --full-sweep)."""
    for name, used_by in USES.items():
        if getattr(args, name) not in (None, parser.get_default(name)) and args.what not in used_by:
            parser.error(f"--{name.replace('_', '-')} is read by benchmark {' and '.join(used_by)}, not {args.what}")
    if args.variants is not None or args.full_sweep is not None:
        from benchmarks.bench_sim import VARIANTS

        for flag, names in (("--variants", args.variants), ("--full-sweep", args.full_sweep)):
            unknown = [n for n in names or () if n not in VARIANTS]
            if unknown:
                parser.error(f"{flag}: no scene variant {', '.join(map(repr, unknown))} (the variants: "
                             f"{', '.join(VARIANTS)})")


@checks.guarded("benchmark")
def main(argv=None):
    parser = checks.parser("benchmark", __doc__)
    parser.add_argument("what", choices=["sim", "warp", "perception", "planner", "resolution", "all"])
    parser.add_argument("--json", help="write the results here (atomically)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes: checks the benchmark runs, in seconds")
    parser.add_argument("--variants", nargs="*", help="sim: scene variants (default: all)")
    parser.add_argument("--worlds", nargs="*", type=checks.count(1, 1 << 20),
                        help="sim: world counts (default 1 16 256 1024 4096); warp: "
                        "batch sizes (default 1024 2048 4096 8192)")
    parser.add_argument("--graph-modes", nargs="*", choices=["WARP", "JAX", "NONE"], help="warp: CUDA graph modes")
    parser.add_argument("--full-sweep", nargs="*", help="sim: variants timed at every world count")
    parser.add_argument("--pieces", type=checks.count(1, 1000), default=100, help="pieces in the pile (default 100)")
    parser.add_argument("--batch", choices=["benchmark", "task"], help="resolution: 1,500 candidates (benchmark) or "
                        "50 (task); default benchmark on a GPU, task on a CPU")
    args = parser.parse_args(argv)
    check_flags(parser, args)
    if args.json is not None:  # before minutes of timing, not after (the audit: a folder lost a whole run)
        checks.out_file(args.json, (".json",), beside=".md" if args.what == "all" else "", flag="--json")
    if args.what == "all":
        from benchmarks import bench_perception, bench_planner, bench_sim

        result = dict(quick=args.quick,
                      sim=bench_sim.run(args.quick, args.pieces, args.variants, args.worlds, args.full_sweep),
                      perception=bench_perception.run(args.quick), planner=bench_planner.run(args.quick))
        table = report_table(result)
        print(table)
        if args.json:
            write_text(args.json + ".md", table + "\n")
    elif args.what == "sim":
        from benchmarks import bench_sim

        result = bench_sim.run(args.quick, args.pieces, args.variants, args.worlds, args.full_sweep)
        print(sim_table(result))
    elif args.what == "warp":
        from benchmarks import bench_warp
        from dynres_jax.errors import InputError
        from dynres_jax.sim.physics import warp

        try:
            warp.check_installed()
        except InputError as e:
            parser.error(str(e))
        result = bench_warp.run(args.quick, pieces=args.pieces, worlds=args.worlds, graph_modes=args.graph_modes)
        print(bench_warp.table(result))
    elif args.what == "resolution":
        from benchmarks import bench_resolution

        result = bench_resolution.run(args.quick, args.batch)
        print(bench_resolution.table(result))
    else:
        import importlib

        result = importlib.import_module(f"benchmarks.bench_{args.what}").run(args.quick)
        print(json.dumps(result, indent=1))
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
