"""The MuJoCo Warp engine (sim.physics.warp, PileEnv backend "warp", SizedPool): C MuJoCo's physics world by world,
batches that equal their worlds one at a time, capacity overflow as an error, and a clear error where the extra is
missing.
The engine tests run where warp-lang is installed (``pip install ".[warp]"``; Warp runs its kernels on the CPU too);
the missing-extra tests run everywhere."""

import dataclasses
import json

import jax
import numpy as np
import pytest

from dynres_jax.commands import evaluate, gather, generate_data, label_resolution, simulate
from dynres_jax.config import PushConfig, SceneConfig, SimConfig
from dynres_jax.errors import InputError
from dynres_jax.learn import data
from dynres_jax.sim.engines import resolve
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.physics import warp
from dynres_jax.sim.pool import EnvWorlds, SizedPool, make_pool

SIM = SimConfig(scene=SceneConfig(kinds=("candy",), pieces=(8,)), push=PushConfig(max_length=0.08, settle_time=0.04))
needs_warp = pytest.mark.skipif(not warp.mjx_warp.WARP_INSTALLED, reason="warp-lang is not installed")


@pytest.fixture
def no_warp(monkeypatch):
    monkeypatch.setattr(warp.mjx_warp, "WARP_INSTALLED", False)


def test_asking_for_warp_without_the_extra_names_the_extra(no_warp, tmp_path, capsys):
    for ask in (warp.check_installed, lambda: resolve("warp"), lambda: make_pool(SIM, "warp"),
                lambda: data.check_devices(data.quick_config(backend="warp"))):
        with pytest.raises(InputError, match=r'pip install "dynres-jax\[warp\]"'):
            ask()
    for command, out, quick in ((generate_data, "d", ["--quick"]), (evaluate, "e", ["--quick"]),
                                (label_resolution, "l", ["--quick"]), (gather, "g", []), (simulate, "s", [])):
        with pytest.raises(SystemExit) as stop:
            command.main(["--out", str(tmp_path / out), *quick, "--backend", "warp"])
        assert stop.value.code == 2
        assert 'dynres-jax[warp]' in capsys.readouterr().err
        assert not (tmp_path / out).exists()  # refused before any work


def test_capacities_grow_with_pieces_and_worlds():
    one = warp.capacities(10, 1)
    assert warp.capacities(10, 4) == (4 * one[0], one[1])  # contacts are counted over the batch, rows per world
    assert warp.capacities(20, 1)[0] == 2 * one[0] and warp.capacities(20, 1)[1] > one[1]
    with pytest.raises(ValueError, match="worlds"):
        warp.capacities(10, 0)


def _pushes(states) -> np.ndarray:
    """A push through each pile's centre, along x, y and a diagonal in turn."""
    centre = np.asarray(states.pos)[:, :, :2].mean(1)
    along = np.array([[0.04, 0], [0, 0.04], [0.03, 0.03]])[np.arange(len(centre)) % 3]
    return np.concatenate([centre - along, centre + 0.75 * along], 1).astype(np.float32)


@pytest.fixture(scope="module")
def c_and_warp():
    """Three C-settled piles, their pushes, and the outcomes in C MuJoCo and in a SizedPool."""
    c = EnvWorlds(PileEnv(SIM, backend="mujoco", render=False))
    keys = jax.random.split(jax.random.PRNGKey(5), 3)
    start = c.reset(keys)
    start = start._replace(overflow=np.zeros(3, np.int32))
    actions = _pushes(start)
    pool = SizedPool(SIM)
    return start, actions, c.push(start, actions), pool, pool.push(start, actions)


@needs_warp
def test_warp_pushes_as_c_mujoco_does(c_and_warp):
    start, actions, c, pool, w = c_and_warp
    moved = np.linalg.norm(np.asarray(c.pos) - np.asarray(start.pos), axis=-1)
    apart = np.linalg.norm(np.asarray(w.pos) - np.asarray(c.pos), axis=-1)
    assert moved.max() > 0.02  # the pushes moved pieces
    assert np.median(apart) < 0.001 and np.mean(apart) < 0.25 * np.mean(moved)  # and Warp moved them as C did
    assert not np.asarray(w.broken).any() and not np.asarray(w.overflow).any()
    assert w.obs.depth.shape[0] == 3  # observed, as every pool's States are


