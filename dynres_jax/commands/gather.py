"""Gather: ``python -m experiments.gather --help``; the work is in ``experiments.task``."""

from dynres_jax.commands import checks
from dynres_jax.commands.task import main as run_task


@checks.guarded("gather")
def main(argv=None):
    return run_task("gather", argv)


if __name__ == "__main__":
    main()
