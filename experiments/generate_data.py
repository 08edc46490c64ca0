"""``python -m experiments.generate_data``: the command ``dynres_jax.commands.generate_data``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("generate_data")

if __name__ == "__main__":
    main()
