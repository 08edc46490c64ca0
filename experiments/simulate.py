"""``python -m experiments.simulate``, the command ``dynres_jax.commands.simulate``."""

from dynres_jax.commands.simulate import main

if __name__ == "__main__":
    main()
