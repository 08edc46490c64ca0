"""Physics checks at scale: ``python -m studies.validate_physics --pushes 1000 --json FILE``.

For every piece kind, random pushes through random piles (MJX, worlds batched), measuring the issue's physics lines:
- no NaN and no broken world (a piece through the table or out of the bin);
- sinking: how far a piece's centre goes below its rest height (free joints; planar pieces cannot sink);
- in the plate's path: pieces that start ahead of the plate within half a plate half-width of its centre line
  should end at or past the end line (1 cm tolerance);
- overlap: how deep pieces' footprints overlap while the plate presses at the end of its travel (exact for
  spheres); contacts dropped by a contact cap show here;
- outside the swept band: pieces that start more than a plate half-width outside the band swept by the plate
  should move less than 5 mm. In a pile, pieces pushed into their neighbours move those too, so the share of
  out-of-band pieces that moved, and by how much, is reported rather than assumed to be zero;
- into the walls: how far a piece's footprint reaches past a wall while the plate presses and after the push.

``--wall``: every push comes from outside a wall (``sim.pushes.wall_pushes`` through pieces near the walls);
``--layout spread`` spreads the pieces over the bin, walls included. Both count the pieces within 1 cm of a wall
before a push that end more than 2 cm from every wall. ``--backend mujoco`` runs the C engine, one world after
another (no GPU needed).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from dynres_jax.config import DEFAULT_PIECES, KINDS, PileConfig, SceneConfig, SimConfig, replace
from dynres_jax.io.files import write_json
from dynres_jax.sim import pushes
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import per_world


def push_frame(action, pos):
    """Coordinates of points pos [..., 2] in the push frame: (along the push from its start, sideways), metres."""
    start, end = action[:2], action[2:]
    length = jnp.linalg.norm(end - start)
    u = (end - start) / jnp.maximum(length, 1e-9)
    rel = pos - start
    return rel @ u, rel @ jnp.stack([-u[1], u[0]]), length


def push_metrics(env: PileEnv, before, pressing, after, action) -> dict:
    """Per-world physics measurements of one push (pure JAX; vmap it). ``pressing``: the world at the end of the
    plate's travel, plate still down (overlap and sinking are measured there, where the pile is squeezed)."""
    hw, t = env.config.scene.plate_half_width, env.config.scene.plate_thickness
    foot = jnp.asarray(env.scene.footprint)
    along, side, length = push_frame(action, before.pos[:, :2])
    along_after, _, _ = push_frame(action, after.pos[:, :2])
    moved = jnp.linalg.norm(after.pos[:, :2] - before.pos[:, :2], axis=1)
    in_path = (jnp.abs(side) < hw / 2) & (along > t / 2 + foot) & (along < length)
    outside = (jnp.abs(side) > 2 * hw + foot) | (along < -hw - foot) | (along > length + t / 2 + hw + foot)
    followed = along_after >= length - 0.01
    # Overlap of pieces' footprint discs after the push (exact for spheres, a bound for the rest): a contact cap
    # that drops real contacts shows up here.
    p = pressing.pos[:, :2]
    gap = jnp.linalg.norm(p[:, None] - p[None], axis=-1) - (foot[:, None] + foot[None])
    gap = jnp.where(jnp.eye(len(foot), dtype=bool), jnp.inf, gap)
    bin_half = env.config.scene.bin_half_width
    into_wall = lambda s: jnp.max(jnp.abs(s.pos[:, :2]) + foot[:, None] - bin_half)  # noqa: E731
    wall_gap = lambda s: bin_half - jnp.max(jnp.abs(s.pos[:, :2]), axis=1) - foot  # noqa: E731
    return dict(
        into_wall=jnp.maximum(0.0, jnp.maximum(into_wall(pressing), into_wall(after))),
        at_wall=(wall_gap(before) < 0.01).sum(),
        brought_in=((wall_gap(before) < 0.01) & (wall_gap(after) > 0.02)).sum(),
        overlap=jnp.maximum(0.0, -gap.min()),
        broken=after.broken,
        sink=jnp.max(jnp.asarray(env.scene.rest_height) - jnp.minimum(pressing.pos[:, 2], after.pos[:, 2])),
        in_path=in_path.sum(), followed=(in_path & followed).sum(),
        outside=outside.sum(), outside_moved_5mm=(outside & (moved > 0.005)).sum(),
        outside_max_move=jnp.max(jnp.where(outside, moved, 0.0)),
    )


def wall_push(env: PileEnv, key, pos):
    """A random push from outside the wall nearest to a piece near a wall (``sim.pushes``), in the action space."""
    k_piece, k_push = jax.random.split(key)
    point = pushes.pile_points(k_piece, pos, jnp.ones(len(pos), bool), (), env.reach)
    p = env.config.push
    return pushes.project(pushes.wall_pushes(k_push, point, env.reach, p.min_length, p.max_length),
                          env.action_bound, p.min_length, p.max_length, env.reach)