@needs_warp
def test_a_warp_batch_equals_its_worlds_one_at_a_time(c_and_warp):
    """Worlds share MuJoCo Warp's contact buffer in a batch; each world's physics is still its own. Over the first 60
    steps of the pushes (the plate lowering and meeting the pile) a world batched with others and the same world alone
    agree to float rounding. (Over a whole push they drift apart by up to millimetres: a world's contact rows are
    ordered by the batch's shared buffer, and a pile amplifies rounding: studies.warp_engine.)"""
    start, actions, _, pool, _ = c_and_warp
    engines = {n: pool._worlds(n).env for n in (1, 3)}
    plate = jax.vmap(engines[3].plate_trajectory)(actions)
    plate = jax.tree.map(lambda x: x[:, :60], plate)
    batch = jax.jit(jax.vmap(engines[3].simulate))(start, *plate)
    assert np.abs(np.asarray(batch.pos) - np.asarray(start.pos)).max() > 1e-3  # the plates moved pieces already
    one = jax.jit(jax.vmap(engines[1].simulate))
    for i in range(3):
        alone = one(*jax.tree.map(lambda x, i=i: x[i:i + 1], (start, *plate)))
        np.testing.assert_allclose(np.asarray(alone.pos[0]), np.asarray(batch.pos[i]), atol=1e-5)


@needs_warp
def test_running_out_of_contacts_is_an_error(monkeypatch, c_and_warp):
    start, actions = c_and_warp[:2]
    monkeypatch.setattr(warp, "CONTACTS_PER_PIECE", 1)
    small = SizedPool(dataclasses.replace(SIM))  # sized with one contact a piece: the piles hold more
    with pytest.raises(warp.CapacityError, match=r"contacts \(naconmax\): 3 worlds"):
        small.push(start, actions)
    env = small._sizes[3].env  # the engine behind the error flags the worlds broken too
    flagged = jax.jit(jax.vmap(env.push))(start, actions)
    assert np.asarray(flagged.broken).all() and np.asarray(flagged.overflow).all()


@needs_warp
def test_generate_data_on_warp_writes_the_shard_layout(tmp_path):
    summary = generate_data.main(["--out", str(tmp_path / "d"), "--quick", "--backend", "warp", "--episodes", "4",
                                  "--no-progress"])
    assert summary["backend"] == "warp" and summary["frames"] == 4 * 3
    shard = np.load(tmp_path / "d" / "shard_00000.npz")
    assert "overflow" not in shard.files and shard["pos"].shape[:2] == (4, 3)
    assert np.abs(shard["pos"][:, -1] - shard["pos"][:, 0]).max() > 0.005  # the random pushes moved pieces


@needs_warp
def test_evaluate_runs_its_episodes_in_warp_worlds(tmp_path):
    """The closed loop over SizedPool worlds: the same episodes as over C workers end close to where C's end."""
    finals = {}
    for backend in ("warp", "mujoco"):
        summary = evaluate.main(["--quick", "--episodes", "2", "--mpc-steps", "2", "--pieces", "30", "--samples", "4",
                                 "--adam-steps", "2", "--methods", "50", "--dynamics", "sweep",
                                 *(["--workers", "1"] if backend == "mujoco" else []), "--backend", backend,
                                 "--out", str(tmp_path / backend)])
        assert list(summary["methods"]) == ["50"]
        finals[backend] = np.array(json.loads((tmp_path / backend / "50.json").read_text())["final_distance"])
    assert np.all(np.isfinite(finals["warp"]))
    np.testing.assert_allclose(finals["warp"], finals["mujoco"], rtol=0.25)
