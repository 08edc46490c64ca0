"""``python -m experiments.eval_dynamics``: the command ``dynres_jax.commands.eval_dynamics``, its flags checked first
(``commands.flags``: a bad flag is refused before the heavy imports)."""

from dynres_jax.commands import entry

main = entry("eval_dynamics")

if __name__ == "__main__":
    main()
