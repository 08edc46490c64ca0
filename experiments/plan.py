"""``python -m experiments.plan``, the command ``dynres_jax.commands.plan``."""

from dynres_jax.commands.plan import main

if __name__ == "__main__":
    main()
