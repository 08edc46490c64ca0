"""Train the dynamics model f(z, u, ω) on generated data; resumes from the newest checkpoint in --out.

    python -m experiments.generate_data --out data/piles
    python -m experiments.train_dynamics --data data/piles --out runs/dynamics --residual --push-frame
    python -m experiments.train_dynamics --data data/piles --out runs/cnn_dynamics --model cnn   # the CNN baseline

--model gnn (default): the PropNet GNN (``dynres_jax.models.dynamics``; --hidden, --propagation-steps, --push-frame,
--world-edges, --bin-position, --height, --global-context, --radius-scale, --substeps, --residual). --model cnn: the
CNN baseline (``dynres_jax.models.cnn_dynamics``; --grid, --channels, and --no-residual to predict whole displacements
instead of correcting the sweep heuristic). --loss mse (default) or distance: the training loss
(``TrainConfig.loss``). --state pieces trains on the full state instead of particles (``TrainConfig.state``).
--substeps S --sub-targets trains each of the S passes on its own sub-push, from data generated with --substeps S
(``TrainConfig.sub_targets``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json

from dynres_jax.learn.train import TrainConfig, train
from dynres_jax.models.cnn_dynamics import CNNDynamicsConfig
from dynres_jax.models.dynamics import DynamicsConfig
from dynres_jax.models.registry import MODEL_CLASSES

GNN_ONLY = ("hidden", "propagation_steps", "push_frame", "world_edges", "bin_position", "height", "global_context",
            "radius_scale", "substeps")
CNN_ONLY = ("grid", "channels")


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m experiments.train_dynamics", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="folder of shards from experiments.generate_data")
    parser.add_argument("--out", required=True, help="run folder: ckpt/, metrics.jsonl, curves.png")
    defaults = TrainConfig()
    for f in dataclasses.fields(TrainConfig):
        if f.name not in ("model", "held_out_kinds"):
            value = getattr(defaults, f.name)
            flag, help_ = "--" + f.name.replace("_", "-"), f"TrainConfig.{f.name} (default {value})"
            if isinstance(value, bool):
                parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=value, help=help_)
            else:
                parser.add_argument(flag, type=int if f.name == "max_points" else type(value), default=value,
                                    help=help_)
    parser.add_argument("--held-out-kinds", nargs="+", default=(), metavar="KIND",
                        help="TrainConfig.held_out_kinds: piece kinds never trained on (eval_dynamics reports them)")
    parser.add_argument("--model", default="gnn", choices=list(MODEL_CLASSES), help="gnn (PropNet) or cnn (baseline)")
    parser.add_argument("--hidden", type=int, default=None, help=f"gnn: width (default {DynamicsConfig.hidden})")
    parser.add_argument("--propagation-steps", type=int, default=None,
                        help=f"gnn: message-passing steps (DynamicsConfig.steps, default {DynamicsConfig.steps})")
    parser.add_argument("--push-frame", action="store_true", default=None,
                        help="gnn: DynamicsConfig.push_frame (push-frame inputs)")
    parser.add_argument("--world-edges", action="store_true", default=None,
                        help="gnn: DynamicsConfig.world_edges (with --push-frame: edges stay in the world frame, so "
                             "the planner builds their codes once per plan)")
    parser.add_argument("--bin-position", action="store_true", default=None,
                        help="gnn: DynamicsConfig.bin_position (node inputs say where in the bin a particle is)")
    parser.add_argument("--height", action="store_true", default=None,
                        help="gnn: DynamicsConfig.height (node inputs say how high above the table a particle is)")
    parser.add_argument("--global-context", action="store_true", default=None,
                        help="gnn: DynamicsConfig.global_context (every node update sees the pile's pooled state)")
    parser.add_argument("--radius-scale", type=float, default=None,
                        help="gnn: DynamicsConfig.radius_scale (edges reach max(edge radius, this x FPS radius))")
    parser.add_argument("--substeps", type=int, default=None,
                        help="gnn: DynamicsConfig.substeps (a push predicted as this many sub-pushes)")
    parser.add_argument("--residual", action=argparse.BooleanOptionalAction, default=None,
                        help="correct the sweep heuristic (default: off for gnn, on for cnn)")
    parser.add_argument("--grid", type=int, default=None,
                        help=f"cnn: cells per side (default {CNNDynamicsConfig.grid})")
    parser.add_argument("--channels", type=int, default=None,
                        help=f"cnn: convolution width (default {CNNDynamicsConfig.channels})")
    parser.add_argument("--max-minutes", type=float, default=None,
                        help="stop after this much wall time, with a checkpoint (run again to go on)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    fields = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig) if f.name != "model"}
    fields["held_out_kinds"] = tuple(args.held_out_kinds)
    wrong = [name for name in (CNN_ONLY if args.model == "gnn" else GNN_ONLY) if getattr(args, name) is not None]
    if wrong:
        parser.error(f"--{', --'.join(n.replace('_', '-') for n in wrong)} do not apply to --model {args.model}")
    options = {name: getattr(args, name) for name in (*GNN_ONLY, *CNN_ONLY, "residual")
               if getattr(args, name) is not None}
    if "propagation_steps" in options:
        options["steps"] = options.pop("propagation_steps")
    try:
        cfg = TrainConfig(**fields, model=MODEL_CLASSES[args.model][0](**options))
    except ValueError as e:
        parser.error(str(e))
    print(json.dumps(train(cfg, args.data, args.out, progress=not args.quiet, max_minutes=args.max_minutes)))


if __name__ == "__main__":
    main()
