"""The command line: ``dynres COMMAND [options]`` (or ``python -m experiments.COMMAND`` from a checkout).

Task commands: gather, redistribute, sort, plan, goal, robot. Evaluation: evaluate, eval_dynamics, tradeoff. Learning:
generate_data, train_dynamics, label_resolution, train_regressor. Other: simulate, export. ``dynres COMMAND --help``
for each; ``-`` and ``_`` are the same in a command's name. For example:

    dynres gather --out out/gather                                   # the main job: Gather on the shipped model
    dynres redistribute --letter T --out out/letter                  # a letter; --goal-png G.png: your own shape
    dynres sort --kind almond mnm --out out/sort                     # two kinds, each to its own disc
    dynres evaluate --task gather --episodes 64 --out runs/eval      # paired methods, intervals, McNemar
    dynres plan --depth D.png --rgb C.png --camera cam.json --goal G.png --out out/push.png   # one push, a real frame
    dynres export --out out/decision.jaxexport                       # the whole decision as one file for a robot
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
import sys

COMMANDS = ("gather", "redistribute", "sort", "plan", "goal", "robot", "evaluate", "eval_dynamics", "tradeoff",
            "generate_data", "train_dynamics", "label_resolution", "train_regressor", "simulate", "export")


def docstring(module: str) -> str:
    """Module ``module``'s docstring, also under ``python -OO`` (PYTHONOPTIMIZE=2 strips ``__doc__``: then read from
    its source), "" when neither is there: the help text of a command never fails on a missing docstring."""
    doc = getattr(sys.modules.get(module), "__doc__", None)
    if doc is not None:
        return doc
    try:
        with open(importlib.util.find_spec(module).origin, encoding="utf-8") as f:
            return ast.get_docstring(ast.parse(f.read()), clean=False) or ""
    except (OSError, SyntaxError, ValueError, AttributeError, ImportError):
        return ""


def main(argv=None) -> None:
    """``dynres COMMAND ...``: run ``dynres_jax.commands.COMMAND.main`` on the rest of the arguments (its result, a
    summary the command has printed, is not returned: a console script's return value is its exit status)."""
    program, argv = argv is None, sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(docstring(__name__).strip())
        return
    name = argv[0].replace("-", "_")
    if name not in COMMANDS:
        print(f"dynres: error: unknown command {argv[0]!r}; the commands: {', '.join(COMMANDS)}", file=sys.stderr)
        raise SystemExit(2)
    if program:  # the console script: the command reads sys.argv, so it runs as the program (guard's deadline)
        sys.argv = [sys.argv[0], *argv[1:]]
        entry(name)()
    else:
        entry(name)(argv[1:])


def entry(name: str):
    """Command ``name``'s main, its flags first checked against the flag table (``flags.precheck``: a bad flag is
    refused before the command's heavy imports), then the command itself; at a terminal a line first says what the
    seconds of imports are (JAX and MuJoCo take 5-20 s to load on a small CPU)."""

    def main(argv=None):
        from dynres_jax.commands.flags import precheck, prog

        args = sys.argv[1:] if argv is None else list(argv)
        precheck(name, args)
        if sys.stderr.isatty() and not {"-h", "--help"} & set(args):
            print(f"{prog(name)}: starting (loading JAX and MuJoCo)", file=sys.stderr, flush=True)
        try:
            command = importlib.import_module(f"dynres_jax.commands.{name}")
        except ValueError as e:  # JAX reads its JAX_* environment variables on import
            flag = re.search(r"JAX flag (\w+)|for environment '(\w+)'", str(e))
            if flag is None:
                raise
            print(f"{prog(name)}: error: the environment variable {(flag.group(1) or flag.group(2)).upper()}: {e}; "
                  "unset it or give a value JAX takes", file=sys.stderr)
            raise SystemExit(2) from None
        return command.main(argv)

    return main
