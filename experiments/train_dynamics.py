"""Train the dynamics model f(z, u, ω) on generated data; resumes from the newest checkpoint in --out.

    python -m experiments.generate_data --out data/piles
    python -m experiments.train_dynamics --data data/piles --out runs/dynamics
"""

from __future__ import annotations

import argparse
import dataclasses
import json

from dynres_jax.train import TrainConfig, train


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m experiments.train_dynamics", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="folder of shards from experiments.generate_data")
    parser.add_argument("--out", required=True, help="run folder: ckpt/, metrics.jsonl, curves.png")
    defaults = TrainConfig()
    for f in dataclasses.fields(TrainConfig):
        if f.name != "model":
            value = getattr(defaults, f.name)
            kind = int if f.name == "max_points" else type(value)
            parser.add_argument("--" + f.name.replace("_", "-"), type=kind, default=value,
                                help=f"TrainConfig.{f.name} (default {value})")
    parser.add_argument("--hidden", type=int, default=defaults.model.hidden, help="model width")
    parser.add_argument("--push-frame", action="store_true", help="DynamicsConfig.push_frame (push-frame inputs)")
    parser.add_argument("--residual", action="store_true", help="DynamicsConfig.residual (correct the sweep)")
    parser.add_argument("--max-minutes", type=float, default=None,
                        help="stop after this much wall time, with a checkpoint (run again to go on)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    fields = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig) if f.name != "model"}
    model = dataclasses.replace(defaults.model, hidden=args.hidden, push_frame=args.push_frame, residual=args.residual)
    cfg = TrainConfig(**fields, model=model)
    print(json.dumps(train(cfg, args.data, args.out, progress=not args.quiet, max_minutes=args.max_minutes)))


if __name__ == "__main__":
    main()
