"""``python -m experiments.robot``, the command ``dynres_jax.commands.robot``."""

from dynres_jax.commands.robot import main

if __name__ == "__main__":
    main()
