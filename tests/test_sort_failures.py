"""scripts/sort_failures.py: each failure's flags from Sort's step records, against episodes built by hand."""

import json

import pytest


@pytest.fixture(scope="module")
def failures(script):
    return script("sort_failures")


def _step(phase, kind, inside, mixing, left):
    """One record as the loop writes it: arrays [1] as one-element lists."""
    return dict(phase=[phase], kind=[kind], kind_inside=[inside], mixing=[mixing], astar_steps=[left])


def _episode(steps):
    return dict(steps=steps, final_inside=steps[-1]["kind_inside"][0], final_mixing=steps[-1]["mixing"][0])


def test_a_success_has_no_flag_and_counts_switches_and_phases(failures):
    steps = [_step("path", 0, [0.5, 0.9], 0.0, 4), _step("path", 1, [0.9, 0.7], 0.0, 2),
             _step("path", 1, [0.9, 0.8], 0.0, 1), _step("final", -1, [0.9, 0.85], 0.0, 0)]
    t = failures.trace(_episode(steps))
    assert t["success"] and t["flags"] == [] and t["astar"] == (4, 0)
    assert t["phases"] == {"path": 3, "final": 1} and t["switches"] == 2


def test_each_flag_is_raised_by_its_own_failure(failures):
    stalled = [_step("path", 0, [0.9, 0.5], 0.0, 1)] * 5 + [_step("path", 0, [0.9, 0.5], 0.0, 1)]
    assert failures.trace(_episode(stalled))["flags"] == ["stalled"]
    four = [_step("path", 0, [0.9, 0.5], 0.0, 1)] * 4 + [_step("path", 1, [0.9, 0.5], 0.0, 1)]
    assert failures.trace(_episode(four))["flags"] == ["short"]  # 4 steps on the inside pile: not stalled
    unfinished = [_step("path", 1, [0.5, 0.2], 0.0, 9), _step("path", 1, [0.5, 0.3], 0.0, 3)]
    assert failures.trace(_episode(unfinished))["flags"] == ["unfinished"]
    mixing = [_step("final", -1, [0.9, 0.95], 0.06, 0)]
    assert failures.trace(_episode(mixing))["flags"] == ["mixing"]
    both = [_step("path", 0, [0.95, 0.4], 0.0, 5)] * 6
    assert failures.trace(_episode(both))["flags"] == ["stalled", "unfinished"]


def test_runs_are_read_from_ladder_folders_and_tabled(failures, tmp_path):
    ok = [_step("final", -1, [0.9, 0.9], 0.0, 0)]
    bad = [_step("final", -1, [0.9, 0.9], 0.1, 0)]
    for seed, steps in ((7, ok), (8, bad)):
        folder = tmp_path / "lane0" / "sort-coffee-candy-model" / str(seed)
        folder.mkdir(parents=True)
        (folder / "metrics.json").write_text(json.dumps(_episode(steps)))
    (tmp_path / "lane0" / "other").mkdir()
    found = failures.runs(str(tmp_path))
    assert list(found) == ["sort-coffee-candy-model"] and sorted(found["sort-coffee-candy-model"]) == [7, 8]
    text = failures.table(found)
    assert "| sort-coffee-candy-model | 2 | 1 | 0 | 0 | 1 | 0 |" in text
    assert "| sort-coffee-candy-model | 8 | no | mixing | 90% / 90% | 10% | 0 -> 0 | final 1 | 0 |" in text
    with pytest.raises(SystemExit):
        failures.main(["--runs", str(tmp_path / "lane0" / "other"), "--out", str(tmp_path / "t.md")])
