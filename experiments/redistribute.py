"""``python -m experiments.redistribute``, the command ``dynres_jax.commands.redistribute``."""

from dynres_jax.commands.redistribute import main

if __name__ == "__main__":
    main()
