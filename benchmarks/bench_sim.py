"""Simulator benchmark: MJX world-steps/s and pushes/s against the number of worlds, and in the same run the C
MuJoCo reference on the same scene, one world per core on every host core (one process per core, and
``mujoco.rollout``'s C thread pool; the faster is the peer).

Steps/s are timed on the first ``steps`` steps of real pushes (plate lowering then moving through the pile);
pushes/s is steps/s divided by the simulator steps of one whole push. Variants in ``full_sweep`` are also timed on
whole pushes at the largest batch, and that figure is the one compared with C MuJoCo (which runs whole pushes).
"""

from __future__ import annotations

import multiprocessing
import os
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dynres_jax.config import SceneConfig, SimConfig, replace
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.physics.c import FULL_STATE, c_rollout

# Scene variants compared (all 100 coffee beans unless --pieces says otherwise).
VARIANTS = {
    "fast": dict(preset="fast"),  # SceneConfig.fast(): CG (8 x 3 line-search steps), frictionless contacts, caps 2N
    "fast-dense": dict(preset="fast", contact_jacobian="dense"),
    "free-CG-3N": dict(joints="free", solver="CG", contact_cap=3.0),  # the plain MJX set-up of DESIGN.md
    "planar-Newton-3N": dict(joints="planar", solver="Newton", contact_cap=3.0),  # the default scene
    "planar-Newton-1.5N": dict(joints="planar", solver="Newton", contact_cap=1.5),
    "planar-Newton-3N-4it": dict(joints="planar", solver="Newton", contact_cap=3.0, solver_iterations=4),
    "planar-CG-3N": dict(joints="planar", solver="CG", contact_cap=3.0),
    "planar-CG-1.5N-yaw": dict(joints="planar", solver="CG", contact_cap=1.5, sphere_yaw=True),
    "planar-Newton-3N-dense": dict(joints="planar", solver="Newton", contact_cap=3.0, contact_jacobian="dense"),
}


def variant(name: str, pieces: int = 100) -> tuple[SimConfig, str]:
    """A variant's SimConfig and PileEnv's contact_jacobian ("sparse" unless the variant says "dense")."""
    overrides = dict(VARIANTS[name])
    jacobian = overrides.pop("contact_jacobian", "sparse")
    base = SceneConfig.fast(pieces=(pieces,)) if overrides.pop("preset", None) == "fast" else SceneConfig(
        pieces=(pieces,))
    return SimConfig(scene=replace(base, **overrides)), jacobian


def _timed(fn, *args, repeats: int):
    """(first call seconds, median of ``repeats`` further calls in seconds)."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return first, float(np.median(times))


def _batch(env: PileEnv, worlds: int, seed: int = 0):
    """Settled piles for ``worlds`` worlds (8 distinct piles, tiled) and one random push each."""
    reset = jax.jit(jax.vmap(env.reset))
    base = reset(jax.random.split(jax.random.PRNGKey(seed), 8))
    states = jax.tree.map(lambda x: jnp.resize(x, (worlds,) + x.shape[1:]), base)
    actions = jax.jit(jax.vmap(env.sample_push))(jax.random.split(jax.random.PRNGKey(seed + 1), worlds), states.pos)
    return states, actions


def mjx_rates(cfg: SimConfig, worlds: list[int], steps: int, repeats: int, whole_push_at: int | None,
              contact_jacobian: str = "sparse") -> dict:
    env = PileEnv(cfg, backend="mjx", render=False, contact_jacobian=contact_jacobian)
    per_push = env.steps_per_push
    rows = []
    for w in worlds:
        states, actions = _batch(env, w)
        plate_pos, plate_quat = jax.vmap(env.plate_trajectory)(actions)
        plate_pos, plate_quat = plate_pos[:, :steps], plate_quat[:, :steps]
        run = jax.jit(jax.vmap(env.simulate))
        first, t = _timed(run, states, plate_pos, plate_quat, repeats=repeats)
        rate = w * steps / t
        rows.append(dict(worlds=w, world_steps_per_s=rate, pushes_per_s=rate / per_push, compile_s=first - t))
        print(f"  MJX {w:5d} worlds: {rate:10.0f} world-steps/s  {rate / per_push:8.1f} pushes/s", flush=True)
    out = dict(steps_per_push=per_push, rows=rows)
    if whole_push_at:
        states, actions = _batch(env, whole_push_at)
        push = jax.jit(jax.vmap(env.push))
        first, t = _timed(push, states, actions, repeats=1)
        out["whole_push"] = dict(worlds=whole_push_at, pushes_per_s=whole_push_at / t, seconds=t)
        print(f"  MJX whole pushes at {whole_push_at} worlds: {whole_push_at / t:.1f} pushes/s", flush=True)
    return out


def compared_rate(mjx: dict) -> dict:
    """The MJX figure compared with C MuJoCo ({"worlds", "pushes_per_s", ...}): whole pushes where timed (C runs
    whole pushes), else the row with the best rate extrapolated from the first steps of pushes."""
    return mjx.get("whole_push") or max(mjx["rows"], key=lambda r: r["pushes_per_s"])


def _c_worker(job) -> tuple[int, float]:
    """One process: rebuild the model from XML and run whole pushes in C for ``seconds``; (pushes, seconds)."""
    xml, state0, plate, seconds = job
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_setState(m, d, state0, FULL_STATE)
    c_rollout(m, d, plate[:1])  # warm-up
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        c_rollout(m, d, plate[n % len(plate)][None])
        n += 1
    return n, time.perf_counter() - t0


def c_jobs(env: PileEnv, qpos, qvel, actions, seconds: float) -> list[tuple]:
    """``_c_worker``'s jobs, one per action [K, 4]: every worker starts from the world (qpos, qvel) of ``env``'s scene
    and cycles through all K pushes' plate trajectories, each worker from a different one."""
    m = env.scene.model
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
    state0 = np.empty(mujoco.mj_stateSize(m, FULL_STATE))
    mujoco.mj_getState(m, d, state0, FULL_STATE)
    pp, pq = jax.vmap(env.plate_trajectory)(jnp.asarray(actions))
    plate = np.concatenate([np.asarray(pp), np.asarray(pq)], axis=2).astype(np.float64)
    return [(env.scene.xml, state0, np.roll(plate, i, 0), seconds) for i in range(len(plate))]


