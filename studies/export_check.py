"""Does the exported decision decide what the library decides, on a robot computer without this package?
``python -m studies.export_check --out DIR [--robot-python PY]`` (issue 38, docs/export).

Frames: ``--frames`` piles of the simulator (coffee, each reset from its own key and pushed 0-2 times at random) seen
through a RealSense's profile (``sim.sensor``) by the camera the robot believes in, calibrated from the first frame
(``perception.calibrate``), each with its own goal (a disc or a letter) and key, ω from 8 to 64, with and without a
warm start. The shipped model's decision is exported for that camera (``export.export_checkpoint``, the planner of
``experiments.export``'s defaults) and called on each frame by a separate Python: ``--robot-python`` (a venv where
only ``pip install jax flatbuffers`` ran), or by default this Python in a site of links to exactly what that install
brings (``bare_site``). The library's decision on the same inputs is ``decision.decide_batch`` as the robot loop calls
it. Reports per frame: the push from each and their difference, and whether every output matched bit for bit.
Results: ``DIR/export_check.json`` and ``DIR/export_check.md``.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import re
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax import export
from dynres_jax.config import CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control.budget import bucket_for
from dynres_jax.control.decision import DecisionSpec, batch, decide_batch
from dynres_jax.control.goals import disc_goal, make_goal, text_goal
from dynres_jax.control.planner import planner_config
from dynres_jax.io.files import write_json, write_text
from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics
from dynres_jax.perception import calibrate
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.sensor import SENSORS

ROBOT_SIDE = textwrap.dedent("""
    # The robot computer: the exported file and its inputs, nothing of dynres_jax. argv: file frames.npz out.npz [site]
    import sys, time
    if len(sys.argv) > 4:
        sys.path.insert(0, sys.argv[4])
    import importlib.util
    found = [m for m in ("dynres_jax", "flax", "mujoco", "cv2", "optax") if importlib.util.find_spec(m)]
    assert not found, f"importable here: {found}"
    import jax, numpy as np
    exported = jax.export.deserialize(bytearray(open(sys.argv[1], "rb").read()))
    data = np.load(sys.argv[2])
    names = ("depth", "goal_mask", "key", "omega", "adam_steps", "init", "warm")
    calls, seconds = [], []
    for i in range(len(data["depth"])):
        t0 = time.perf_counter()
        calls.append(jax.block_until_ready(exported.call(*(data[n][i] for n in names))))
        seconds.append(time.perf_counter() - t0)
    np.savez(sys.argv[3], seconds=np.array(seconds), jax_version=np.array(jax.__version__),
             **{k: np.stack([np.asarray(c[k]) for c in calls]) for k in calls[0]})
""")


def bare_site(folder: str) -> list[str]:
    """A site folder holding only what ``pip install jax flatbuffers`` installs (jax's requirements without extras,
    recursively), as links to this environment's copies: not this package, flax, mujoco or OpenCV. Returns the
    distributions' names."""
    todo, names = ["jax", "flatbuffers"], set()
    while todo:
        name = todo.pop()
        if name in names:
            continue
        names.add(name)
        for req in importlib.metadata.requires(name) or []:
            if "extra ==" not in req:
                todo.append(re.match(r"[A-Za-z0-9_.-]+", req).group(0))
    os.makedirs(folder, exist_ok=True)
    for name in names:
        dist = importlib.metadata.distribution(name)
        for top in {str(f).split("/")[0] for f in dist.files if not str(f).startswith("..")}:
            if not os.path.lexists(os.path.join(folder, top)):
                os.symlink(dist.locate_file(top), os.path.join(folder, top))
    return sorted(names)


def run_robot_side(file: str, frames: str, out: str, python: str | None, work: str) -> dict:
    """``ROBOT_SIDE`` on ``file`` and the inputs in ``frames`` (npz of ``export.INPUT_NAMES``) in a separate process:
    ``python`` as it is, or (None) this Python isolated in a ``bare_site``. Returns the outputs (arrays)."""
    script = os.path.join(work, "robot_side.py")
    with open(script, "w") as f:
        f.write(ROBOT_SIDE)
    if python is None:
        command = [sys.executable, "-I", "-S", script, file, frames, out, os.path.join(work, "site")]
        bare_site(command[-1])
    else:
        command = [python, "-I", script, file, frames, out]
    run = subprocess.run(command, capture_output=True, text=True, timeout=1800)
    if run.returncode:
        raise RuntimeError(f"the robot side failed:\n{run.stderr[-3000:]}")
    return dict(np.load(out))


def library_decision(obs, goal, key, omega, steps, init, warm, *, spec, dynamics, camera) -> dict:
    """The library's decision on one frame as the robot loop makes it (``decision.decide_batch`` on a batch of one):
    the outputs the exported file gives too (push, best_cost, objective, positions, mask)."""
    particles, c_now, result = decide_batch(batch(obs), batch(goal), batch(key), jnp.asarray(init)[None], warm,
                                            [omega], [steps], spec=spec, dynamics=dynamics, camera=camera)
    return dict(push=result.best[0, 0], best_cost=result.best_cost[0], objective=c_now[0],
                positions=particles.positions[0], mask=particles.mask[0])


