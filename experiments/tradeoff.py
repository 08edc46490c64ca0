"""``python -m experiments.tradeoff``, the command ``dynres_jax.commands.tradeoff``."""

from dynres_jax.commands.tradeoff import main

if __name__ == "__main__":
    main()
