"""Where Gather's failing episodes leave their pieces (issue 26): for each kind's evaluate result (METHOD.json with
start_pieces / final_pieces), the pieces outside the goal at the end, how many of them lie within WALL m of a bin wall,
how many never moved from such a start, and how many failing episodes would succeed if the pieces at the walls were
inside. Goals are rebuilt from the evaluation's seed (tasks.episode_goal), so pass the seed it ran with.

    python scripts/kinds_walls.py --seed 1000 mnm=docs/kinds/rerun/mnm/50.json almond=docs/kinds/rerun/almond/50.json
"""

import argparse
import json

import numpy as np

from dynres_jax.config import DEFAULT_PIECES, KINDS, CameraConfig, PileConfig, SceneConfig, SimConfig
from dynres_jax.control.tasks import episode_goal, succeeded
from dynres_jax.sim.env import PileEnv

WALL = 0.02  # m: a piece whose centre is this close to a bin wall counts as at the wall
STILL = 0.002  # m: a piece that moved less than this never moved


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("runs", nargs="+", help="KIND=PATH of an evaluate METHOD.json")
    args = parser.parse_args(argv)
    for run_arg in args.runs:
        kind, path = run_arg.split("=", 1)
        env = PileEnv(SimConfig(scene=SceneConfig(kinds=(kind,), pieces=(DEFAULT_PIECES[kind],)),
                                pile=PileConfig(layout="spread"), camera=CameraConfig()), backend="mujoco")
        with open(path) as f:
            run = json.load(f)
        goals = [episode_goal("gather", i, args.seed, env) for i in range(len(run["final_inside"]))]
        half, height = env.config.scene.bin_half_width, KINDS[kind].size[0]  # a lying piece's centre height (m)
        outside = at_wall = never_moved = fails = saved = 0
        for goal, start, final in zip(goals, np.array(run["start_pieces"]), np.array(run["final_pieces"]), strict=True):
            uv, _ = env.camera.world_to_pixel(np.c_[final, np.full(len(final), height)])
            u, v = np.floor(np.asarray(uv)).astype(int).T
            inside = goal[np.clip(v, 0, goal.shape[0] - 1), np.clip(u, 0, goal.shape[1] - 1)]
            wall = half - np.abs(final).max(axis=1) < WALL
            still = np.linalg.norm(final - start, axis=1) < STILL
            outside += np.sum(~inside)
            at_wall += np.sum(~inside & wall)
            never_moved += np.sum(~inside & wall & still)
            if not succeeded(inside.mean()):
                fails += 1
                saved += bool(succeeded((inside | wall).mean()))
        print(f"{kind}: {outside} pieces outside in {len(goals)} episodes, {at_wall} of them within "
              f"{WALL * 100:.0f} cm of a wall ({never_moved} never moved from there); {fails} episodes fail, {saved} "
              f"of them would succeed with the pieces at the walls inside")


if __name__ == "__main__":
    main()
