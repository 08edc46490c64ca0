"""``python -m experiments.robot``: the command ``dynres_jax.commands.robot``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("robot")

if __name__ == "__main__":
    main()
