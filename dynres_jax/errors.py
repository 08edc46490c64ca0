"""The one error type for a user's mistake."""


class InputError(ValueError):
    """Input a user gave (an argument, a file, a folder) that cannot be used. The message names it and what would be
    accepted; a command prints it as one line and exits with status 2 (``commands.checks``)."""


class JobError(RuntimeError):
    """A job of several processes that cannot go on: a peer never joined, or one was lost mid-run. The message names
    it (process id and pid); a command prints it as one line and exits with status 1."""
