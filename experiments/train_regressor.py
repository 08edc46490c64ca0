"""``python -m experiments.train_regressor``, the command ``dynres_jax.commands.train_regressor``."""

from dynres_jax.commands.train_regressor import main

if __name__ == "__main__":
    main()
