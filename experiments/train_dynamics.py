"""``python -m experiments.train_dynamics``, the command ``dynres_jax.commands.train_dynamics``."""

from dynres_jax.commands.train_dynamics import main

if __name__ == "__main__":
    main()
