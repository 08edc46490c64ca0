"""``python -m experiments.sort``, the command ``dynres_jax.commands.sort``."""

from dynres_jax.commands.sort import main

if __name__ == "__main__":
    main()
