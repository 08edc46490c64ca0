"""Does a loss on the ranking itself teach a model to rank the planner's candidates? (issue 48 item 4, a study)

A dynamics checkpoint is fine-tuned on ranking sets (``dynres_jax.learn.ranking``: closed-loop states, each with the
planner's candidates pushed in C MuJoCo) with a listwise loss (ListNet's top-one: the cross-entropy between the
softmax of -c_true / τ and of -c_pred / τ over a state's candidates, τ in pixels) beside the position loss on the same
candidates (the mean distance between predicted and carried particles, weighted by ``--position-weight``, in units of
5 cm). The ranking benchmark's scores on held-out sets before and after say whether it helped; nothing here is in the
core until a study shows it does.

    python -m studies.rank_finetune --train docs/dynamics_scale/sets/gather_mnm.npz \
        --test docs/dynamics_scale/sets/redistribute_jtuly.npz --out runs/rank_finetune --steps 300

Rounds of on-policy candidates (plan with model k, fine-tune model k + 1 on its candidates): scripts/gpu_rank_rounds.sh.
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from dynres_jax.control.objective import objective
from dynres_jax.io import ckpt
from dynres_jax.learn import ranking
from dynres_jax.learn.train import DISTANCE_EPS
from dynres_jax.models.dynamics import LENGTH_SCALE, predict, resolution_code
from dynres_jax.models.registry import SHIPPED_DYNAMICS, build_model, learned_dynamics


def listwise(pred_c, true_c, temperature: float):
    """ListNet's top-one loss of one state: pred_c, true_c [C] (pixels; lower is better) -> []."""
    target = jax.nn.softmax(-true_c / temperature)
    return -jnp.sum(target * jax.nn.log_softmax(-pred_c / temperature))


def state_losses(graphdef, params, state, camera, temperature: float):
    """One state's (listwise loss, position loss in length units): state = (positions [N, 3], mask [N], radius [],
    goal, candidates [C, 4], true_c [C], true_positions [C, N, 3])."""
    positions, mask, radius, goal, candidates, true_c, true_positions = state
    code = resolution_code(radius)
    final = jax.vmap(lambda a: predict(graphdef, params, positions, mask, a, code))(candidates)  # [C, N, 3]
    pred_c = jax.vmap(lambda p: objective(p, mask, goal, camera))(final)
    error = jnp.sqrt(jnp.sum(jnp.square(final - true_positions), -1) + DISTANCE_EPS**2) / LENGTH_SCALE  # [C, N]
    position = jnp.sum(error * mask) / jnp.maximum(jnp.sum(mask) * len(candidates), 1)
    return listwise(pred_c, true_c, temperature), position


def arrays(s: ranking.RankingSet):
    """A set as the tuple ``state_losses`` takes, batched over states (goals rebuilt from their masks)."""
    return (jnp.asarray(s.positions), jnp.asarray(s.mask), jnp.asarray(s.radius), ranking.goals(s),
            jnp.asarray(s.candidates), jnp.asarray(s.true_c), jnp.asarray(s.true_positions))


def finetune(model, train: ranking.RankingSet, *, steps: int, batch: int, lr: float, temperature: float,
             rank_weight: float, position_weight: float, seed: int = 0, log=print):
    """The model fine-tuned on ``train`` (a copy; Adam, ``batch`` states a step drawn uniformly; the loss
    rank_weight x listwise + position_weight x position)."""
    graphdef, params = nnx.split(model)
    data, camera = arrays(train), train.camera
    optimizer = optax.adam(lr)
    opt_state = optimizer.init(params)

    @jax.jit
    def step(params, opt_state, rows):
        def loss(p):
            rank, position = jax.vmap(lambda *x: state_losses(graphdef, p, x, camera, temperature))(
                *jax.tree.map(lambda x: x[rows], data))
            total = rank_weight * jnp.mean(rank) + position_weight * jnp.mean(position)
            return total, (jnp.mean(rank), jnp.mean(position))

        (_, parts), grads = jax.value_and_grad(loss, has_aux=True)(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, parts

    rng = np.random.default_rng(seed)
    for i in range(steps):
        params, opt_state, (rank, position) = step(params, opt_state, rng.integers(0, len(train.group), batch))
        if (i + 1) % max(1, steps // 5) == 0:
            log(f"step {i + 1}: listwise {float(rank):.4f}, position {float(position) * LENGTH_SCALE * 1000:.2f} mm")
    return nnx.merge(graphdef, params)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m studies.rank_finetune", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train", nargs="+", required=True, help="ranking sets to fine-tune on")
    parser.add_argument("--test", nargs="+", required=True, help="ranking sets to score on, before and after")
    parser.add_argument("--ckpt", default=SHIPPED_DYNAMICS)
    parser.add_argument("--out", required=True)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--batch", type=int, default=8, help="states a step (each with all its candidates)")
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--temperature", type=float, default=1.0, help="τ of the listwise loss, pixels")
    parser.add_argument("--rank-weight", type=float, default=1.0, help="0: the position loss alone (the control)")
    parser.add_argument("--position-weight", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", default=None,
                        help="a new folder: the fine-tuned model as a checkpoint (--ckpt's card, plus these settings), "
                             "for evaluate --ckpt or the next round's --policy")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.batch < 1 or not args.lr > 0 or not args.temperature > 0 or min(
            args.rank_weight, args.position_weight) < 0:
        parser.error("--steps and --batch must be >= 1, --lr and --temperature > 0, the weights >= 0")
    if args.save and os.path.exists(args.save):
        parser.error(f"--save {args.save} exists: a fine-tuned checkpoint is written to a new folder")
    train, test = (ranking.concatenate([ranking.load(p) for p in paths]) for paths in (args.train, args.test))
    model, meta, _ = ckpt.load_module(args.ckpt, build_model)
    before = ranking.score_model(test, learned_dynamics(model))
    tuned = finetune(model, train, steps=args.steps, batch=args.batch, lr=args.lr, temperature=args.temperature,
                     rank_weight=args.rank_weight, position_weight=args.position_weight, seed=args.seed)
    after = ranking.score_model(test, learned_dynamics(tuned))
    if args.save:
        ckpt.save_module(args.save, args.steps, tuned, {**meta, "rank_finetune": vars(args)})
    results = {"before": before, "after": after, "settings": {k: v for k, v in vars(args).items()}}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "rank_finetune.json"), "w") as f:
        json.dump(results, f, indent=1)
    ranking.write_table({"before": before, "after": after}, os.path.join(args.out, "rank_finetune.md"))
    print(f"before: {ranking.headline(before)}\nafter: {ranking.headline(after)}")
    return results


if __name__ == "__main__":
    main()
