"""What a user sees during a wait: a start line, then a bar per loop (shards, episodes, steps, labels): tqdm's at a
terminal, a plain line per update (at most one every ``LOG_SECONDS``) when stderr is a log or a pipe. All on stderr,
so a command's printed record stays alone on stdout; ``quiet`` silences the bars (a scripted run)."""

from __future__ import annotations

import sys

from tqdm import tqdm

LOG_SECONDS = 10.0  # the shortest gap between two lines of one bar in a log


def start(prog: str, text: str) -> None:
    """The first line of a long command, before its loading and compiling: ``PROG: TEXT``."""
    print(f"{prog}: {text}", file=sys.stderr, flush=True)


def at_terminal(prog: str, text: str) -> None:
    """``start``'s line at a terminal only: a wait a user watches (a log's record, and a refusal's one line, need
    none)."""
    if sys.stderr.isatty():
        start(prog, text)


def bar(iterable=None, *, total: int | None = None, desc: str, unit: str = "it", initial: int = 0,
        quiet: bool = False) -> tqdm:
    """A progress bar over ``iterable`` (or ``total`` updates): tqdm's at a terminal, ``Lines`` elsewhere."""
    kind = tqdm if sys.stderr.isatty() else Lines
    return kind(iterable, total=total, desc=desc, unit=unit, initial=initial, disable=quiet, file=sys.stderr)


class Lines(tqdm):
    """A tqdm bar written as lines, ``desc: n/total unit [elapsed<remaining, rate]``, for a log: one at the start, one
    each time the count moved after ``LOG_SECONDS``, and the last at the end."""

    _shown = None  # the count of the last line written

    def __init__(self, *args, **kwargs):
        super().__init__(*args, mininterval=LOG_SECONDS, leave=False, **kwargs,
                         bar_format="{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed}<{remaining}, {rate_fmt}{postfix}]")

    def display(self, msg=None, pos=None):
        if msg is None and self.n != self._shown:  # msg "": tqdm clearing a terminal's bar
            self.fp.write(f"{self}\n")
            self.fp.flush()
            self._shown = self.n
        return False

    def close(self):
        if not self.disable:
            self.display()
        super().close()