def validate_kind(kind: str, pieces: int, worlds: int, rounds: int, scene_overrides: dict, seed: int = 0,
                  fast: bool = False, wall: bool = False, backend: str = "mjx", layout: str = "blob") -> dict:
    base = (SceneConfig.fast if fast else SceneConfig)(kinds=(kind,), pieces=(pieces,))
    cfg = SimConfig(scene=replace(base, **scene_overrides), pile=PileConfig(layout=layout))
    env = PileEnv(cfg, backend=backend, render=False)
    sample = jax.jit(jax.vmap(functools.partial(wall_push, env) if wall else env.sample_push))
    metrics = jax.jit(jax.vmap(lambda *a: push_metrics(env, *a)))
    travel = env.n_lower + env.n_move

    def one(state, action):
        """One push, stopped once at the end of the plate's travel to measure the squeezed pile."""
        pos, quat = env.plate_trajectory(action)
        pressing = env.simulate(state, pos[:travel], quat[:travel])
        return pressing, env.simulate(pressing, pos[travel:], quat[travel:])

    if backend == "mjx":
        reset, push = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(one))
    else:  # the C engine: one world after another
        reset, push = per_world(env.reset), per_world(one)

    def step(states, actions):
        pressing, after = push(states, actions)
        return after, metrics(states, pressing, after, actions)

    key = jax.random.PRNGKey(seed)
    states = reset(jax.random.split(key, worlds))
    rows = []
    for r in range(rounds):
        actions = sample(jax.random.split(jax.random.fold_in(key, r + 1), worlds), states.pos)
        states, m = step(states, actions)
        rows.append(jax.tree.map(np.asarray, m))
    m = {k: np.concatenate([row[k] for row in rows]) for k in rows[0]}
    return dict(
        kind=kind, scene={k: v for k, v in dataclasses.asdict(cfg.scene).items() if k not in ("kinds", "pieces")},
        pushes=worlds * rounds, broken=int(m["broken"].sum()),
        nan_free=bool(np.all(np.isfinite(m["sink"]))),
        max_sink_mm=float(np.nanmax(m["sink"]) * 1000), in_path=int(m["in_path"].sum()),
        followed_share=float(m["followed"].sum() / max(1, m["in_path"].sum())), outside=int(m["outside"].sum()),
        outside_moved_5mm_share=float(m["outside_moved_5mm"].sum() / max(1, m["outside"].sum())),
        outside_max_move_mm=float(m["outside_max_move"].max() * 1000),
        max_overlap_mm=float(m["overlap"].max() * 1000), p99_overlap_mm=float(np.quantile(m["overlap"], 0.99) * 1000),
        max_into_wall_mm=float(m["into_wall"].max() * 1000), at_wall=int(m["at_wall"].sum()),
        brought_in=int(m["brought_in"].sum()),
    )


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m studies.validate_physics", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pushes", type=int, default=1000, help="pushes per kind")
    parser.add_argument("--worlds", type=int, default=250, help="worlds simulated at once")
    parser.add_argument("--pieces", type=int, help="pieces per pile (default: each kind's config.DEFAULT_PIECES)")
    parser.add_argument("--wall", action="store_true", help="every push from outside a wall")
    parser.add_argument("--layout", choices=["blob", "spread"], default="blob", help="initial piles")
    parser.add_argument("--backend", choices=["mjx", "mujoco"], default="mjx")
    parser.add_argument("--kinds", nargs="*", default=list(KINDS))
    parser.add_argument("--scene", default="default", choices=["default", "fast"],
                        help="SceneConfig() or SceneConfig.fast(); the flags below override either")
    parser.add_argument("--joints", choices=["planar", "free"])
    parser.add_argument("--solver", choices=["Newton", "CG"])
    parser.add_argument("--solver-iterations", type=int)
    parser.add_argument("--ls-iterations", type=int)
    parser.add_argument("--contact-cap", type=float)
    parser.add_argument("--condim", type=int, choices=[1, 3],
                        help="pieces' contacts: 3 with friction, 1 frictionless (a quarter of the constraint rows)")
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    rounds = max(1, -(-args.pushes // args.worlds))
    overrides = {k: v for k, v in dict(joints=args.joints, solver=args.solver, solver_iterations=args.solver_iterations,
                                       ls_iterations=args.ls_iterations, contact_cap=args.contact_cap,
                                       condim=args.condim).items() if v is not None}
    out = dict(device=jax.devices()[0].device_kind, pieces=args.pieces, wall=args.wall, backend=args.backend,
               layout=args.layout, scene=dict(preset=args.scene, **overrides),
               kinds=[])
    for kind in tqdm(args.kinds, desc="kinds"):
        t0 = time.perf_counter()
        res = validate_kind(kind, args.pieces or DEFAULT_PIECES[kind], args.worlds, rounds, overrides,
                            fast=args.scene == "fast", wall=args.wall, backend=args.backend,
                            layout=args.layout)
        res["seconds"] = time.perf_counter() - t0
        tqdm.write(str(res))
        out["kinds"].append(res)
        if args.json:  # after every kind, so a stopped run keeps what it finished
            write_json(args.json, out)
    return out

if __name__ == "__main__":
    main()
