"""``python -m experiments.simulate``: the command ``dynres_jax.commands.simulate``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("simulate")

if __name__ == "__main__":
    main()
