"""MuJoCo Warp benchmark: whole pushes per second of the default (C) scene on one GPU, against C MuJoCo on every host
core measured in the same run (``bench_sim.c_reference``), and both engines at once (Warp on the GPU while C workers
use the other cores: what a data run gets from one machine).

Warp is timed at each batch size in ``worlds`` and each CUDA graph mode in ``graph_modes`` (Warp captures a graph
per call and replays it: "WARP", MJX's default; JAX captures: "JAX"; no capture: "NONE"); a batch in which a world ran
out of capacity is reported, never timed. The benchmark always reports: C is measured first, and a graph mode or batch
that fails (JAX's graph mode died with CUDA_ERROR_NOT_SUPPORTED on an H200) is a row naming its error, as is the
run of both engines at once when no Warp row ran.
"""

from __future__ import annotations

import multiprocessing
import os
import time

import jax
import numpy as np

from benchmarks.bench_sim import _batch, _c_worker, _timed, c_jobs, c_reference
from dynres_jax.config import SceneConfig, SimConfig, replace
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.physics import warp


def warp_engine(cfg: SimConfig, worlds: int, graph_mode: str) -> PileEnv:
    """A warp PileEnv for ``worlds`` worlds whose model captures CUDA graphs the ``graph_mode`` way."""
    from warp import JaxCallableGraphMode

    env = PileEnv(cfg, backend="warp", render=False, worlds=worlds)
    if graph_mode != "NONE":  # the engine's default; replace the model before the first call traces it
        env.physics.mx = warp.put(env.scene.model, env.scene.n_pieces, worlds,
                                  graph_mode=JaxCallableGraphMode[graph_mode])[0]
    return env


def mode_rate(cfg: SimConfig, w: int, mode: str) -> dict:
    """Warp's row at ``w`` worlds in graph mode ``mode``: pushes per second, the first call's extra seconds and the
    worlds that overflowed a capacity."""
    env = warp_engine(cfg, w, mode)
    states, actions = _batch(env, w)
    push = jax.jit(jax.vmap(env.push))
    first, t = _timed(push, states, actions, repeats=1)
    flags = np.asarray(push(states, actions).overflow)
    return dict(graph_mode=mode, worlds=w, pushes_per_s=w / t, seconds=t, compile_s=first - t,
                overflowed_worlds=int((flags != 0).sum()))


def failed(e: Exception) -> str:
    """An error as one line for a row: its type and first line."""
    return f"{type(e).__name__}: {(str(e).strip().splitlines() or [''])[0][:200]}"


def warp_rates(cfg: SimConfig, worlds: list[int], graph_modes: list[str]) -> list[dict]:
    """Every (graph mode, batch) row of ``mode_rate``; one that raises is a row with ``failed`` naming the error."""
    rows = []
    for mode in graph_modes:
        for w in worlds:
            try:
                row = mode_rate(cfg, w, mode)
            except Exception as e:  # noqa: BLE001 (a benchmark row reports any failure of its engine)
                rows.append(dict(graph_mode=mode, worlds=w, failed=failed(e)))
                print(f"  Warp {mode:5s} {w:5d} worlds: failed: {rows[-1]['failed']}", flush=True)
                continue
            rows.append(row)
            print(f"  Warp {mode:5s} {w:5d} worlds: {row['pushes_per_s']:8.1f} pushes/s (first call "
                  f"{row['compile_s'] + row['seconds']:.1f} s, overflowed {row['overflowed_worlds']})", flush=True)
    return rows


def together(cfg: SimConfig, worlds: int, graph_mode: str, seconds: float, cores: int) -> dict:
    """Warp batches on the GPU for ``seconds`` while ``cores`` C worker processes push in the same scene."""
    env = warp_engine(cfg, worlds, graph_mode)
    states, actions = _batch(env, worlds)
    push = jax.jit(jax.vmap(env.push))
    jax.block_until_ready(push(states, actions).pos)  # compiled
    jobs = c_jobs(env, states.qpos[0], states.qvel[0], actions[:cores], seconds)
    with multiprocessing.get_context("spawn").Pool(cores) as pool:
        c_done = pool.map_async(_c_worker, jobs)
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            jax.block_until_ready(push(states, actions).pos)
            n += worlds
        w_rate = n / (time.perf_counter() - t0)
        c_rate = sum(k / t for k, t in c_done.get())
    print(f"  together: Warp {w_rate:.1f} + C ({cores} cores) {c_rate:.1f} = {w_rate + c_rate:.1f} pushes/s",
          flush=True)
    return dict(worlds=worlds, graph_mode=graph_mode, c_cores=cores, warp_pushes_per_s=w_rate,
                c_pushes_per_s=c_rate, pushes_per_s=w_rate + c_rate)


