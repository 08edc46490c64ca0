"""``python -m experiments.train_regressor``: the command ``dynres_jax.commands.train_regressor``, its flags
checked first (``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("train_regressor")

if __name__ == "__main__":
    main()
