"""Benchmark of perception h on whatever device JAX sees.

- FPS: 100 particles from each of 1,024 clouds of 20,000 points at once (``jax.vmap`` of ``perception.fps``).
- The same FPS in NumPy (the usual vectorised loop over picks) on a few clouds, scaled per cloud, and the speed-up.
- The whole h (``sample_particles``, n_max = 100, ω = 50) from 256 x 256 rendered piles, 1,024 observations at once,
  with every pixel a candidate point and with the foreground packed into 8,192 slots.

Times are medians over several runs after a warm-up; compile time is reported separately. ``run(quick=True)`` uses
tiny sizes so it finishes in seconds on a CPU. ``python -m experiments.benchmark perception [--quick]`` prints JSON.

Measured on one H200 (JAX 0.11.2): FPS batch 12.1 ms (compile 0.2 s; NumPy 32.5 ms a cloud, about 2,700 times
slower over the batch); h over 1,024 observations 81.6 ms with every pixel a candidate, 17.3 ms packed into 8,192.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import CameraConfig, SceneConfig, SimConfig
from dynres_jax.perception import fps, sample_particles
from dynres_jax.sim.env import PileEnv

# max_points: foreground slots of the packed-cloud variant of h (a 100-bean pile covers about 5,000 of 65,536 pixels)
FULL = dict(clouds=1024, points=20_000, n=100, numpy_clouds=4, image=256, pieces=100, observations=1024,
            distinct_piles=8, n_max=100, omega=50, max_points=8192, repeats=10)
QUICK = dict(clouds=16, points=2_000, n=20, numpy_clouds=2, image=64, pieces=10, observations=8,
             distinct_piles=2, n_max=16, omega=8, max_points=256, repeats=3)


def _timed(fn, *args, repeats: int) -> dict:
    """Compile ``fn`` for ``args`` (timed), run once to warm up, then time ``repeats`` runs: seconds and ms."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return {"compile_s": round(compile_s, 3), "median_ms": round(1e3 * float(np.median(times)), 3),
            "min_ms": round(1e3 * min(times), 3), "runs": repeats}


def numpy_fps(points: np.ndarray, n: int, start: int) -> np.ndarray:
    """Reference FPS: a running min-distance over the cloud, one vectorised NumPy pass per pick -> indices [n]."""
    min_d2 = np.full(len(points), np.inf, np.float32)
    indices = [start]
    for _ in range(1, n):
        min_d2 = np.minimum(min_d2, np.sum(np.square(points - points[indices[-1]]), axis=1))
        indices.append(int(np.argmax(min_d2)))
    return np.array(indices)


def bench_fps(s: dict) -> tuple[dict, dict]:
    k_pts, k_start = jax.random.split(jax.random.PRNGKey(0))
    scale = jnp.array([0.4, 0.4, 0.02])  # clouds shaped like a pile on the table: 0.4 m square, 2 cm thick
    points = jax.random.uniform(k_pts, (s["clouds"], s["points"], 3)) * scale - scale * jnp.array([0.5, 0.5, 0.0])
    valid = jnp.ones((s["clouds"], s["points"]), bool)
    starts = jax.random.randint(k_start, (s["clouds"],), 0, s["points"])
    n = s["n"]
    batched = jax.vmap(lambda p, v, st: fps(p, v, n, st))
    result = {"clouds": s["clouds"], "points": s["points"], "n": n,
              **_timed(batched, points, valid, starts, repeats=s["repeats"])}

    host_points, host_starts = np.asarray(points[: s["numpy_clouds"]]), np.asarray(starts)
    jax_indices = np.asarray(batched(points, valid, starts)[0])
    times, agree = [], True
    for c in range(s["numpy_clouds"]):
        t0 = time.perf_counter()
        indices = numpy_fps(host_points[c], n, int(host_starts[c]))
        times.append(time.perf_counter() - t0)
        agree &= bool(np.array_equal(indices, jax_indices[c]))
    per_cloud_ms = 1e3 * float(np.median(times))
    numpy = {"clouds_timed": s["numpy_clouds"], "ms_per_cloud": round(per_cloud_ms, 3),
             "batch_ms_scaled": round(per_cloud_ms * s["clouds"], 1),
             "speedup": round(per_cloud_ms * s["clouds"] / result["median_ms"], 1), "same_indices_as_jax": agree}
    return result, numpy


def bench_h(s: dict) -> dict:
    env = PileEnv(SimConfig(scene=SceneConfig(pieces=(s["pieces"],)),
                            camera=CameraConfig(width=s["image"], height=s["image"])), backend="mujoco")
    piles = [env.reset(jax.random.PRNGKey(i)).obs for i in range(s["distinct_piles"])]
    reps = -(-s["observations"] // len(piles))
    obs = jax.tree.map(lambda *x: jnp.concatenate([jnp.stack(x)] * reps)[: s["observations"]], *piles)
    keys = jax.random.split(jax.random.PRNGKey(1), s["observations"])
    foreground = float(np.mean([np.sum(np.asarray(o.piece) >= 0) for o in piles]))
    out = {}
    for name, max_points in (("h", None), ("h_max_points", s["max_points"])):
        h = jax.vmap(lambda o, k, mp=max_points: sample_particles(o, env.camera, s["omega"], k, s["n_max"],
                                                                  max_points=mp))
        errors = int(jnp.count_nonzero(h(obs, keys).error))
        out[name] = {"observations": s["observations"], "image": s["image"], "pieces": s["pieces"],
                     "n_max": s["n_max"], "omega": s["omega"], "max_points": max_points,
                     "mean_foreground_pixels": foreground, "observations_with_errors": errors,
                     **_timed(h, obs, keys, repeats=s["repeats"])}
    return out


def run(quick: bool) -> dict:
    """Run the benchmark (tiny sizes when ``quick``) and return its results as a JSON-ready dict."""
    s = QUICK if quick else FULL
    fps_result, numpy_result = bench_fps(s)
    return {"device": jax.devices()[0].device_kind, "backend": jax.default_backend(), "quick": quick,
            "fps": fps_result, "fps_numpy": numpy_result, **bench_h(s)}

