"""``python -m experiments.label_resolution``: the command ``dynres_jax.commands.label_resolution``, its flags
checked first (``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("label_resolution")

if __name__ == "__main__":
    main()
