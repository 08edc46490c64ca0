"""``python -m experiments.eval_dynamics``, the command ``dynres_jax.commands.eval_dynamics``."""

from dynres_jax.commands.eval_dynamics import main

if __name__ == "__main__":
    main()
