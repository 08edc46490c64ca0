"""scripts/ladder_table.py: the ladder's tables and failure split from evaluate's and sort's files, against counts by
hand."""

import json
import os

import pytest


@pytest.fixture(scope="module")
def ladder(script):
    return script("ladder_table")


def _method(folder, name, inside, distance):
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, f"{name}.json"), "w") as f:
        json.dump(dict(final_inside=inside, final_distance=distance, seconds=1.0, device="cpu"), f)


def _sort(folder, seed, inside, mixing):
    os.makedirs(os.path.join(folder, str(seed)))
    with open(os.path.join(folder, str(seed), "metrics.json"), "w") as f:
        json.dump(dict(final_inside=inside, final_mixing=mixing, seconds=2.0), f)


def test_the_split_counts_what_each_rung_rescues(ladder, tmp_path):
    # episodes 0-3: ω = 50 succeeds in 0 only; best2 rescues 1 and 2; sim (2 episodes) rescues 1; oracle rescues 2
    _method(tmp_path / "lane0" / "gather-mnm-4", "50", [0.95, 0.5, 0.5, 0.5], [1.0, 2.0, 2.0, 2.0])
    _method(tmp_path / "lane0" / "gather-mnm-4", "best2", [0.95, 0.9, 0.92, 0.5], [0.9, 1.0, 1.0, 2.0])
    _method(tmp_path / "lane0" / "gather-mnm-4", "oracle", [0.95, 0.5, 0.91, 0.5], [1.0, 2.5, 1.1, 2.2])
    _method(tmp_path / "lane1" / "gather-mnm-2", "sim", [0.5, 0.9], [2.0, 1.2])
    _method(tmp_path / "lane1" / "gather-mnm-2", "run", [], [])  # not a method: skipped
    for seed, inside, mixing in ((7, [0.9, 0.85], 0.01), (8, [0.9, 0.7], 0.01), (9, [0.9, 0.9], 0.2)):
        _sort(str(tmp_path / "lane1" / "sort-coffee-candy-model"), seed, inside, mixing)
    _sort(str(tmp_path / "lane1" / "sort-coffee-candy-best5"), 8, [0.9, 0.8], 0.0)  # paired by seed: 8 and 9
    _sort(str(tmp_path / "lane1" / "sort-coffee-candy-best5"), 9, [0.5, 0.8], 0.0)
    out = str(tmp_path / "out")
    ladder.main(["--runs", str(tmp_path), "--out", out])
    with open(os.path.join(out, "ladder.json")) as f:
        result = json.load(f)
    gather = result["gather mnm"]["comparison"]
    assert gather["split"] == dict(episodes=2, base_fails=1, rescued_by=dict(best2=1, oracle=0, sim=1),
                                   rescued_by_none=0)  # the first 2 episodes: every rung ran them
    assert gather["methods"]["best2"]["success"]["first_only"] == 2 and gather["methods"]["sim"]["episodes"] == 2
    assert gather["methods"]["oracle_vs_best"]["success"]["second_only"] == 1
    sort = result["sort coffee-candy"]["runs"]
    assert sort["50"]["episode"] == [7, 8, 9] and sort["50"]["success"] == [True, False, False]
    assert sort["best5"]["episode"] == [8, 9] and sort["best5"]["success"] == [True, False]
    split = result["sort coffee-candy"]["comparison"]["split"]
    assert split == dict(episodes=2, base_fails=2, rescued_by=dict(best5=1), rescued_by_none=1)  # seeds 8 and 9
    assert sort["50"]["distance"] == pytest.approx([0.15, 0.3, 0.1])
    assert "| best2 | 4 | 75% " in open(os.path.join(out, "ladder.md")).read()
    assert open(os.path.join(out, "ladder.png"), "rb").read(4) == b"\x89PNG"
    with pytest.raises(SystemExit):
        ladder.main(["--runs", str(tmp_path / "nothing"), "--out", out])
