"""Where an on-policy shard's time goes (``learn.on_policy.planned_episodes``, issue 50 item 3): seconds in each
stage of ``learn.data.simulate_shard`` with ``--planned``, each stage's device work waited for, in rounds of the same
shard (round 1 pays the compiles; later rounds show what a further shard of the same scene costs).

    python scripts/profile_on_policy.py --backend warp --worlds 1024 --pushes 3 --rounds 2 --json FILE
    python scripts/profile_on_policy.py --backend mujoco --worlds 1024 --workers 16 --pushes 3 --json FILE

Stages: ``pool`` (the engine's worlds built), ``masks`` (goal masks on the host), ``goals`` (``make_goals``),
``reset`` and ``push`` (the engine; C workers' pushes include rendering on the device), ``visible`` (each frame's
foreground points), ``decide`` (perception and the plan, batched over the shard's worlds), ``random`` (random pushes),
``record`` (a frame's arrays); ``other`` is the rest of the round (copies to the host, the planned share's draw,
bookkeeping).
With C workers the worlds run in ``--lanes`` threads whose stages overlap, so the stages may add up to more than
the round.
Prints a line a round and writes them to --json.
"""

import argparse
import contextlib
import json
import time
from collections import defaultdict

import jax

from dynres_jax.learn import data, on_policy
from dynres_jax.sim import engines
from dynres_jax.sim import pool as pools
from dynres_jax.sim.pool import process_pool

SECONDS = defaultdict(float)


def timed(name, fn):
    """fn, its seconds (device work waited for) added to SECONDS[name]."""
    def wrapped(*args, **kwargs):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args, **kwargs))
        SECONDS[name] += time.perf_counter() - t0
        return out
    return wrapped


def timed_pool(make_pool):
    def make(*args, **kwargs):
        worlds = timed("pool", make_pool)(*args, **kwargs)
        worlds.reset, worlds.push = timed("reset", worlds.reset), timed("push", worlds.push)
        return worlds
    return make


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", default="warp")
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--pushes", type=int, default=3)
    parser.add_argument("--workers", type=int, default=None, help="C worker processes (backend mujoco)")
    parser.add_argument("--shard", type=int, default=0, help="the shard (its scene; ω = OMEGAS[shard % 3])")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--seed", type=int, default=16)
    parser.add_argument("--lanes", type=int, default=on_policy.HOST_LANES, help="on_policy.HOST_LANES (C workers)")
    parser.add_argument("--slack", type=float, default=on_policy.PLAN_SLACK, help="on_policy.PLAN_SLACK")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    config = data.DataConfig(episodes=args.worlds, pushes=args.pushes, worlds=args.worlds, backend=args.backend,
                             planned=0.5, seed=args.seed)
    on_policy.HOST_LANES, on_policy.PLAN_SLACK = args.lanes, args.slack
    on_policy.episode_goals = timed("masks", on_policy.episode_goals)
    on_policy.make_goals = timed("goals", on_policy.make_goals)
    on_policy.decide_batch = timed("decide", on_policy.decide_batch)
    on_policy._visible_points = timed("visible", on_policy._visible_points)
    on_policy._random_pushes = timed("random", on_policy._random_pushes)
    pools.make_pool = timed_pool(pools.make_pool)
    data.frame_record = timed("record", data.frame_record)
    rows = []
    with (process_pool(args.workers) if engines.uses_workers(config.backend) else contextlib.nullcontext()) as pool:
        for r in range(args.rounds):
            SECONDS.clear()
            t0 = time.perf_counter()
            out = data.simulate_shard(config, args.shard, pool=pool)
            total = time.perf_counter() - t0
            row = dict(round=r + 1, backend=config.backend, worlds=args.worlds, pushes=args.pushes, lanes=args.lanes,
                       slack=args.slack,
                       omega=on_policy.OMEGAS[args.shard % len(on_policy.OMEGAS)], pieces=int(len(out["kind"])),
                       kinds=list(map(str, out["kind_names"])), device=jax.devices()[0].device_kind, total=total,
                       **{k: round(v, 2) for k, v in SECONDS.items()},
                       other=round(total - sum(SECONDS.values()), 2),
                       frames_per_s=round(out["broken"].size / total, 1))
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
