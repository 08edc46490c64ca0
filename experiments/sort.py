"""``python -m experiments.sort``: the command ``dynres_jax.commands.sort``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("sort")

if __name__ == "__main__":
    main()
