"""``python -m experiments.tradeoff``: the command ``dynres_jax.commands.tradeoff``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("tradeoff")

if __name__ == "__main__":
    main()