def frames(n: int, seed: int):
    """n simulated frames as a RealSense gives them, the camera calibrated from the first, and each frame's call:
    (camera, [(depth, goal_mask, key, omega, adam_steps, init, warm)], the scene's planner settings)."""
    sim = SimConfig(scene=SceneConfig(kinds=("coffee",), pieces=(300,)), pile=PileConfig(layout="spread"),
                    camera=CameraConfig())
    env, sensor = PileEnv(sim, backend="mujoco"), SENSORS["realsense"]
    rng, seen = np.random.default_rng(seed), []
    for i in range(n):
        key = jax.random.PRNGKey(seed * 1000 + i)
        state = env.reset(key)
        for k in range(i % 3):
            state = env.push(state, env.sample_push(jax.random.fold_in(key, k + 1), state.pos))
        seen.append(sensor.observe(state.obs, jax.random.fold_in(key, 99)))
    camera = calibrate(seen[0], sensor.believed_camera(env.camera), bin_half_width=sim.scene.bin_half_width,
                       wall_height=sim.scene.wall_height)
    calls = []
    for i, obs in enumerate(seen):
        centre = rng.uniform(-0.06, 0.06, 2)
        goal = text_goal(camera, "LSU"[i % 3], centre, 0.12) if i % 4 == 3 else \
            disc_goal(camera, centre, rng.uniform(0.05, 0.09))
        init = rng.uniform(-0.15, 0.15, (planner_config(env).horizon, 4)).astype(np.float32)
        calls.append((np.asarray(obs.depth, np.float32), goal, np.asarray(jax.random.PRNGKey(seed + i)),
                      np.int32([8, 16, 25, 32, 50, 64][i % 6]), np.int32(100 if i % 5 else 40), init,
                      np.bool_(i % 2)))
    return camera, calls, seen, env


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ckpt", default=SHIPPED_DYNAMICS)
    parser.add_argument("--robot-python", default=None,
                        help="the Python of a venv where only 'pip install jax flatbuffers' ran (default: this one, "
                             "isolated in a site of links to exactly that)")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    camera, calls, seen, env = frames(args.frames, args.seed)
    spec = DecisionSpec(bucket_for(64), planner_config(env, samples=50, adam_steps=100), real_depth=True)
    exported, info = export.export_checkpoint(args.ckpt, spec, camera, platforms=("cpu",))
    file = os.path.join(args.out, "decision.jaxexport")
    size = export.save(exported, file, info)
    npz = os.path.join(args.out, "frames.npz")
    np.savez(npz, **{n: np.stack([c[k] for c in calls]) for k, n in enumerate(export.INPUT_NAMES)})
    robot = run_robot_side(file, npz, os.path.join(args.out, "robot_out.npz"), args.robot_python, args.out)

    dynamics, _, _ = load_dynamics("learned", args.ckpt, env.config.scene.plate_half_width)
    rows = []
    for i, (obs, call) in enumerate(zip(seen, calls, strict=True)):
        depth, goal_mask, key, omega, steps, init, warm = call
        t0 = time.perf_counter()
        live = library_decision(obs, make_goal(goal_mask, camera), key, omega, steps, init, warm, spec=spec,
                                dynamics=dynamics, camera=camera)
        seconds = time.perf_counter() - t0
        same = all(np.array_equal(robot[k][i], np.asarray(v)) for k, v in live.items())
        rows.append(dict(frame=i, omega=int(omega), adam_steps=int(steps), warm=bool(warm),
                         push_file=robot["push"][i].tolist(), push_library=np.asarray(live["push"]).tolist(),
                         push_difference_m=float(np.max(np.abs(robot["push"][i] - np.asarray(live["push"])))),
                         bit_for_bit=same, error=int(robot["error"][i]), file_s=float(robot["seconds"][i]),
                         library_s=seconds))
        verdict = "same bits" if same else f"differs by {rows[-1]['push_difference_m']:.2e} m"
        print(f"frame {i}: ω {int(omega)}, push {np.round(robot['push'][i], 4).tolist()}, {verdict}", flush=True)
    summary = dict(frames=len(rows), bit_for_bit=sum(r["bit_for_bit"] for r in rows),
                   max_push_difference_m=max(r["push_difference_m"] for r in rows), file_bytes=size,
                   robot_python=args.robot_python or f"{sys.executable} -I -S in a site of links (bare_site)",
                   robot_jax=str(robot["jax_version"]), library_jax=jax.__version__, checkpoint=info["checkpoint"],
                   planner=info["planner"], capacity=spec.capacity, rows=rows)
    write_json(os.path.join(args.out, "export_check.json"), summary)
    lines = [f"# Exported decision against the library ({len(rows)} frames)", "",
             f"- {summary['bit_for_bit']} of {len(rows)} frames: every output the same bits; largest push difference "
             f"{summary['max_push_difference_m']:.2e} m.",
             f"- Robot side: {summary['robot_python']} (jax {summary['robot_jax']}); file {size / 1e6:.2f} MB.", "",
             "| frame | ω | Adam steps | warm | push (file), m | same bits | file s | library s |",
             "|---:|---:|---:|:--:|---|:--:|---:|---:|"]
    lines += [f"| {r['frame']} | {r['omega']} | {r['adam_steps']} | {'yes' if r['warm'] else 'no'} | "
              f"{', '.join(f'{x:+.4f}' for x in r['push_file'])} | {'yes' if r['bit_for_bit'] else 'no'} | "
              f"{r['file_s']:.2f} | {r['library_s']:.2f} |" for r in rows]
    write_text(os.path.join(args.out, "export_check.md"), "\n".join(lines) + "\n")
    print(f"{summary['bit_for_bit']} / {len(rows)} frames bit for bit; largest push difference "
          f"{summary['max_push_difference_m']:.2e} m")
    return summary


if __name__ == "__main__":
    main()