def c_reference(cfg: SimConfig, seconds: float, cores: int | None = None) -> dict:
    """C MuJoCo on whole pushes, one world per core on every core, two ways: one process per core, and one
    ``mujoco.rollout`` call on a pool of C threads. The faster of the two is the peer MJX is compared with."""
    cores = cores or os.cpu_count()
    env = PileEnv(cfg, backend="mujoco", render=False)
    m = env.scene.model
    state = env.reset(jax.random.PRNGKey(0))
    actions = jax.vmap(env.sample_push, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(1), cores), state.pos)
    jobs = c_jobs(env, state.qpos, state.qvel, actions, seconds)
    d, plate = mujoco.MjData(m), jobs[0][2]
    mujoco.mj_setState(m, d, jobs[0][1], FULL_STATE)

    with multiprocessing.get_context("spawn").Pool(cores) as pool:
        done = pool.map(_c_worker, jobs)
    per_process = sum(n / t for n, t in done)

    threads = [mujoco.MjData(m) for _ in range(cores)]
    c_rollout(m, d, plate[:1], threads)  # warm-up
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        c_rollout(m, d, plate, threads)
        n += cores
    per_thread = n / (time.perf_counter() - t0)
    best = max(per_process, per_thread)
    steps = env.steps_per_push
    print(f"  C MuJoCo, {cores} cores: {per_process:8.1f} pushes/s in processes, {per_thread:8.1f} in threads "
          f"({best * steps:,.0f} world-steps/s)", flush=True)
    return dict(cores=cores, pushes_per_s_processes=per_process, pushes_per_s_threads=per_thread,
                pushes_per_s=best, world_steps_per_s=best * steps)


def run(quick: bool = False, pieces: int = 100, variants: list[str] | None = None, worlds: list[int] | None = None,
        full_sweep: list[str] | None = None, c_seconds: float = 5.0, steps: int = 100) -> dict:
    """Benchmark every variant; ``full_sweep`` variants over all ``worlds``, the rest at the largest only."""
    if quick:
        pieces, worlds, steps, c_seconds = 6, [1, 4], 10, 0.5
        variants = variants or ["planar-Newton-3N"]
    variants = variants or list(VARIANTS)
    worlds = worlds or [1, 16, 256, 1024, 4096]
    full_sweep = full_sweep if full_sweep is not None else variants[:1]
    result = dict(device=jax.devices()[0].device_kind, host_cores=os.cpu_count(), pieces=pieces, variants={})
    for name in variants:
        cfg, jacobian = variant(name, pieces)
        print(f"{name}: {cfg.scene}, {jacobian} contact Jacobians", flush=True)
        sizes = worlds if name in full_sweep else worlds[-1:]
        mjx = mjx_rates(cfg, sizes, steps, repeats=2, whole_push_at=sizes[-1] if name in full_sweep else None,
                        contact_jacobian=jacobian)
        c = c_reference(cfg, c_seconds)
        best = compared_rate(mjx)["pushes_per_s"]
        result["variants"][name] = dict(scene=VARIANTS[name], mjx=mjx, c_mujoco=c,
                                        mjx_over_c=best / c["pushes_per_s"])
        print(f"  MJX / C MuJoCo pushes/s: {best / c['pushes_per_s']:.2f}x", flush=True)
    return result
