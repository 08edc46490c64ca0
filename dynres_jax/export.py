"""Deployment: one MPC planning call of a trained model, serialised with ``jax.export`` (StableHLO).

A robot computer with JAX installed (``jax`` and ``jaxlib`` at least as new as the exporting ones; not this
package) loads the file with ``jax.export.deserialize`` and calls it; the model weights, the camera and the
``PlannerConfig`` are constants inside it, the particles, the goal and the PRNG key are inputs, so the goal can
change without exporting again:

    exported = jax.export.deserialize(open("planner.jaxexport", "rb").read())
    out = exported.call(positions, mask, radius, goal_mask, goal_distance, goal_samples, goal_sample_mask, key,
                        init, warm)
    out["best"][0]  # the push to execute: (x_start, y_start, x_end, y_end), metres

Inputs (``INPUT_NAMES`` order; shapes fixed at export, the sidecar ``FILE.json`` lists them):

- positions [n_max, 3] float32 m, world frame: the particles (``perception.Particles.positions``); n_max is the
  model's (its checkpoint card).
- mask [n_max] bool: valid particles (``Particles.mask``; the first ω).
- radius [] float32 m: the FPS covering radius of the ω-sample over the whole point cloud (``Particles.radius``),
  from which the learned dynamics take their resolution code. It is an input, not computed inside, because it
  depends on the point cloud, not only on the particles.
- goal_mask [H, W] bool, goal_distance [H, W] float32 px, goal_samples [Q, 2] float32 px, goal_sample_mask [Q] bool:
  the fields of ``goals.Goal`` (``goals.make_goal(mask, camera, n_samples=Q)``), H x W the camera's image.
- key [2] uint32: ``jax.random.PRNGKey(seed)``'s data (the planner's key, not the perception one).
- init [T, 4] float32 m and warm [] bool: warm start; with warm True, ``init`` (e.g. the previous plan shifted by
  one push) replaces sample 0, as ``planner.plan(init=...)``; with warm False ``init`` is ignored (``plan(init=None)``).

Output: a dict with best [T, 4] float32 m (the lowest-cost push sequence; execute best[0]), best_cost [] float32
(its predicted task objective c, pixels) and history [steps] float32 (the best cost seen up to each Adam step).

Platforms. Exported for one platform (the default: the exporting machine's backend; ``platforms=("cuda",)`` lowers
for a GPU robot on any machine, no GPU needed), the call on the CPU equals ``planner.plan(dynamics(radius),
decision.goal_cost(goal, camera), positions, mask, key, config, init if warm else None)`` with the live model bit for
bit
(tests/test_export.py). One file for several platforms (``platforms=("cpu", "cuda")``) works too, but JAX then wraps
every matrix product, scatter, gather and random-bits call in a per-platform switch, XLA fuses the program
differently and the floats round differently; the Adam refinement amplifies that (on the CPU, 8 sequences x 20 steps
of the shipped model ended with a best push 7.6 cm from the live one; 50 x 100 steps within 4 mm and 0.04 px of
cost): an equally good plan, not the same one. On a GPU nothing repeats bit for bit: scatter-adds there use atomics,
so the live planner itself gives plans a few mm apart from run to run (seen on an H200 with jax 0.11.2: the
cuda-only and the cpu+cuda files and the live planner all spread the same way, cost 13.53-13.66 px on one scene; the
file took 0.04 s a call after an 8-10 s compilation).

Serialisation needs the ``flatbuffers`` package (``jax.export`` imports it to write and read files).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import export as jax_export

from dynres_jax.config import CameraConfig, SceneConfig
from dynres_jax.control.decision import goal_cost
from dynres_jax.control.goals import Goal
from dynres_jax.control.planner import PlannerConfig, plan
from dynres_jax.io import ckpt, files
from dynres_jax.models.graph import no_gpu_kernels
from dynres_jax.models.registry import load_dynamics
from dynres_jax.sim.camera import Camera

FORMAT = "dynres_jax planner, jax.export serialized Exported (StableHLO)"
DEFAULT_GOAL_SAMPLES = 500  # Q: goals.make_goal's default n_samples
INPUT_NAMES = ("positions", "mask", "radius", "goal_mask", "goal_distance", "goal_samples", "goal_sample_mask", "key",
               "init", "warm")
OUTPUT_NAMES = ("best", "best_cost", "history")


def planner_step(dynamics: Callable, camera: Camera, config: PlannerConfig) -> Callable:
    """The pure function that is exported: ``(positions, mask, radius, goal_mask, goal_distance, goal_samples,
    goal_sample_mask, key, init, warm) -> {"best", "best_cost", "history"}`` (module docstring for shapes and units).

    dynamics: radius (m) -> planner dynamics (the first value of ``registry.load_dynamics``, or
    ``registry.learned_dynamics(model)``); its arrays are closed over, so they become constants of the export.
    camera: the camera the goal's pixels belong to (static). config: the planner's settings (static; one particle
    set, so resamples must be 1; the step count is ``config.adam_steps``).
    """
    if config.resamples != 1:
        raise ValueError(f"the exported planner takes one particle set: PlannerConfig.resamples must be 1, got "
                         f"{config.resamples}")

    def step(positions, mask, radius, goal_mask, goal_distance, goal_samples, goal_sample_mask, key, init, warm):
        dyn = dynamics(radius)
        cost = goal_cost(Goal(goal_mask, goal_distance, goal_samples, goal_sample_mask), camera)

        def run(start):
            result = plan(dyn, cost, positions, mask, key, config, start)
            return {"best": result.best, "best_cost": result.best_cost, "history": result.history}

        # Both branches are compiled into the file; only the chosen one runs.
        return jax.lax.cond(jnp.asarray(warm, bool), lambda: run(init), lambda: run(None))

    return step


def input_specs(n_max: int, camera: Camera, config: PlannerConfig, goal_samples: int = DEFAULT_GOAL_SAMPLES):
    """The exported function's inputs: a list of dicts (name, shape, dtype, units, description), INPUT_NAMES order."""
    h, w, t = camera.height, camera.width, config.horizon
    rows = [
        ("positions", (n_max, 3), "float32", "m", "particles, world frame (z up, table at z = 0): "
                                                  "perception.Particles.positions"),
        ("mask", (n_max,), "bool", "", "valid particles (Particles.mask; the first omega)"),
        ("radius", (), "float32", "m", "FPS covering radius of the omega-sample over the point cloud "
                                       "(Particles.radius): sets the learned dynamics' resolution code"),
        ("goal_mask", (h, w), "bool", "", "goal pixels (goals.Goal.mask)"),
        ("goal_distance", (h, w), "float32", "px", "signed distance field, negative inside (goals.Goal.distance)"),
        ("goal_samples", (goal_samples, 2), "float32", "px", "(u, v) FPS samples of the goal pixel centres "
                                                             "(goals.Goal.samples)"),
        ("goal_sample_mask", (goal_samples,), "bool", "", "valid goal samples (goals.Goal.sample_mask)"),
        ("key", (2,), "uint32", "", "planner PRNG key: the data of jax.random.PRNGKey(seed)"),
        ("init", (t, 4), "float32", "m", "warm start (x_start, y_start, x_end, y_end) per push; used when warm"),
        ("warm", (), "bool", "", "True: init replaces sample 0 (planner.plan(init=init)); False: init is ignored"),
    ]
    return [dict(name=n, shape=list(s), dtype=d, units=u, description=e) for n, s, d, u, e in rows]


