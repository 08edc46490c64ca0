"""Does the robot loop succeed as often as the closed-loop evaluation? ``python -m studies.robot_episodes --out DIR
--evaluate EVAL_DIR`` (issue 38, docs/robot).

Runs ``control.robot.run_robot`` on the simulator as camera and arm (``SimulatedRobot``: a depth camera's profile,
the camera it believes in, calibrated from each episode's first frame) on the Gather episodes of
``experiments.evaluate`` (episode i's pile, goal and planner key from ``tasks.episode_keys`` and
``tasks.episode_goal``, so the two runs pair episode by episode). The robot stops when its own frames show ``--success``
of the foreground inside the goal, or after ``--steps`` pushes; the evaluation always runs every step. Success is
scored as the evaluation scores it, on the true pieces: at least ``tasks.SUCCESS`` of them inside the goal.
``--workers K`` runs K processes (one C world each, the GPU shared); each episode is written to
``DIR/episodes/NNNN.json`` as it ends, and a rerun skips finished episodes. With ``--evaluate`` (an evaluate run of
the same --seed, --kind, --sensor and --episodes), the summary pairs the two: success shares with Wilson intervals,
McNemar's test, Δ final d with a paired-bootstrap interval. Results: ``DIR/robot_episodes.json``, ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import jax
import numpy as np

from dynres_jax.config import DEFAULT_PIECES, KINDS, CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control import tasks
from dynres_jax.control.goals import make_goal
from dynres_jax.control.mpc import MPCConfig
from dynres_jax.control.objective import distribution_distance, inside_share
from dynres_jax.control.planner import planner_config
from dynres_jax.control.robot import STOP_SHARE, SimulatedRobot, Workspace, run_robot
from dynres_jax.io.files import write_json, write_text
from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.sensor import SENSORS
from dynres_jax.stats import mcnemar, paired_bootstrap, wilson


def episode_path(out: str, i: int) -> str:
    return os.path.join(out, "episodes", f"{i:04d}.json")


def run_part(args, part: int, parts: int) -> None:
    """Episodes part, part + parts, ... not yet written."""
    sim = SimConfig(scene=SceneConfig(kinds=(args.kind,), pieces=(DEFAULT_PIECES[args.kind],)),
                    pile=PileConfig(layout="spread"), camera=CameraConfig())
    env = PileEnv(sim, backend="mujoco")
    masks = [tasks.episode_goal("gather", i, args.seed, env) for i in range(args.episodes)]
    piles, planners = tasks.episode_keys(args.seed, np.arange(args.episodes))
    dynamics, _, _ = load_dynamics("learned", args.ckpt, sim.scene.plate_half_width)
    cfg = MPCConfig(mpc_steps=args.steps, real_depth=True,
                    planner=planner_config(env, samples=args.samples, adam_steps=args.adam_steps))
    for i in range(part, args.episodes, parts):
        if os.path.exists(episode_path(args.out, i)):
            continue
        t0 = time.perf_counter()
        robot = SimulatedRobot(env, piles[i], SENSORS[args.sensor])
        start = np.round(np.asarray(robot.state.pos)[:, :2], 5).tolist()  # as evaluate records it
        steps = run_robot(robot, robot, masks[i], dynamics, cfg, args.resolution, planners[i],
                          workspace=Workspace.of(env), success=args.success, log=lambda _: None,
                          bin_size=(sim.scene.bin_half_width, sim.scene.wall_height))
        goal = make_goal(masks[i], env.camera)
        state = robot.state
        inside = float(inside_share(state.pos, np.ones(len(state.pos), bool), goal, env.camera))
        write_json(episode_path(args.out, i), dict(
            episode=i, start_pieces=start, pushes=sum("action" in s for s in steps), seen_inside=steps[-1]["inside"],
            final_inside=inside, final_distance=float(distribution_distance(state.obs, goal, env.camera)),
            success=bool(tasks.succeeded(inside)), stopped_at_goal=steps[-1]["inside"] >= args.success,
            seconds=time.perf_counter() - t0, steps=steps))
        print(f"episode {i}: {inside:.0%} inside after {sum('action' in s for s in steps)} pushes", flush=True)


def evaluate_episodes(folder: str, method: str) -> dict:
    """An evaluate run's final inside share, d and start pieces per episode for ``method``."""
    with open(os.path.join(folder, f"{method}.json")) as f:
        result = json.load(f)
    return dict(inside=np.asarray(result["final_inside"]), distance=np.asarray(result["final_distance"]),
                start=result["start_pieces"])


