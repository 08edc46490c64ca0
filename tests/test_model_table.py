"""scripts/model_table.py: models compared in closed loop on the episodes both ran, against counts by hand; runs of
named checkpoints (the ladder recipe's folder suffix) are told apart from the method alone."""

import json
import os

import pytest


@pytest.fixture(scope="module")
def table(script):
    return script("model_table")


def _run(folder, inside, distance):
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "50.json"), "w") as f:
        json.dump(dict(final_inside=inside, final_distance=distance, seconds=1.0, device="cpu"), f)


def test_models_are_paired_on_their_common_episodes(table, tmp_path):
    # the shipped model on 4 episodes (succeeds in 0, 1), a new one on the first 3 (succeeds in 0, 2), one unnamed run
    _run(tmp_path / "lane0" / "gather-mnm-4-checkpoints", [0.95, 0.9, 0.5, 0.5], [1.0, 1.0, 2.0, 2.0])
    _run(tmp_path / "lane1" / "gather-mnm-3-new", [0.91, 0.5, 0.93], [0.5, 1.5, 1.0])
    _run(tmp_path / "lane1" / "gather-mnm-3", [0.5, 0.5, 0.5], [3.0, 3.0, 3.0])
    results = table.compare(table.load([str(tmp_path)], None), "50@shipped")
    rows = results["gather mnm"]
    assert set(rows) == {"50@shipped", "50@new", "50"}
    assert rows["50@shipped"]["episodes"] == 4 and rows["50@shipped"]["success"] == pytest.approx(0.5)
    new = rows["50@new"]
    assert new["episodes"] == 3 and new["success"] == pytest.approx(2 / 3)
    assert new["final_d"] == pytest.approx(1.0)
    pair = new["against_base"]
    assert pair["episodes"] == 3
    assert pair["delta_d"]["mean"] == pytest.approx(((0.5 - 1.0) + (1.5 - 1.0) + (1.0 - 2.0)) / 3)
    assert pair["success"]["first_only"] == 1 and pair["success"]["second_only"] == 1  # episode 2 / episode 1
    assert "| gather mnm | 50@new | 3 | 67 %" in table.table(results, "50@shipped")


def test_a_task_without_the_base_is_left_out(table, tmp_path):
    _run(tmp_path / "lane0" / "redistribute-coffee-2-new", [0.95, 0.5], [1.0, 2.0])
    assert table.compare(table.load([str(tmp_path)], None), "50@shipped") == {}
