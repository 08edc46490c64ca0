"""Train the dynamics model f(z, u, ω) on generated data; resumes from the newest checkpoint in --out.

    python -m experiments.generate_data --out data/piles
    python -m experiments.train_dynamics --data data/piles --out runs/dynamics --recipe shipped
    python -m experiments.train_dynamics --data data/piles --out runs/cnn_dynamics --recipe cnn   # the CNN baseline
    python -m experiments.train_dynamics --data data/piles --out runs/mine --residual --push-frame --steps 5000

Data-parallel: each batch is split over every device of every process (jax.distributed: under srun or mpirun nothing
more is needed; by hand --coordinator, --num-processes, --process-id); --batch must divide by the device count.

--recipe NAME starts from a named config (``train.RECIPES``: "shipped", the shipped model's; "cnn", the CNN
baseline's; "quick", seconds on a CPU for ``generate_data --quick``'s data); flags given beside it override its values.

--model gnn (default): the graph network (``dynres_jax.models.dynamics``; --processor propnet or gns, --hidden,
--propagation-steps, --push-frame, --world-edges, --bin-position, --residual). --model cnn: the
CNN baseline (``dynres_jax.models.cnn_dynamics``; --grid, --channels, and --no-residual to predict whole displacements
instead of correcting the sweep heuristic). --loss mse (default) or distance: the training loss
(``TrainConfig.loss``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os

import numpy as np

from dynres_jax import distributed
from dynres_jax.commands import checks
from dynres_jax.errors import InputError
from dynres_jax.io.shards import iter_shards
from dynres_jax.learn.targets import is_validation
from dynres_jax.learn.train import RECIPES, SCHEDULE, TrainConfig, train
from dynres_jax.models.cnn_dynamics import CNNDynamicsConfig
from dynres_jax.models.dynamics import PROCESSORS, DynamicsConfig
from dynres_jax.models.registry import MODEL_CLASSES, model_class

GNN_ONLY = ("hidden", "propagation_steps", "push_frame", "world_edges", "bin_position", "processor")
CNN_ONLY = ("grid", "channels")


def build_parser(argv=None):
    """``train_dynamics``'s flags, their defaults the --recipe's in argv (if any). Returns (parser, the recipe's
    TrainConfig or the default one)."""
    parser = checks.parser("train_dynamics", __doc__)
    recipe = checks.Parser(prog=parser.prog, add_help=False)
    recipe.add_argument("--recipe", choices=sorted(RECIPES), default=None,
                        help="start from a named config (train.RECIPES); other flags override it")
    start = recipe.parse_known_args(argv)[0].recipe
    base = RECIPES[start] if start else TrainConfig()
    parser.add_argument("--recipe", choices=sorted(RECIPES), default=None,
                        help="start from a named config (train.RECIPES); other flags override it")
    parser.add_argument("--data", required=True, nargs="+",
                        help="folder(s) of shards from experiments.generate_data (several: one data set)")
    parser.add_argument("--out", required=True, help="run folder: ckpt/, metrics.jsonl, curves.png")
    checks.add_fresh(parser)
    for f in dataclasses.fields(TrainConfig):
        if f.name not in ("model", "held_out_kinds"):
            value = getattr(base, f.name)
            flag, help_ = "--" + f.name.replace("_", "-"), f"TrainConfig.{f.name} (default {value})"
            if isinstance(value, bool):
                parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=value, help=help_)
            else:
                kind = {int: checks.count(0), float: checks.number()}.get(type(value), type(value))
                parser.add_argument(flag, type=checks.count(1) if f.name == "max_points" else kind, default=value,
                                    help=help_)
    parser.add_argument("--held-out-kinds", nargs="+", default=base.held_out_kinds, metavar="KIND",
                        help="TrainConfig.held_out_kinds: piece kinds never trained on (eval_dynamics reports them)")
    parser.add_argument("--model", default=model_class(base.model), choices=list(MODEL_CLASSES),
                        help="gnn (PropNet) or cnn (baseline)")
    parser.add_argument("--hidden", type=checks.count(1), default=None,
                        help=f"gnn: width (default {DynamicsConfig.hidden})")
    parser.add_argument("--propagation-steps", type=checks.count(1), default=None,
                        help=f"gnn: message-passing rounds (default {DynamicsConfig.propagation_steps})")
    parser.add_argument("--push-frame", action=argparse.BooleanOptionalAction, default=None,
                        help="gnn: DynamicsConfig.push_frame (push-frame inputs; default on)")
    parser.add_argument("--world-edges", action=argparse.BooleanOptionalAction, default=None,
                        help="gnn: DynamicsConfig.world_edges (with --push-frame: edges stay in the world frame, so "
                             "the planner builds their codes once per plan; default on)")
    parser.add_argument("--bin-position", action=argparse.BooleanOptionalAction, default=None,
                        help="gnn: DynamicsConfig.bin_position (node inputs say where in the bin a particle is; "
                             "default on)")
    parser.add_argument("--processor", choices=PROCESSORS, default=None,
                        help="gnn: propnet (the reference's propagation; default) or gns (encode-process-decode "
                             "with unshared 2-layer MLPs, LayerNorm and residuals: models/dynamics.py)")
    parser.add_argument("--residual", action=argparse.BooleanOptionalAction, default=None,
                        help="correct the sweep heuristic (default on; all four off: the paper's architecture)")
    parser.add_argument("--grid", type=checks.count(2), default=None,
                        help=f"cnn: cells per side (default {CNNDynamicsConfig.grid})")
    parser.add_argument("--channels", type=checks.count(1), default=None,
                        help=f"cnn: convolution width (default {CNNDynamicsConfig.channels})")
    parser.add_argument("--max-minutes", type=checks.positive, default=None,
                        help="stop after this much wall time, with a checkpoint (run again to go on)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    distributed.add_args(parser)
    return parser, base


@checks.guarded("train_dynamics")
def main(argv=None):
    parser, base = build_parser(argv)
    args = parser.parse_args(argv)
    distributed.from_args(parser, args)
    fields = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig) if f.name != "model"}
    fields["held_out_kinds"] = tuple(args.held_out_kinds)
    wrong = [name for name in (CNN_ONLY if args.model == "gnn" else GNN_ONLY) if getattr(args, name) is not None]
    if wrong:
        parser.error(f"--{', --'.join(n.replace('_', '-') for n in wrong)} do not apply to --model {args.model}")
    options = {name: getattr(args, name) for name in (*GNN_ONLY, *CNN_ONLY, "residual")
               if getattr(args, name) is not None}
    if model_class(base.model) == args.model:  # the recipe's model, with the flags given beside it
        options = {**dataclasses.asdict(base.model), **options}
    try:
        cfg = TrainConfig(**fields, model=MODEL_CLASSES[args.model][0](**options))
        distributed.check_batch(cfg.batch, distributed.batch_mesh())
    except (ValueError, TypeError) as e:
        parser.error(str(e))
    absolute = [os.path.realpath(f) for f in args.data]  # a link to a folder named beside it is the same data
    twice = sorted({f for f, a in zip(args.data, absolute, strict=True) if absolute.count(a) > 1})
    if twice:
        parser.error(f"--data names {', '.join(twice)} twice: its episodes would count twice")
    for folder in args.data:
        check_data(folder, cfg)
    checks.claim(args.out, "train_dynamics", checks.settings(args, ignore=(*SCHEDULE, "max_minutes")), args.fresh,
                 {"--data": args.data})
    print(f"train_dynamics: {args.model} on {', '.join(args.data)}, {cfg.steps} steps of batch {cfg.batch}; "
          f"checkpoints and metrics.jsonl in {args.out}", flush=True)
    print(json.dumps(train(cfg, args.data, args.out, progress=not args.quiet, max_minutes=args.max_minutes)))


def check_data(folder: str, cfg: TrainConfig) -> None:
    """InputError naming --data unless it is a finished data set (every shard there and readable) whose episodes are
    long enough for ``cfg.horizon``; reads no images."""
    if not os.path.isdir(folder):
        raise InputError(f"--data {folder!r}: no such folder")
    episodes = []
    for _, shard in iter_shards(folder, members=("action", "episode")):
        if shard["action"].shape[1] < cfg.horizon:
            raise InputError(f"--data {folder}: its episodes have {shard['action'].shape[1]} pushes, fewer than "
                             f"--horizon {cfg.horizon} (make data with --pushes {cfg.horizon} or more; for "
                             "generate_data --quick's data: --recipe quick)")
        episodes.append(shard["episode"])
    if not is_validation(np.concatenate(episodes)).any():
        raise InputError(f"--data {folder}: its {sum(map(len, episodes))} episodes leave none for validation (every "
                         "10th episode is held out): make at least 10")


if __name__ == "__main__":
    main()
