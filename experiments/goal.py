"""``python -m experiments.goal``, the command ``dynres_jax.commands.goal``."""

from dynres_jax.commands.goal import main

if __name__ == "__main__":
    main()
