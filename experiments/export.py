"""``python -m experiments.export``, the command ``dynres_jax.commands.export``."""

from dynres_jax.commands.export import main

if __name__ == "__main__":
    main()
