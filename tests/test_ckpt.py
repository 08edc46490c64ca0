"""Checkpoints: bit-identical predictions after a restore; clear errors for missing, corrupt or mismatched ones."""

import dataclasses
import os
import re
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from dynres_jax.io import ckpt
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig

CFG = DynamicsConfig(hidden=16)


def build(meta):
    return Dynamics(DynamicsConfig(**meta["dynamics"]), rngs=nnx.Rngs(0))


def inputs():
    pos = jax.random.uniform(jax.random.PRNGKey(0), (12, 3), minval=-0.05, maxval=0.05).at[:, 2].set(0.007)
    return pos, jnp.arange(12) < 9, jnp.array([-0.08, 0.0, 0.04, 0.0]), jnp.asarray(0.3)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    model = Dynamics(CFG, rngs=nnx.Rngs(42))
    directory = tmp_path_factory.mktemp("ckpt")
    ckpt.save_module(directory, 7, model, {"dynamics": dataclasses.asdict(CFG), "note": "test"})
    return model, directory


def test_restore_gives_bit_identical_predictions(saved):
    model, directory = saved
    restored, meta, _ = ckpt.load_module(directory, build)
    assert meta["note"] == "test" and ckpt.latest_step(directory) == 7
    np.testing.assert_array_equal(np.asarray(restored(*inputs())), np.asarray(model(*inputs())))


def test_restoring_is_quiet(saved, capsys, caplog):
    """A restore prints none of orbax's read-only-manager warnings (they said nothing a user could act on)."""
    _, directory = saved
    with caplog.at_level("INFO"):
        ckpt.load_module(directory, build)
    assert "read only" not in caplog.text and "read_only" not in caplog.text
    assert "read only" not in capsys.readouterr().err


def test_missing_checkpoint_is_a_clear_error(saved, tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        ckpt.load_module(tmp_path / "nowhere", build)
    shutil.copytree(saved[1], tmp_path / "run" / "ckpt")  # a training run's --out: the checkpoint one folder down
    says = r"no checkpoint in .*run' .*; a training run's --out keeps it in ckpt/: give .*run/ckpt'"
    with pytest.raises(FileNotFoundError, match=says):
        ckpt.load_module(tmp_path / "run", build)


def test_checkpoint_of_another_model_is_a_clear_error(saved, tmp_path):
    _, directory = saved
    with pytest.raises(ckpt.CheckpointError):
        ckpt.load_module(directory, lambda meta: Dynamics(DynamicsConfig(hidden=32), rngs=nnx.Rngs(0)))


def test_one_flipped_byte_anywhere_is_refused_before_restore_naming_the_file(saved, tmp_path):
    """Every file of a step, the manifest too: one byte flipped is named, and orbax is never asked to read it."""
    import shutil

    _, directory = saved
    step_dir = os.path.join(directory, "7")
    names = [os.path.relpath(os.path.join(root, n), step_dir) for root, _, ns in os.walk(step_dir) for n in ns]
    assert len(names) > 10 and ckpt.MANIFEST in names
    for i, name in enumerate(sorted(names)):
        copy = tmp_path / str(i)
        shutil.copytree(directory, copy)
        path = copy / "7" / name
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0x01
        path.write_bytes(bytes(data))
        with pytest.raises(ckpt.CheckpointError, match=re.escape(str(path)) + " is damaged"):
            ckpt.load_module(copy, build)
        with pytest.raises(ckpt.CheckpointError, match="damaged"):
            ckpt.load_meta(copy)


def test_a_save_killed_before_its_manifest_is_unfinished(saved, tmp_path):
    """A step orbax finished but whose manifest was never written is not a checkpoint: not the latest, not readable,
    and a new save of that step replaces it."""
    import shutil

    model, directory = saved
    shutil.copytree(directory, tmp_path / "c")
    os.remove(tmp_path / "c" / "7" / ckpt.MANIFEST)
    assert ckpt.latest_step(tmp_path / "c") is None
    with pytest.raises(FileNotFoundError, match="step 7 has no manifest.json"):
        ckpt.load_module(tmp_path / "c", build)
    ckpt.save_module(tmp_path / "c", 7, model, {"dynamics": dataclasses.asdict(CFG)})
    assert ckpt.latest_step(tmp_path / "c") == 7


def test_keeps_the_newest_steps(tmp_path):
    model = Dynamics(CFG, rngs=nnx.Rngs(1))
    for step in range(4):
        ckpt.save_module(tmp_path, step, model, {"dynamics": dataclasses.asdict(CFG)}, keep=2)
    assert ckpt.latest_step(tmp_path) == 3
    assert sorted(p for p in os.listdir(tmp_path) if p.isdigit()) == ["2", "3"]
