"""``python -m experiments.gather``, the command ``dynres_jax.commands.gather``."""

from dynres_jax.commands.gather import main

if __name__ == "__main__":
    main()