def run(quick: bool = False, kind: str = "coffee", pieces: int = 100, worlds: list[int] | None = None,
        graph_modes: list[str] | None = None, c_seconds: float = 10.0) -> dict:
    """Warp's rows, C's peer, and both at once at Warp's best (batch, graph mode)."""
    warp.check_installed()
    if quick:
        pieces, worlds, c_seconds = 6, [2], 0.5
    worlds = worlds or [1024, 2048, 4096, 8192]
    graph_modes = graph_modes or ["WARP", "JAX", "NONE"]
    cfg = SimConfig(scene=replace(SceneConfig(), kinds=(kind,), pieces=(pieces,)))
    print(f"MuJoCo Warp, {kind} x {pieces}: {cfg.scene}", flush=True)
    c = c_reference(cfg, c_seconds)  # first: the peer is measured whatever Warp does
    rows = warp_rates(cfg, worlds, graph_modes)
    ran = [r for r in rows if "failed" not in r and not r["overflowed_worlds"]]
    best = max(ran, key=lambda r: r["pushes_per_s"]) if ran else None
    both = dict(failed="no Warp row ran") if best is None else None
    if best is not None:
        try:
            both = together(cfg, best["worlds"], best["graph_mode"], c_seconds, max(1, (os.cpu_count() or 2) - 1))
        except Exception as e:  # noqa: BLE001
            both = dict(worlds=best["worlds"], graph_mode=best["graph_mode"], failed=failed(e))
    ratio = (lambda r: None if r is None or "failed" in r else r["pushes_per_s"] / c["pushes_per_s"])
    out = dict(device=jax.devices()[0].device_kind, host_cores=os.cpu_count(), kind=kind, pieces=pieces,
               warp=rows, c_mujoco=c, best=best, together=both, warp_over_c=ratio(best), together_over_c=ratio(both))
    print(f"  Warp / C MuJoCo: {out['warp_over_c']}; both at once / C: {out['together_over_c']}", flush=True)
    return out


def table(result: dict) -> str:
    c = result["c_mujoco"]["pushes_per_s"]
    lines = [f"Device: {result['device']}; host: {result['host_cores']} cores; {result['kind']} x {result['pieces']}, "
             "the default scene, whole pushes.", "",
             "| engine | graph mode | worlds | pushes/s | / C MuJoCo |", "|---|---|---:|---:|---:|"]
    for r in result["warp"]:
        if "failed" in r:
            lines.append(f"| MuJoCo Warp | {r['graph_mode']} | {r['worlds']} | failed: {r['failed']} | - |")
            continue
        flag = f" ({r['overflowed_worlds']} overflowed)" if r["overflowed_worlds"] else ""
        lines.append(f"| MuJoCo Warp | {r['graph_mode']} | {r['worlds']} | {r['pushes_per_s']:,.1f}{flag} | "
                     f"{r['pushes_per_s'] / c:.2f}x |")
    lines.append(f"| C MuJoCo, {result['c_mujoco']['cores']} cores | - | - | {c:,.1f} | 1.00x |")
    b = result["together"]
    if "failed" in b:
        lines.append(f"| Warp + C at once | {b.get('graph_mode', '-')} | {b.get('worlds', '-')} | failed: "
                     f"{b['failed']} | - |")
    else:
        lines.append(f"| Warp + C on {b['c_cores']} cores at once | {b['graph_mode']} | {b['worlds']} | "
                     f"{b['pushes_per_s']:,.1f} ({b['warp_pushes_per_s']:,.1f} + {b['c_pushes_per_s']:,.1f}) | "
                     f"{b['pushes_per_s'] / c:.2f}x |")
    return "\n".join(lines)
