"""The ranking benchmark (``dynres_jax.learn.ranking``): build a set of planning states and candidate pushes once,
then score every model on the same candidates.

    python -m studies.ranking build --out runs/ranking --task gather --kind mnm --episodes 16
    python -m studies.ranking build --out runs/ranking_letters --task redistribute --letters ZRKW --episodes 16
    python -m studies.ranking score --set runs/ranking runs/ranking_letters --ckpt shipped sweep runs/new/ckpt \\
        --out runs/ranking/scores.md

build: ``--episodes`` closed-loop episodes of the task (the shipped model, ω = ``--omega``, the planner's M x N)
run ``--mpc-steps`` steps; at each step of ``--capture`` the world is kept. Each kept state is planned again with
fresh keys and no warm start (the planner's M plans after its Adam steps, and its best: C = M + 1 candidates), and
every candidate's first push is pushed on a copy of the world in C MuJoCo; the particles the planner saw are carried
with their pieces to where the push left them (the true outcome). Written atomically to ``OUT/ranking_set.npz``.

score: each model (a checkpoint folder, ``shipped``, or ``sweep`` for the sweep heuristic) on every set, beside the
physics ceiling (the twin's c as the prediction; left out where a set was built without twins, ``--twin-sigma 0``);
a Markdown table and its JSON.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import DEFAULT_PIECES, PileConfig, SceneConfig, SimConfig
from dynres_jax.control import tasks
from dynres_jax.control.choosers import FixedOmega
from dynres_jax.control.decision import decide_batch, fold
from dynres_jax.control.goals import make_goals
from dynres_jax.control.keep import scorer
from dynres_jax.control.mpc import MPCConfig, run
from dynres_jax.control.objective import objective
from dynres_jax.control.planner import planner_config
from dynres_jax.learn import ranking
from dynres_jax.learn.targets import attach_particles, particle_trajectory
from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics
from dynres_jax.sim.pool import WorldPool, process_pool
from studies.noise_floor import perturb

CAPTURE_FOLD = 1 << 21  # a kept state's re-planning keys fold this + its step into the episode's keys


def carried(states, particles, camera, after):
    """The particles [B, N] of each world carried rigidly with their pieces from states [B] to after [B]: [B, N, 3]."""

    def one(obs_piece, pos, mat, p, m, pos_after, mat_after):
        index, local = attach_particles(p, m, pos, mat, obs_piece, camera)
        return particle_trajectory(index, local, pos_after[None], mat_after[None])[0]

    return jax.vmap(one)(states.obs.piece, states.pos, states.mat, particles.positions, particles.mask, after.pos,
                         after.mat)


def outcome(states, particles, after, goals, camera, c: int):
    """Candidate-major worlds [C * B] before and after their pushes, the particles [C * B] the planner saw and the
    goals [B] -> (the particles carried to where each push left their pieces [B, C, N, 3], their c [B, C])."""
    moved = np.asarray(carried(states, particles, camera, after))
    moved = moved.reshape(c, -1, *moved.shape[1:]).transpose(1, 0, 2, 3)
    mask = np.asarray(particles.mask)[:moved.shape[0]]
    cost = jax.vmap(jax.vmap(lambda p, m, g: objective(p, m, g, camera), (0, None, None)))
    return moved, np.asarray(cost(jnp.asarray(moved), mask, goals))


def build(args) -> ranking.RankingSet:
    pieces = args.pieces or DEFAULT_PIECES[args.kind]
    sim = SimConfig(scene=SceneConfig(kinds=(args.kind,), pieces=(pieces,)),
                    pile=PileConfig(layout=tasks.TASKS[args.task].layout))
    model = load_dynamics("learned", SHIPPED_DYNAMICS if args.policy == "shipped" else args.policy,
                          sim.scene.plate_half_width)
    with process_pool(args.workers) as processes:
        pool = WorldPool(sim, processes)
        camera = pool.camera
        masks = [tasks.episode_goal(args.task, i, args.seed, pool.env, args.letters) for i in range(args.episodes)]
        goals = make_goals(masks, camera)
        piles = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(args.seed), i))(jnp.arange(args.episodes))
        keys = fold(piles, 1)
        cfg = MPCConfig(mpc_steps=max(args.capture) + 1,
                        planner=planner_config(pool.env, samples=args.samples, adam_steps=args.adam_steps))
        kept = {}

        def keep(t, states, particles, record):
            if t in args.capture:
                kept[t] = states

        print(f"closed loop: {args.episodes} episodes of {args.task} ({args.kind}), {cfg.mpc_steps} steps")
        run(pool, pool.reset(piles), FixedOmega(goals, args.omega), model.dynamics, cfg, keys, on_step=[keep])
        score = scorer(camera, tuple(np.asarray(pool.scene.kind).tolist()))
        parts = []
        for t in args.capture:
            t0 = time.perf_counter()
            states, b = kept[t], args.episodes
            omega = np.full(b, args.omega, np.int32)
            particles, _, result = decide_batch(
                states.obs, goals, fold(keys, CAPTURE_FOLD + t), jnp.zeros((b, 1, 4)), False, omega,
                np.full(b, args.adam_steps, np.int32), spec=cfg.spec(64), dynamics=model.dynamics, camera=camera)
            candidates = np.concatenate([np.asarray(result.actions[:, :, 0]), np.asarray(result.best[:, None, 0])], 1)
            c = candidates.shape[1]
            tile = lambda x, c=c: jax.tree.map(lambda y: jnp.concatenate([jnp.asarray(y)] * c), x)  # noqa: E731
            pushes = candidates.transpose(1, 0, 2).reshape(c * b, 4)  # candidate-major: [C * B, ...]
            after = pool.push(tile(states), pushes)
            d = np.asarray(score(after, tile(goals))["distance"]).reshape(c, b).T
            moved, true_c = outcome(tile(states), tile(particles), after, goals, camera, c)
            broken = np.asarray(after.broken).reshape(c, b).T.any(1)
            twin_c = np.full_like(true_c, np.nan)
            if args.twin_sigma > 0:
                twin = pool.push(perturb(tile(states), pool.scene.qpos_adr, args.twin_sigma / 1000,
                                         jax.random.PRNGKey(args.seed * 1000 + t))[0], pushes)
                _, twin_c = outcome(tile(states), tile(particles), twin, goals, camera, c)
                broken |= np.asarray(twin.broken).reshape(c, b).T.any(1)
            ok = ~broken & (np.asarray(particles.error) == 0)
            parts.append(ranking.RankingSet(
                group=np.array([f"{args.task} {args.kind}"] * int(ok.sum())),
                positions=np.asarray(particles.positions)[ok], mask=np.asarray(particles.mask)[ok],
                radius=np.asarray(particles.radius)[ok], goal_mask=np.asarray(masks)[ok],
                candidates=candidates[ok], true_positions=moved[ok], true_c=true_c[ok], true_d=d[ok], twin_c=twin_c[ok],
                sim=sim))
            print(f"step {t}: {int(ok.sum())} of {b} states, {c} candidates each ({time.perf_counter() - t0:.0f} s)")
    return ranking.concatenate(parts)


def score(args) -> dict:
    sets = ranking.concatenate([ranking.load(path) for path in args.set])
    results = {"physics (twin)": ranking.score_ceiling(sets)} if sets.has_twins else {}
    for name in args.ckpt:
        if name == "sweep":
            model = load_dynamics("sweep", None, sets.sim.scene.plate_half_width)
        else:
            model = load_dynamics("learned", SHIPPED_DYNAMICS if name == "shipped" else name,
                                  sets.sim.scene.plate_half_width)
        t0 = time.perf_counter()
        results[name] = ranking.score_model(sets, model.dynamics)
        print(f"{name}: {ranking.headline(results[name])} ({time.perf_counter() - t0:.0f} s)")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    ranking.write_table(results, args.out)
    return results


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="closed-loop states, the planner's candidates, each pushed in C MuJoCo")
    b.add_argument("--out", required=True)
    b.add_argument("--task", choices=sorted(t for t, spec in tasks.TASKS.items() if spec.kinds == 1), default="gather")
    b.add_argument("--kind", default="mnm", choices=sorted(DEFAULT_PIECES))
    b.add_argument("--pieces", type=int, default=None)
    b.add_argument("--letters", default="ZRKW")
    b.add_argument("--episodes", type=int, default=16)
    b.add_argument("--capture", type=int, nargs="+", default=[0, 3, 6, 10, 14])
    b.add_argument("--omega", type=int, default=50)
    b.add_argument("--samples", type=int, default=50)
    b.add_argument("--adam-steps", type=int, default=100)
    b.add_argument("--policy", default="shipped", help="the checkpoint the closed loop and the candidates plan with")
    b.add_argument("--seed", type=int, default=7700)
    b.add_argument("--workers", type=int, default=None)
    b.add_argument("--twin-sigma", type=float, default=1.0,
                   help="mm: each candidate is also pushed on a twin world whose pieces are moved by N(0, σ²) in x and "
                        "y; the twin's ranking of the candidates is the physics ceiling (0: no twin, half the pushes; "
                        "a set to train on)")
    s = sub.add_parser("score", help="models on sets")
    s.add_argument("--set", nargs="+", required=True)
    s.add_argument("--ckpt", nargs="+", default=["shipped", "sweep"])
    s.add_argument("--out", required=True, help="the table (.md; its JSON beside it)")
    args = parser.parse_args(argv)
    if args.command == "build":
        if min(args.capture) < 0 or args.episodes < 1 or not 1 <= args.omega <= 64 or args.twin_sigma < 0:
            parser.error("--capture steps must be >= 0, --episodes >= 1, --omega in [1, 64], --twin-sigma >= 0")
        path = os.path.join(args.out, ranking.SET_FILE)
        if os.path.exists(path):
            parser.error(f"{path} exists: a set is built once (another --out for another)")
        os.makedirs(args.out, exist_ok=True)
        result = build(args)
        ranking.save(path, result)
        print(f"wrote {path}: {len(result.group)} states")
        return result
    return score(args)


if __name__ == "__main__":
    main()