def output_specs(config: PlannerConfig):
    """The exported function's outputs (a dict of these names): list of dicts like ``input_specs``."""
    rows = [
        ("best", (config.horizon, 4), "float32", "m", "the lowest-cost push sequence (x_start, y_start, x_end, "
                                                      "y_end); execute best[0]"),
        ("best_cost", (), "float32", "px", "its predicted task objective c"),
        ("history", (config.adam_steps,), "float32", "px", "the best cost seen up to each Adam step"),
    ]
    return [dict(name=n, shape=list(s), dtype=d, units=u, description=e) for n, s, d, u, e in rows]


def export_planner(dynamics: Callable, n_max: int, camera: Camera, config: PlannerConfig, *,
                   goal_samples: int = DEFAULT_GOAL_SAMPLES, platforms: Sequence[str] | None = None
                   ) -> jax_export.Exported:
    """``planner_step`` lowered for inputs of ``input_specs`` shapes -> a ``jax.export.Exported``.
    platforms: a subset of "cpu", "cuda", "rocm", "tpu" (default: this machine's backend); one platform reproduces
    the live planner bit for bit (on the CPU), several give one file for all of them whose plans differ by rounding
    (module docstring).
    """
    specs = [jax.ShapeDtypeStruct(tuple(s["shape"]), np.dtype(s["dtype"]))
             for s in input_specs(n_max, camera, config, goal_samples)]
    fn = jax.jit(planner_step(dynamics, camera, config))
    with no_gpu_kernels():  # a file must lower for every platform named, on any machine
        return jax_export.export(fn, platforms=None if platforms is None else tuple(platforms))(*specs)


