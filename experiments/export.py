"""``python -m experiments.export``: the command ``dynres_jax.commands.export``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("export")

if __name__ == "__main__":
    main()
