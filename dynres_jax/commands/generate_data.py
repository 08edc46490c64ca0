"""Generate dynamics training data: episodes of random pushes, written in resumable shards.

    python -m experiments.generate_data --out data/piles --episodes 2000 --pushes 10 --worlds 256
    python -m experiments.generate_data --out data/piles --backend mujoco   # C engine on every host core
    python -m experiments.generate_data --out /tmp/quick --quick          # seconds-scale smoke run

The engine (--backend): "mujoco" (default) runs C MuJoCo worker processes on every host core; "warp" is MuJoCo Warp on
one GPU (the C engine's algorithms: ``pip install "dynres-jax[warp]"``, docs/warp); "mjx-fast" is MJX on the
fast scene (2.8x faster on one H200 than the C workers on its 16 cores, but a model trained on its data does worse in
the C scene: docs/performance.md, "Data from MJX"); "mjx" is MJX on the default scene; "auto" is "mjx-fast" where JAX
has a GPU, "mujoco" elsewhere. Several processes share a run through
jax.distributed: under srun or mpirun nothing more is needed; by hand, start K processes with ``--coordinator
HOST:PORT --num-processes K --process-id I`` (README, "Several GPUs and machines"). Process I makes shards I, I + K,
...; all write into --out.

Every DataConfig field is a flag of the same name (``--two-kinds 0.5``, ``--pieces 40 100``); given flags override
the defaults, or the --quick sizes. Run the same command again after a kill: finished shards are kept, the rest
simulated, and the result is that of an uninterrupted run. Worlds are split over all visible devices.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

from dynres_jax import distributed, progress
from dynres_jax.commands import checks
from dynres_jax.config import SceneConfig
from dynres_jax.io import ckpt
from dynres_jax.learn import data, on_policy
from dynres_jax.sim import engines
from dynres_jax.sim.scene import check_room

TYPES = {int: checks.count(0), float: checks.number()}  # a field's flag type by its default's type


def _add_field_flags(parser: argparse.ArgumentParser) -> list[str]:
    """One flag per scalar or tuple DataConfig field (not ``sim``), typed by its default; returns their names."""
    names = []
    for f in dataclasses.fields(data.DataConfig):
        if f.name == "sim":
            continue
        default = f.default
        flag = "--" + f.name.replace("_", "-")
        help_ = f"DataConfig.{f.name} (default {default!r})"
        if isinstance(default, bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_)
        elif isinstance(default, tuple):
            parser.add_argument(flag, nargs="+", type=TYPES.get(type(default[0]), str), default=None, help=help_)
        elif f.name == "backend":
            parser.add_argument(flag, choices=engines.NAMES, default=None, help=engines.help_text(default))
        else:
            parser.add_argument(flag, type=TYPES.get(type(default), str), default=None, help=help_)
        names.append(f.name)
    return names


@checks.guarded("generate_data")
def main(argv=None) -> dict:
    parser = checks.parser("generate_data", __doc__)
    parser.add_argument("--out", required=True, help="output folder (shards, config.json, summary.json)")
    checks.add_fresh(parser)
    parser.add_argument("--quick", action="store_true",
                        help="tiny sizes (6 coffee beans, 48x48, 2 short pushes, 10 episodes in shards of 4 worlds, "
                             "on mjx unless --backend says otherwise)")
    parser.add_argument("--workers", type=checks.workers(), default=None,
                        help="C engine processes for --backend mujoco (default: every host core)")
    parser.add_argument("--cpu-workers", type=checks.workers(0), default=0,
                        help="C MuJoCo processes filling shards beside --backend warp, whichever engine is free "
                             "(default 0: the engine alone)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    names = _add_field_flags(parser)
    distributed.add_args(parser)
    args = parser.parse_args(argv)
    distributed.from_args(parser, args)
    overrides = {n: tuple(v) if isinstance(v, list) else v for n in names if (v := getattr(args, n)) is not None}
    try:
        config = data.quick_config(**overrides) if args.quick else data.DataConfig(**overrides)
        data.check_devices(config)
        checks.check_workers(parser, args.workers, data.concrete(config).backend)
        data.check_helpers(data.concrete(config), args.cpu_workers)
        for scene in (SceneConfig(kinds=(kind,), pieces=(config.pieces[1],)) for kind in config.kinds):
            check_room(scene)
    except (ValueError, TypeError) as e:
        parser.error(str(e))
    if args.policy is not None and config.planned == 0:
        parser.error("--policy plans the on-policy pushes: it needs --planned above 0")
    if config.planned > 0 and ckpt.latest_step(on_policy.policy_dir(config.policy)) is None:
        parser.error(f"--policy {config.policy}: no checkpoint there (a folder with a finished step, RUN/ckpt)")
    checks.claim(args.out, "generate_data", checks.settings(args), args.fresh)
    progress.start(checks.prog("generate_data"), f"{config.episodes} episodes of {config.pushes} pushes in "
                   f"{config.n_shards} shard(s) on {config.backend}, into {args.out} (finished shards are kept); the "
                   "first shard compiles (minutes on a CPU)")
    summary = data.generate(config, args.out, progress=not args.no_progress, workers=args.workers,
                            cpu_workers=args.cpu_workers)
    print(json.dumps(summary, indent=1, sort_keys=True))
    return summary


if __name__ == "__main__":
    main()
