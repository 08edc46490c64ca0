"""``python -m experiments.gather``: the command ``dynres_jax.commands.gather``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("gather")

if __name__ == "__main__":
    main()
