"""``python -m experiments.evaluate``: the command ``dynres_jax.commands.evaluate``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("evaluate")

if __name__ == "__main__":
    main()
