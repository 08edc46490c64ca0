"""Redistribute: ``python -m experiments.redistribute --help``; the work is in ``experiments.task``."""

from dynres_jax.commands import checks
from dynres_jax.commands.task import main as run_task


@checks.guarded("redistribute")
def main(argv=None):
    return run_task("redistribute", argv)


if __name__ == "__main__":
    main()
