"""Fine-tune a dynamics checkpoint to rank the planner's candidates (issue 48 item 4; the shipped model was made so).

The checkpoint is fine-tuned on ranking sets (``dynres_jax.learn.ranking``: closed-loop states, each with the
planner's candidates pushed in C MuJoCo; ``studies.ranking build --twin-sigma 0`` makes them) with the listwise loss
of ``dynres_jax.learn.rank_loss`` (``--rank-weight``) beside the position loss on the same candidates (the mean
distance between predicted and carried particles, weighted by ``--position-weight``, in units of 5 cm;
``--rank-weight 0``: the position loss alone, the control). The ranking benchmark's scores on held-out sets before
and after are written to OUT; ``--save`` writes the fine-tuned checkpoint (docs/dynamics_scale/rounds.md).

    python -m studies.rank_finetune --train docs/dynamics_scale/sets/gather_mnm.npz \
        --test docs/dynamics_scale/sets/redistribute_jtuly.npz --out runs/rank_finetune --steps 300

Rounds of on-policy candidates (plan with model k, fine-tune model k + 1 on its candidates): the rank_rounds recipe,
python scripts/gpu.py rank_rounds.
"""

from __future__ import annotations

import argparse
import json
import os

from dynres_jax.io import ckpt
from dynres_jax.learn import ranking
from dynres_jax.learn.rank_loss import finetune
from dynres_jax.models.registry import SHIPPED_DYNAMICS, build_model, learned_dynamics


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
        ckpt.save_module(args.save, args.steps, tuned, {**meta, "step": args.steps, "rank_finetune": vars(args)})
    results = {"before": before, "after": after, "settings": vars(args)}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "rank_finetune.json"), "w") as f:
        json.dump(results, f, indent=1)
    ranking.write_table({"before": before, "after": after}, os.path.join(args.out, "rank_finetune.md"))
    print(f"before: {ranking.headline(before)}\nafter: {ranking.headline(after)}")
    return results


if __name__ == "__main__":
    main()
