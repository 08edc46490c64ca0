"""``python -m experiments.goal``: the command ``dynres_jax.commands.goal``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("goal")

if __name__ == "__main__":
    main()
