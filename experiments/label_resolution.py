"""``python -m experiments.label_resolution``, the command ``dynres_jax.commands.label_resolution``."""

from dynres_jax.commands.label_resolution import main

if __name__ == "__main__":
    main()
