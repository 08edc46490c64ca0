"""Deployment: one whole MPC decision of a trained model, serialised with ``jax.export`` (StableHLO).

A robot computer with ``jax`` (jaxlib at least as new as the exporting one) and ``flatbuffers`` (which
``jax.export`` reads its files with), not this package, loads the file and calls it on a depth frame and a goal mask:

    exported = jax.export.deserialize(open("out/decision.jaxexport", "rb").read())
    out = exported.call(depth, goal_mask, key, omega, adam_steps, init, warm)
    out["push"]  # the push to execute: (x_start, y_start, x_end, y_end), metres; NaN unless out["error"] == 0

Everything between the frame and the push runs inside (``decision_step``): the goal's signed distance field and
samples (``goals.goal_fields``), perception h(y, ω) (``perception.perceive``: foreground, farthest point sampling,
re-centring; a real camera's depth by default), the particles' objective c and the shooting planner with the learned
dynamics f(z, u, ω). The model weights, the camera, the particle capacity and the planner settings are constants
inside it; the frame, the goal, ω, the Adam steps and the keys are inputs, so the goal or the resolution can change
without exporting again. Inputs (``INPUT_NAMES`` order; shapes fixed at export, the sidecar ``FILE.json`` lists them):

- depth [H, W] float32 m: the camera's z-depth, H x W its image; 0, NaN, ±inf (or ``sim.sensor.NO_READING``) where it
  gave no reading (``sim.sensor.is_reading``, the rule perception and the robot's loop use); a frame with no reading
  at all is an error.
- goal_mask [H, W] bool: goal pixels (``io.frames.load_goal`` of a goal PNG, ``experiments.goal`` writes them).
- key [2] uint32: ``jax.random.PRNGKey(seed)``'s data; split into perception's and the planner's keys as the closed
  loop splits it (``decision.perceive_and_decide``).
- omega [] int32: the resolution ω, 1 <= ω <= the capacity (the sidecar's ``capacity``).
- adam_steps [] int32: refinement steps, 0 <= steps <= the planner's (an anytime budget).
- init [T, 4] float32 m and warm [] bool: warm start; with warm True, ``init`` (e.g. the previous plan shifted by one
  push) replaces sample 0, as the closed loop's warm start; with warm False ``init`` is ignored.

Outputs (a dict): push [4] and best [T, 4] float32 m (the lowest-cost sequence; NaN when error != 0), best_cost []
(its predicted objective c, px), objective [] (c of the frame's particles now, px), positions [capacity, 3] m and mask
[capacity] bool (the particles), error [] int32 (0: ok; bits of ``ERRORS``) and history [N] (the best cost up to each
Adam step). A file exported with a judge (``export_checkpoint(judge_dir=)``, ``experiments.export --judge``) holds
both models: best and best_cost are then the judge's choice among the planner's refined candidates and its c
(``judge_pick``); the sidecar's ``judge`` names it.

A frame that shows no table where the camera puts it (a depth scaled or shifted, another camera's intrinsics or pose)
sets ``NOT_A_TABLE``, by the rule ``plan`` refuses such frames with (``io.frames.table_fit``); a goal pixel outside
the workspace (an inverted mask, a goal on the walls) sets ``GOAL_OUTSIDE``, as ``plan`` refuses it. The sidecar
records the file's SHA-256 (``sha256``); ``load`` refuses a file that does not match it, and a robot without this
package checks ``hashlib.sha256(open(FILE, "rb").read()).hexdigest()`` against it.

On the CPU the file decides bit for bit what the library's closed loop decides on the same frame, goal and key
(``decision.decide_batch``, as ``control.robot.run_robot`` calls it; tests/test_export.py, in an environment with only
jax and flatbuffers). ``platforms=("cuda",)`` lowers for a GPU robot on any machine. One file for several platforms
(``platforms=("cpu", "cuda")``) works too, but JAX then wraps every matrix product, scatter, gather and random-bits
call in a per-platform switch, XLA fuses the program differently and the floats round differently, which the Adam
refinement amplifies into an equally good plan, not the same one. On a GPU nothing repeats bit for bit: scatter-adds
use atomics, so the live planner itself gives plans a few mm apart from run to run.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import export as jax_export

from dynres_jax.config import CameraConfig, SceneConfig
from dynres_jax.control.decision import DecisionSpec, perceive_and_decide
from dynres_jax.control.goals import goal_fields, table_xy
from dynres_jax.control.judge import judged_costs, lowest_judged
from dynres_jax.control.planner import BAD_START, BAD_STEPS, NOT_FINITE, PlannerConfig
from dynres_jax.io import ckpt, files
from dynres_jax.io.frames import on_a_table, table_fit
from dynres_jax.models.graph import no_gpu_kernels
from dynres_jax.models.registry import load_dynamics
from dynres_jax.perception import BAD_OMEGA, EMPTY_FOREGROUND, NO_DEPTH, TOO_FEW_POINTS, WORKSPACE_HALF_WIDTH
from dynres_jax.sim.camera import Camera, Observation
from dynres_jax.sim.sensor import is_reading

FORMAT = "dynres_jax decision (depth + goal mask -> push), jax.export serialized Exported (StableHLO)"
DEFAULT_GOAL_SAMPLES = 500  # Q: goals.make_goal's default n_samples
GOAL_EMPTY = 16  # error bit: the goal mask has no pixel
GOAL_FULL = 32  # error bit: the goal mask covers the whole image
NOT_A_TABLE = 2048  # error bit: the frame shows no table where the camera puts it (``io.frames.table_fit``)
GOAL_OUTSIDE = 4096  # error bit: a goal pixel lies outside the workspace (``goals.check_within``, as plan refuses it)
ERRORS = {NO_DEPTH: "the depth image has no reading (every pixel 0, NaN, infinite, negative or beyond 100 m: a depth "
                    "in millimetres reads as none; give metres)",
          EMPTY_FOREGROUND: "no foreground: nothing stands above the table inside the workspace",
          BAD_OMEGA: "omega outside [1, capacity]",
          TOO_FEW_POINTS: "fewer foreground points than omega",
          GOAL_EMPTY: "the goal mask has no pixel",
          GOAL_FULL: "the goal mask covers the whole image",
          GOAL_OUTSIDE: f"a goal pixel lies outside the workspace (table square ±{WORKSPACE_HALF_WIDTH:g} m: pieces "
                        "cannot be pushed there; an inverted mask?), as plan refuses it",
          BAD_STEPS: "adam_steps outside [0, the planner's adam_steps]",
          BAD_START: "warm is set and init (the warm start) has NaN or infinite values",
          NOT_A_TABLE: "the frame shows no table where the camera puts it (its median point off the table plane, too "
                       "few flat readings, or a median reading outside a table-top camera's range: depth scaled, or "
                       "another camera's intrinsics or pose), as plan refuses it",
          NOT_FINITE: "the plan is NaN or infinite"}
INPUT_NAMES = ("depth", "goal_mask", "key", "omega", "adam_steps", "init", "warm")
OUTPUT_NAMES = ("push", "best", "best_cost", "objective", "positions", "mask", "error", "history")


def judge_pick(particles, goal, result, judge: Callable, camera: Camera):
    """The judge's choice among one decision's refined candidates (``judge.JudgeKeep``'s, traced): particles and goal
    of one frame, result its ``PlanResult`` -> (best [T, 4] m, NaN when the judge can score no candidate, and its
    judged c [] px). The candidates are the planner's M after its Adam steps and its best, as ``proposals="plans"``."""
    candidates = jnp.concatenate([result.actions, result.best[None]])  # [M + 1, T, 4]
    one = jax.tree.map(lambda x: x[None], (particles, goal))
    pick, cost = lowest_judged(judged_costs(*one, candidates[None], dynamics=judge, camera=camera)[0])
    return jnp.where(jnp.isfinite(cost), candidates[pick], jnp.nan), cost


def decision_step(dynamics: Callable, camera: Camera, spec: DecisionSpec, goal_samples: int = DEFAULT_GOAL_SAMPLES,
                  judge: Callable | None = None) -> Callable:
    """The pure function that is exported: ``(depth, goal_mask, key, omega, adam_steps, init, warm) -> {"push",
    "best", ...}`` (module docstring for shapes and units): ``goals.goal_fields`` of the mask, then
    ``decision.perceive_and_decide`` on the frame, as the closed loop decides.

    dynamics: radius (m) -> planner dynamics (the first value of ``registry.load_dynamics``); its arrays are closed
    over, so they become constants of the export. camera: the camera the frame and goal belong to (static). spec: the
    particle capacity, the planner (one particle set: resamples must be 1) and perception's settings. judge: a second
    model of the same kind that chooses among the planner's refined candidates (``judge_pick``; best and best_cost
    are then its choice and its judged c), or None.
    """
    if spec.planner.resamples != 1:
        raise ValueError(f"the exported decision takes one particle set: PlannerConfig.resamples must be 1, got "
                         f"{spec.planner.resamples}")

    xy = table_xy(camera)  # [H, W, 2]: where each pixel's ray meets the table (NaN: never)
    workspace = jnp.asarray(np.all(np.abs(xy) <= WORKSPACE_HALF_WIDTH, axis=-1))  # NaN is outside

    def step(depth, goal_mask, key, omega, adam_steps, init, warm):
        goal_mask = jnp.asarray(goal_mask, bool)
        goal = goal_fields(goal_mask, camera, goal_samples)
        steps_ok = (adam_steps >= 0) & (adam_steps <= spec.planner.adam_steps)
        adam_steps = jnp.clip(adam_steps, 0, spec.planner.adam_steps).astype(jnp.int32)
        frame = Observation(depth, None, None, None)  # perception reads the depth only
        particles, c_now, result = perceive_and_decide(frame, goal, key, init, warm, omega, adam_steps, spec=spec,
                                                       dynamics=dynamics, camera=camera)
        best, best_cost = (result.best, result.best_cost) if judge is None else judge_pick(
            particles, goal, result, judge, camera)
        init_ok = ~jnp.asarray(warm, bool) | jnp.all(jnp.isfinite(init))
        table_ok = on_a_table(*table_fit(depth, camera)) | ~jnp.any(is_reading(depth))  # none at all: NO_DEPTH
        error = (particles.error | jnp.where(~jnp.any(goal_mask), GOAL_EMPTY, 0) | jnp.where(table_ok, 0, NOT_A_TABLE)
                 | jnp.where(jnp.all(goal_mask), GOAL_FULL, 0) | jnp.where(steps_ok, 0, BAD_STEPS)
                 | jnp.where(init_ok, 0, BAD_START)
                 | jnp.where(jnp.any(goal_mask & ~workspace), GOAL_OUTSIDE, 0)).astype(jnp.int32)
        error = error | jnp.where((error == 0) & ~jnp.all(jnp.isfinite(best)), NOT_FINITE, 0)  # never a NaN push
        best = jnp.where(error == 0, best, jnp.nan)
        return dict(push=best[0], best=best, best_cost=best_cost, objective=c_now.astype(jnp.float32),
                    positions=particles.positions, mask=particles.mask, error=error, history=result.history)

    return step


def input_specs(camera: Camera, config: PlannerConfig):
    """The exported function's inputs: a list of dicts (name, shape, dtype, units, description), INPUT_NAMES order."""
    h, w, t = camera.height, camera.width, config.horizon
    rows = [
        ("depth", (h, w), "float32", "m", "the camera's z-depth; 0 or NaN where it gave no reading"),
        ("goal_mask", (h, w), "bool", "", "goal pixels (a goal PNG read by io.frames.load_goal)"),
        ("key", (2,), "uint32", "", "PRNG key: the data of jax.random.PRNGKey(seed)"),
        ("omega", (), "int32", "particles", "the resolution, 1 <= omega <= capacity"),
        ("adam_steps", (), "int32", "", f"refinement steps, 0 to {config.adam_steps}"),
        ("init", (t, 4), "float32", "m", "warm start (x_start, y_start, x_end, y_end) per push; used when warm"),
        ("warm", (), "bool", "", "True: init replaces sample 0 (the previous plan, shifted); False: init is ignored"),
    ]
    return [dict(name=n, shape=list(s), dtype=d, units=u, description=e) for n, s, d, u, e in rows]


def output_specs(spec: DecisionSpec):
    """The exported function's outputs (a dict of these names): list of dicts like ``input_specs``."""
    t, n = spec.planner.horizon, spec.capacity
    rows = [
        ("push", (4,), "float32", "m", "the push to execute (x_start, y_start, x_end, y_end); NaN unless error == 0"),
        ("best", (t, 4), "float32", "m", "the lowest-cost push sequence; best[0] is push"),
        ("best_cost", (), "float32", "px", "its predicted task objective c (with a judge: the judge's)"),
        ("objective", (), "float32", "px", "c of the frame's particles now"),
        ("positions", (n, 3), "float32", "m", "the particles h(y, omega), zero where masked"),
        ("mask", (n,), "bool", "", "valid particles (the first omega)"),
        ("error", (), "int32", "", "0: ok; else bits of 'errors'"),
        ("history", (spec.planner.adam_steps,), "float32", "px", "the best cost seen up to each Adam step"),
    ]
    return [dict(name=n, shape=list(s), dtype=d, units=u, description=e) for n, s, d, u, e in rows]


def export_decision(dynamics: Callable, camera: Camera, spec: DecisionSpec, *,
                    goal_samples: int = DEFAULT_GOAL_SAMPLES, platforms: Sequence[str] | None = None,
                    judge: Callable | None = None) -> jax_export.Exported:
    """``decision_step`` lowered for inputs of ``input_specs`` shapes -> a ``jax.export.Exported`` (with a judge: both
    models in one file).
    platforms: a subset of "cpu", "cuda", "rocm", "tpu" (default: this machine's backend); one platform reproduces
    the library's decision bit for bit (on the CPU), several give one file for all of them whose plans differ by
    rounding (module docstring)."""
    specs = [jax.ShapeDtypeStruct(tuple(s["shape"]), np.dtype(s["dtype"])) for s in input_specs(camera, spec.planner)]
    fn = jax.jit(decision_step(dynamics, camera, spec, goal_samples, judge))
    with no_gpu_kernels():  # a file must lower for every platform named, on any machine
        return jax_export.export(fn, platforms=None if platforms is None else tuple(platforms))(*specs)


def export_checkpoint(ckpt_dir: str, spec: DecisionSpec, camera: Camera | None = None, *,
                      goal_samples: int = DEFAULT_GOAL_SAMPLES, platforms: Sequence[str] | None = None,
                      plate_half_width: float = SceneConfig.plate_half_width, judge_dir: str | None = None
                      ) -> tuple[jax_export.Exported, dict]:
    """Export the decision of the learned model in ``ckpt_dir`` (``registry.load_dynamics("learned", ...)``), with
    the learned judge in ``judge_dir`` choosing the push where given -> (Exported, its description for the sidecar:
    ``describe``). camera: default the simulator's (``CameraConfig()``). Raises FileNotFoundError (no checkpoint
    there), ``ckpt.CheckpointError`` (unreadable) or ValueError (a capacity above a model's n_max)."""
    camera = Camera.top_down(CameraConfig()) if camera is None else camera
    models = {}
    for role, path in (("checkpoint", ckpt_dir), ("judge", judge_dir)):
        if path is None:
            continue
        dynamics, n_max, _ = load_dynamics("learned", path, plate_half_width)
        if spec.capacity > n_max:
            raise ValueError(f"the capacity {spec.capacity} exceeds the {'judge' if role == 'judge' else 'model'}'s "
                             f"n_max = {n_max}")
        models[role] = dynamics, dict(path=os.path.abspath(path), step=ckpt.latest_step(path), n_max=n_max)
    judge = models.get("judge", (None, None))
    exported = export_decision(models["checkpoint"][0], camera, spec, goal_samples=goal_samples, platforms=platforms,
                               judge=judge[0])
    info = describe(exported, camera, spec, goal_samples, checkpoint=models["checkpoint"][1], judge=judge[1])
    return exported, info


def describe(exported: jax_export.Exported, camera: Camera, spec: DecisionSpec,
             goal_samples: int = DEFAULT_GOAL_SAMPLES, checkpoint: dict | None = None, judge: dict | None = None
             ) -> dict:
    """The sidecar's content: how to call the file (inputs and outputs with shapes, dtypes, units; the error bits),
    the baked-in capacity, perception and planner settings, camera, checkpoint and judge (None: the planner's own
    best is pushed), and the JAX that wrote it."""
    inputs = input_specs(camera, spec.planner)
    got = [(list(a.shape), str(a.dtype)) for a in exported.in_avals]
    if got != [(s["shape"], s["dtype"]) for s in inputs]:  # the sidecar must describe the file, not a guess
        raise AssertionError(f"exported inputs {got} differ from input_specs")
    return dict(
        format=FORMAT,
        call=("exported = jax.export.deserialize(open(FILE, 'rb').read()); out = exported.call(" + ", ".join(
            INPUT_NAMES) + "); execute out['push'] when out['error'] == 0"),
        needs="pip install jax flatbuffers (jaxlib no older than jax_version)",
        inputs=inputs, outputs=output_specs(spec), errors={str(bit): text for bit, text in ERRORS.items()},
        platforms=list(exported.platforms), jax_version=jax.__version__,
        calling_convention_version=exported.calling_convention_version,
        capacity=spec.capacity, goal_samples=goal_samples,
        perception=dict(max_points=spec.max_points, real_depth=spec.real_depth),
        planner={k: v for k, v in dataclasses.asdict(spec.planner).items() if k != "seed"},  # the key is an input
        camera=json.loads(camera.to_json()), checkpoint=checkpoint, judge=judge,
    )


def describe_error(error: int) -> str:
    """A readable list of the problems in an exported decision's ``error`` ('' when 0)."""
    return "; ".join(text for bit, text in ERRORS.items() if int(error) & bit)


def _serialization_error(e: ImportError) -> ImportError:
    return ImportError(f"jax.export needs the 'flatbuffers' package to write and read files: pip install flatbuffers "
                       f"({e})")


def save(exported: jax_export.Exported, path: str, info: dict | None = None) -> int:
    """Write the serialised ``exported`` to ``path`` atomically, and ``info`` (``describe``) with the file's SHA-256
    (``sha256``, what ``load`` checks) to ``path + ".json"``; returns the file's size in bytes."""
    try:
        data = bytes(exported.serialize())
    except ImportError as e:
        raise _serialization_error(e) from e
    files.atomic_write(path, lambda f: f.write(data))
    if info is not None:
        files.write_json(path + ".json", dict(info, sha256=hashlib.sha256(data).hexdigest()))
    return len(data)


def load(path: str) -> jax_export.Exported:
    """An exported decision from ``path`` (``jax.export.deserialize``; needs only JAX); call it with ``.call``. When
    its sidecar (``path + ".json"``) names a SHA-256, the file must match it: ValueError for a damaged or replaced
    file; ValueError too for a file ``jax.export`` cannot read (truncated, or not an export)."""
    with open(path, "rb") as f:
        data = bytearray(f.read())
    sidecar = path + ".json"
    if os.path.isfile(sidecar):
        record = files.read_json(sidecar)
        expected = record.get("sha256") if isinstance(record, dict) else None
        if not isinstance(expected, str):  # a damaged sidecar cannot vouch for the file: say so, do not skip it
            raise ValueError(f"the sidecar {sidecar!r} of {path!r} is damaged (no SHA-256 to check the file by); "
                             "export it again, or remove the sidecar to load the file unchecked")
        if hashlib.sha256(data).hexdigest() != expected:
            raise ValueError(f"{path!r} does not match the SHA-256 its sidecar {sidecar!r} records: the file is "
                             "damaged or another export's; export it again")
    try:
        return jax_export.deserialize(data)
    except ImportError as e:
        raise _serialization_error(e) from e
    except Exception as e:  # a truncated or foreign file fails inside flatbuffers (struct.error, IndexError, ...)
        raise ValueError(f"{path!r} is not a whole exported decision ({type(e).__name__}: {e}); export it again") from e


def call(exported: jax_export.Exported, depth, goal_mask, key, omega: int, adam_steps: int | None = None,
         init=None) -> dict:
    """Convenience for callers that have this package: ``exported.call`` with a key (raw uint32[2] or a typed key),
    adam_steps (None: the planner's) and an optional warm start (None: no warm start)."""
    key = jnp.asarray(key)
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    horizon = exported.in_avals[INPUT_NAMES.index("init")].shape[0]
    if adam_steps is None:
        adam_steps = exported.out_avals[sorted(OUTPUT_NAMES).index("history")].shape[0]  # dict leaves: key order
    for name, value in (("omega", omega), ("adam_steps", adam_steps)):
        if isinstance(value, bool | str) or np.ndim(value) or not float(value).is_integer():
            raise ValueError(f"{name} must be a whole number, got {value!r}")
    warm = init is not None
    init = jnp.zeros((horizon, 4), jnp.float32) if init is None else jnp.asarray(init, jnp.float32)
    return exported.call(jnp.asarray(depth, jnp.float32), jnp.asarray(goal_mask, bool), key, jnp.int32(omega),
                         jnp.int32(adam_steps), init, jnp.asarray(warm))


def signature(exported: jax_export.Exported) -> str:
    """A one-line readable signature of an exported decision: ``(name: dtype[shape], ...) -> {...}``."""
    def fmt(a):
        return f"{a.dtype}[{', '.join(map(str, a.shape))}]"

    ins = ", ".join(f"{n}: {fmt(a)}" for n, a in zip(INPUT_NAMES, exported.in_avals, strict=True))
    outs = dict(zip(sorted(OUTPUT_NAMES), exported.out_avals, strict=True))  # a dict's leaves are in key order
    return f"({ins}) -> {{{', '.join(f'{n}: {fmt(outs[n])}' for n in OUTPUT_NAMES)}}}"


__all__ = ["BAD_START", "BAD_STEPS", "DEFAULT_GOAL_SAMPLES", "ERRORS", "FORMAT", "GOAL_EMPTY", "GOAL_FULL",
           "GOAL_OUTSIDE", "INPUT_NAMES", "NOT_A_TABLE", "NOT_FINITE", "OUTPUT_NAMES", "call", "decision_step",
           "describe", "describe_error", "export_checkpoint", "export_decision", "input_specs", "judge_pick", "load",
           "output_specs", "save", "signature"]
