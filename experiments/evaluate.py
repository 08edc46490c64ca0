"""``python -m experiments.evaluate``, the command ``dynres_jax.commands.evaluate``."""

from dynres_jax.commands.evaluate import main

if __name__ == "__main__":
    main()
