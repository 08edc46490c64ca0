"""Progress on a wait: a start line, then a bar, tqdm's at a terminal and plain lines in a log; quiet silences it."""

import sys

from tqdm import tqdm

from dynres_jax import progress


def test_a_log_gets_a_line_at_the_start_on_progress_and_at_the_end(capsys, monkeypatch):
    monkeypatch.setattr(progress, "LOG_SECONDS", 0.0)
    progress.start("dynres x", "3 shards into out/x")
    for _ in progress.bar(range(3), desc="shards", unit="shard"):
        pass
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "dynres x: 3 shards into out/x"
    assert [line.split(" [")[0] for line in lines[1:]] == [f"shards: {n}/3 shard" for n in range(4)], lines
    assert "\r" not in "".join(lines)


def test_a_log_line_waits_its_interval_but_the_end_is_always_written(capsys):
    bar = progress.bar(total=1000, desc="steps", unit="step")
    for _ in range(1000):
        bar.update()
    bar.close()
    assert [line.split(" [")[0] for line in capsys.readouterr().err.splitlines()] == ["steps: 0/1000 step",
                                                                                       "steps: 1000/1000 step"]


def test_a_terminal_gets_tqdm_and_quiet_gets_nothing(capsys, monkeypatch):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert type(progress.bar(total=2, desc="d")) is tqdm
    monkeypatch.undo()
    capsys.readouterr()
    for _ in progress.bar(range(2), desc="d", quiet=True):
        pass
    assert capsys.readouterr().err == ""
