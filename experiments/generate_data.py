"""``python -m experiments.generate_data``, the command ``dynres_jax.commands.generate_data``."""

from dynres_jax.commands.generate_data import main

if __name__ == "__main__":
    main()