def summarise(args) -> dict:
    rows = []
    for i in range(args.episodes):
        with open(episode_path(args.out, i)) as f:
            rows.append(json.load(f))
    success = np.array([r["success"] for r in rows])
    summary = dict(episodes=len(rows), kind=args.kind, sensor=args.sensor, seed=args.seed, omega=args.resolution,
                   steps=args.steps, success_share=float(success.mean()),
                   success_ci95=wilson(int(success.sum()), len(rows)),
                   final_inside=float(np.mean([r["final_inside"] for r in rows])),
                   final_distance=float(np.mean([r["final_distance"] for r in rows])),
                   pushes=float(np.mean([r["pushes"] for r in rows])),
                   stopped_at_goal=int(sum(r["stopped_at_goal"] for r in rows)), device=jax.devices()[0].device_kind)
    lines = [f"# Robot loop on the simulator ({args.kind}, {args.sensor} camera, ω = {args.resolution}, "
             f"{len(rows)} Gather episodes, seed {args.seed})", "",
             f"- Robot loop: {summary['success_share']:.0%} succeeded (Wilson 95 % {summary['success_ci95'][0]:.0%}-"
             f"{summary['success_ci95'][1]:.0%}); final d {summary['final_distance']:.2f} px; "
             f"{summary['pushes']:.1f} pushes on average; {summary['stopped_at_goal']} stopped when their frames "
             f"showed {args.success:.0%} inside."]
    if args.evaluate:
        ev = evaluate_episodes(args.evaluate, str(args.resolution))
        starts = [r["start_pieces"] for r in rows]
        if len(ev["inside"]) != len(rows) or starts != ev["start"]:
            raise SystemExit("--evaluate ran other episodes (their count or piles differ): give it this run's --seed, "
                             "--kind and --episodes")
        ev_success = tasks.succeeded(ev["inside"])
        delta = paired_bootstrap(np.array([r["final_distance"] for r in rows]), ev["distance"])
        summary["evaluate"] = dict(success_share=float(ev_success.mean()),
                                   success_ci95=wilson(int(ev_success.sum()), len(rows)),
                                   final_distance=float(ev["distance"].mean()), folder=args.evaluate,
                                   success=mcnemar(success, ev_success), delta_distance=delta)
        e = summary["evaluate"]
        lines.append(f"- `evaluate --sensor {args.sensor}` on the same episodes: {e['success_share']:.0%} "
                     f"({e['success_ci95'][0]:.0%}-{e['success_ci95'][1]:.0%}); final d {e['final_distance']:.2f} px. "
                     f"Successes only in the robot loop {e['success']['first_only']}, only in the evaluation "
                     f"{e['success']['second_only']} (McNemar p = {e['success']['p']:.3f}); Δ final d (robot - "
                     f"evaluation) {delta['mean']:+.2f} [{delta['ci95'][0]:+.2f}, {delta['ci95'][1]:+.2f}] px.")
    write_json(os.path.join(args.out, "robot_episodes.json"), dict(summary, rows=rows))
    write_text(os.path.join(args.out, "robot_episodes.md"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    return summary


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kind", default="coffee", choices=sorted(KINDS))
    parser.add_argument("--sensor", default="realsense", choices=sorted(k for k in SENSORS if k != "none"))
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--success", type=float, default=STOP_SHARE, help="the robot stops at this share seen inside")
    parser.add_argument("--resolution", type=int, default=50)
    parser.add_argument("--samples", type=int, default=50)
    parser.add_argument("--adam-steps", type=int, default=100)
    parser.add_argument("--ckpt", default=SHIPPED_DYNAMICS)
    parser.add_argument("--evaluate", default=None, help="an evaluate run of the same episodes to pair with")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--part", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    os.makedirs(os.path.join(args.out, "episodes"), exist_ok=True)
    if args.part is not None:
        return run_part(args, args.part, args.workers)
    if args.workers == 1:
        run_part(args, 0, 1)
    else:
        env = dict(os.environ, XLA_PYTHON_CLIENT_MEM_FRACTION=f"{0.8 / args.workers:.3f}")
        argv = sys.argv[1:] if argv is None else list(argv)
        procs = [subprocess.Popen([sys.executable, "-m", "studies.robot_episodes", *argv, "--part", str(p)], env=env)
                 for p in range(args.workers)]
        if any(p.wait() for p in procs):
            raise SystemExit("a worker failed; rerun to finish the episodes left")
    return summarise(args)


if __name__ == "__main__":
    main()
