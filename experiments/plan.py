"""``python -m experiments.plan``: the command ``dynres_jax.commands.plan``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("plan")

if __name__ == "__main__":
    main()