def export_checkpoint(ckpt_dir: str, config: PlannerConfig | None = None, camera: Camera | None = None, *,
                      goal_samples: int = DEFAULT_GOAL_SAMPLES, platforms: Sequence[str] | None = None,
                      plate_half_width: float = SceneConfig.plate_half_width) -> tuple[jax_export.Exported, dict]:
    """Export the planner of the learned model in ``ckpt_dir`` (``registry.load_dynamics("learned", ...)``) ->
    (Exported, its description for the sidecar: ``describe``). config: default ``PlannerConfig()``; camera: default the
    simulator's (``CameraConfig()``).
    Raises FileNotFoundError (no checkpoint there) or ``ckpt.CheckpointError`` (unreadable)."""
    config = PlannerConfig() if config is None else config
    camera = Camera.top_down(CameraConfig()) if camera is None else camera
    dynamics, n_max, _ = load_dynamics("learned", ckpt_dir, plate_half_width)
    exported = export_planner(dynamics, n_max, camera, config, goal_samples=goal_samples, platforms=platforms)
    info = describe(exported, n_max, camera, config, goal_samples,
                    checkpoint=dict(path=os.path.abspath(ckpt_dir), step=ckpt.latest_step(ckpt_dir)))
    return exported, info


def describe(exported: jax_export.Exported, n_max: int, camera: Camera, config: PlannerConfig,
             goal_samples: int = DEFAULT_GOAL_SAMPLES, checkpoint: dict | None = None) -> dict:
    """The sidecar's content: how to call the file (inputs and outputs with shapes, dtypes, units), the baked-in
    planner config, camera and checkpoint, and the JAX that wrote it."""
    inputs = input_specs(n_max, camera, config, goal_samples)
    got = [(list(a.shape), str(a.dtype)) for a in exported.in_avals]
    if got != [(s["shape"], s["dtype"]) for s in inputs]:  # the sidecar must describe the file, not a guess
        raise AssertionError(f"exported inputs {got} differ from input_specs")
    return dict(
        format=FORMAT,
        call=("exported = jax.export.deserialize(open(FILE, 'rb').read()); out = exported.call(" + ", ".join(
            INPUT_NAMES) + "); out['best'][0] is the push to execute"),
        inputs=inputs, outputs=output_specs(config),
        platforms=list(exported.platforms), jax_version=jax.__version__,
        calling_convention_version=exported.calling_convention_version,
        n_max=n_max, goal_samples=goal_samples,
        planner={k: v for k, v in dataclasses.asdict(config).items() if k != "seed"},  # the key is an input
        camera=json.loads(camera.to_json()), checkpoint=checkpoint,
    )


def _serialization_error(e: ImportError) -> ImportError:
    return ImportError(f"jax.export needs the 'flatbuffers' package to write and read files: pip install flatbuffers "
                       f"({e})")


def save(exported: jax_export.Exported, path: str, info: dict | None = None) -> int:
    """Write the serialised ``exported`` to ``path`` atomically, and ``info`` (``describe``) to ``path + ".json"``;
    returns the file's size in bytes."""
    try:
        data = bytes(exported.serialize())
    except ImportError as e:
        raise _serialization_error(e) from e
    files.atomic_write(path, lambda f: f.write(data))
    if info is not None:
        files.write_json(path + ".json", info)
    return len(data)


def load(path: str) -> jax_export.Exported:
    """An exported planner from ``path`` (``jax.export.deserialize``; needs only JAX); call it with ``.call``."""
    with open(path, "rb") as f:
        data = bytearray(f.read())
    try:
        return jax_export.deserialize(data)
    except ImportError as e:
        raise _serialization_error(e) from e


def call(exported: jax_export.Exported, positions, mask, radius, goal: Goal, key, init=None) -> dict:
    """Convenience for callers that have this package: ``exported.call`` with a ``Goal``, a key (raw uint32[2] or a
    typed key) and an optional warm start (None: no warm start) -> {"best", "best_cost", "history"}."""
    key = jnp.asarray(key)
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    horizon = exported.in_avals[INPUT_NAMES.index("init")].shape[0]
    warm = init is not None
    init = jnp.zeros((horizon, 4), jnp.float32) if init is None else jnp.asarray(init, jnp.float32)
    return exported.call(jnp.asarray(positions, jnp.float32), jnp.asarray(mask, bool), jnp.float32(radius),
                         *goal, key, init, jnp.asarray(warm))


def signature(exported: jax_export.Exported) -> str:
    """A one-line readable signature of an exported planner: ``(name: dtype[shape], ...) -> {...}``."""
    def fmt(a):
        return f"{a.dtype}[{', '.join(map(str, a.shape))}]"

    ins = ", ".join(f"{n}: {fmt(a)}" for n, a in zip(INPUT_NAMES, exported.in_avals, strict=True))
    outs = dict(zip(sorted(OUTPUT_NAMES), exported.out_avals, strict=True))  # a dict's leaves are in key order
    return f"({ins}) -> {{{', '.join(f'{n}: {fmt(outs[n])}' for n in OUTPUT_NAMES)}}}"


__all__ = ["DEFAULT_GOAL_SAMPLES", "FORMAT", "INPUT_NAMES", "OUTPUT_NAMES", "call", "describe",
           "export_checkpoint", "export_planner", "input_specs", "load", "output_specs", "planner_step", "save",
           "signature"]
