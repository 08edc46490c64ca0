"""``python -m experiments.redistribute``: the command ``dynres_jax.commands.redistribute``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("redistribute")

if __name__ == "__main__":
    main()
