"""scripts/stop_rule.py and tasks.stopped: the stop rule replayed on episodes built by hand."""

import numpy as np
import pytest

from dynres_jax.control import tasks


@pytest.fixture(scope="module")
def stop_rule(script):
    return script("stop_rule")


def _results():
    """Three episodes of four steps (seen_inside before each push; inside and d after it), made by hand: episode 0
    reaches 0.9 after push 1 and loses it; episode 1 succeeds at the end only; episode 2 never sees 0.9."""
    seen = [[0.2, 0.3, 0.1], [0.92, 0.5, 0.5], [0.95, 0.85, 0.6], [0.80, 0.93, 0.7]]
    inside = [[0.5, 0.6, 0.2], [0.91, 0.7, 0.3], [0.85, 0.92, 0.4], [0.84, 0.95, 0.5]]
    distance = [[5.0, 6.0, 9.0], [1.0, 4.0, 8.0], [2.0, 1.5, 7.0], [3.0, 1.0, 6.0]]
    return dict(seen_inside=seen, inside=inside, distance=distance, final_inside=inside[-1],
                final_distance=distance[-1])


def test_stopped_keeps_the_scores_after_the_push_before_the_frame_that_met_it():
    out = tasks.stopped(_results(), 0.9)
    assert out["stopped_at"] == [1, 3, 4]  # episode 0's frame before push 1 met 0.9; episode 2 never
    assert out["final_inside"] == [0.5, 0.92, 0.5] and out["final_distance"] == [5.0, 1.5, 6.0]
    np.testing.assert_array_equal(np.asarray(out["inside"])[:, 0], [0.5, 0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match="before their first push"):
        tasks.stopped(_results(), 0.15)  # episode 0's first frame already meets it


def test_the_table_counts_gains_and_losses_and_chooses_the_best_share(stop_rule):
    lines, best = stop_rule.rows(_results(), "redistribute", (0.9, 0.94), None)
    assert "| all | none | 33% " in lines[0]  # episode 1 alone ends >= 90 % inside
    # 0.90: episode 0 stops before push 1 (0.5 inside: failed either way), episode 1 before push 3 (0.92: kept)
    assert "| all | 0.90 | 33% " in lines[1] and "| 0 / 0 " in lines[1]
    # 0.94: episode 0 stops before push 2 with 0.91 inside (gained), episode 1 runs on to 0.95: 2 of 3
    assert "| all | 0.94 | 67% " in lines[2] and "| 1 / 0 " in lines[2] and best == (2, 0.94)


def test_the_first_steps_of_a_run_are_the_shorter_run(stop_rule):
    out = tasks.first_steps(_results(), 2)
    assert out["final_inside"] == [0.91, 0.7, 0.3] and out["final_distance"] == [1.0, 4.0, 8.0]
    assert np.shape(out["seen_inside"]) == (2, 3) and out["mean_inside"] == pytest.approx([0.705, 0.65, 0.25])
    lines, best = stop_rule.rows(out, "redistribute", (0.9,), None)
    assert "| all | none | 33% " in lines[0] and best == (1, np.inf)  # episode 0 alone; the rule changes nothing
    with pytest.raises(ValueError, match="steps must be in 1..4"):
        tasks.first_steps(_results(), 5)


def test_variants_compares_each_variant_at_its_own_steps_and_share(script, tmp_path):
    """scripts/variants.py --at: a variant read at T steps with the stop rule replayed, paired against another at its
    own T, by hand: "a" at 4 steps with the rule at 0.94 succeeds on episodes 0 and 1, "b" (the same run) at 2 steps on
    episode 0 alone: 2 of 3 against 1 of 3, one episode only in "a"."""
    import json

    variants = script("variants")
    for name in ("a", "b"):
        (tmp_path / name / "redistribute-coffee").mkdir(parents=True)
        (tmp_path / name / "redistribute-coffee" / "50.json").write_text(json.dumps(_results()))
    text = variants.table([str(tmp_path)], "redistribute", ["a", "b"], "50", settings=dict(a=(4, 0.94), b=(2, None)))
    a, b = (line for line in text.splitlines() if line.startswith("| coffee | all |"))
    assert "| a | 67% " in a and "| b | 33% " in b and "| 0 / 1 " in b  # only in b / only in a
    assert variants.at("hinge=90") == ("hinge", (90, None)) and variants.at("base=80:0.92") == ("base", (80, 0.92))
    with pytest.raises(Exception, match="VARIANT=T"):
        variants.at("base80")


def test_variants_reads_blocks_of_episodes_as_one_run(script, tmp_path):
    """scripts/variants.py --runs A B: a run split into two blocks of episodes (episode 0 in A, 1 and 2 in B) gives
    the table of the whole run, the per-step means recomputed over the three episodes; blocks of other steps are
    refused."""
    import json

    variants = script("variants")
    whole, cols = _results(), {"A": [0], "B": [1, 2]}
    for block, keep in cols.items():
        part = {k: (np.asarray(v)[keep] if k.startswith("final") else np.asarray(v)[:, keep]).tolist()
                for k, v in whole.items()}
        for name in ("a", "b"):
            (tmp_path / block / name / "redistribute-coffee").mkdir(parents=True)
            (tmp_path / block / name / "redistribute-coffee" / "50.json").write_text(json.dumps(part))
    for name in ("a", "b"):
        (tmp_path / "W" / name / "redistribute-coffee").mkdir(parents=True)
        (tmp_path / "W" / name / "redistribute-coffee" / "50.json").write_text(json.dumps(whole))
    settings = dict(a=(4, 0.94), b=(2, None))
    blocks = [str(tmp_path / "A"), str(tmp_path / "B")]
    assert variants.table(blocks, "redistribute", ["a", "b"], "50", settings=settings) == variants.table(
        [str(tmp_path / "W")], "redistribute", ["a", "b"], "50", settings=settings)
    one = variants.joined([variants.read_method(b, "a", "redistribute", "coffee", "50") for b in blocks])
    assert one["mean_inside"] == pytest.approx(np.mean(whole["inside"], axis=1))
    with pytest.raises(ValueError, match="different MPC steps"):
        variants.joined([whole, tasks.first_steps(whole, 2)])
    with pytest.raises(SystemExit):  # the same block twice would double the episodes and shrink the p-values
        variants.main(["--runs", blocks[0], blocks[0], "--variants", "a", "b", "--task", "redistribute"])


def test_stop_share_reads_off_in_any_case_and_names_it_when_wrong():
    import argparse

    from dynres_jax.commands import checks

    assert [checks.stop_share(t) for t in ("off", "OFF", "Off", "0.9", "1")] == ["off", "off", "off", 0.9, 1.0]
    for bad in ("0", "1.5", "x", "nan"):
        with pytest.raises(argparse.ArgumentTypeError, match="'off' for no stop rule"):
            checks.stop_share(bad)
