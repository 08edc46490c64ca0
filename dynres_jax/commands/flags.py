"""Bad flags refused in a blink: every command's flags as a table (``flags.json``, beside this file), read before the
command's heavy imports (JAX, MuJoCo, Flax: about 5 s), so a misspelt flag, a missing ``--out`` or a value outside
its choices is one line, exit status 2, at once. The table only refuses what the command's own parser would refuse
too (no types, no checks between flags): whatever it lets through, the command's parser then reads in full.

``python -m dynres_jax.commands.flags`` rewrites the table from the commands' parsers; tests/test_flags.py checks
that the committed table is theirs.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys

TABLE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "flags.json")
NO_VALUE = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._StoreConstAction, argparse._CountAction,
            argparse.BooleanOptionalAction)


def prog(name: str) -> str:
    """How the user called command ``name``: ``dynres NAME`` from the installed script, else ``python -m
    experiments.NAME``."""
    return f"dynres {name}" if os.path.basename(sys.argv[0]) == "dynres" else f"python -m experiments.{name}"


class OneLineParser(argparse.ArgumentParser):
    """A parser whose every mistake is one line (``PROG: error: ...`` and where the options are), exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (options: {self.prog} --help)\n")


def describe(parser: argparse.ArgumentParser) -> list[dict]:
    """A parser's actions as the table keeps them: option strings (none: a positional), dest, nargs (0: a flag
    without a value), the choices of an untyped argument, required; --help left out."""
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        untyped = action.type is None and action.choices is not None
        rows.append(dict(options=list(action.option_strings), dest=action.dest,
                         nargs=0 if isinstance(action, NO_VALUE) else action.nargs,
                         choices=[str(c) for c in action.choices] if untyped else None, required=action.required,
                         append=isinstance(action, argparse._AppendAction)))
    return rows


def light_parser(name: str, rows: list[dict]) -> OneLineParser:
    """The table's parser of command ``name``: the same flags, counts and choices, every value a string."""
    parser = OneLineParser(prog=prog(name), add_help=False)
    for row in rows:
        if not row["options"]:
            parser.add_argument(row["dest"], nargs=row["nargs"], choices=row["choices"])
        elif row["nargs"] == 0:
            parser.add_argument(*row["options"], dest=row["dest"], action="store_true")
        else:
            parser.add_argument(*row["options"], dest=row["dest"], nargs=row["nargs"], choices=row["choices"],
                                required=row["required"], action="append" if row["append"] else "store")
    return parser


def precheck(name: str, argv: list[str]) -> None:
    """Refuse argv for command ``name`` as its parser would, from the table alone: one line and exit status 2 on an
    unknown flag, a missing required one, a wrong count of values or a value outside an untyped flag's choices.
    ``--help``, a command the table lacks, or no table: nothing (the command's parser answers)."""
    if any(a in ("-h", "--help") for a in argv) or not os.path.isfile(TABLE):
        return
    with open(TABLE, encoding="utf-8") as f:
        rows = json.load(f).get(name)
    if rows is not None:
        light_parser(name, rows).parse_args(argv)


def command_parser(name: str) -> argparse.ArgumentParser:
    """The parser command ``name`` builds, caught at its first ``parse_args`` (nothing runs)."""

    class Caught(Exception):
        pass

    original = argparse.ArgumentParser.parse_args

    def catch(self, args=None, namespace=None):
        raise Caught(self)

    argparse.ArgumentParser.parse_args = catch
    try:
        importlib.import_module(f"dynres_jax.commands.{name}").main(["--help"])
    except Caught as caught:
        return caught.args[0]
    finally:
        argparse.ArgumentParser.parse_args = original
    raise RuntimeError(f"command {name} parsed no arguments")


def table() -> dict:
    """{command: its rows (``describe``)} for every command."""
    from dynres_jax.commands import COMMANDS

    return {name: describe(command_parser(name)) for name in COMMANDS}


if __name__ == "__main__":
    with open(TABLE, "w", encoding="utf-8") as f:
        json.dump(table(), f, indent=1, sort_keys=True)
        f.write("\n")
    print(f"wrote {TABLE}")
