"""Training and evaluation of the dynamics on a tiny generated data set (CPU)."""

import dataclasses
import json
import os
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from flax import nnx

from dynres_jax.commands import eval_dynamics
from dynres_jax.errors import InputError
from dynres_jax.io import ckpt
from dynres_jax.learn import data, targets
from dynres_jax.learn.train import (
    DISTANCE_EPS,
    TrainConfig,
    _Speed,
    _trim_metrics,
    draw,
    make_step,
    resident,
    rollout_errors,
    train,
)
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig, resolution_code
from dynres_jax.models.graph import SWEEP_REGIONS
from dynres_jax.models.registry import build_model

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CFG = TrainConfig(steps=4, batch=4, horizon=2, n_max=8, max_points=256, eval_every=2, ckpt_every=2, val_batches=1,
                  model=DynamicsConfig(hidden=16))


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    out = tmp_path_factory.mktemp("data")
    data.generate(data.quick_config(episodes=20, pushes=3, backend="mujoco"), str(out), progress=False)  # C MuJoCo
    return str(out)


@pytest.fixture(scope="module")
def run(shards, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    return str(out), train(CFG, shards, str(out), progress=False)


@pytest.mark.slow
def test_training_writes_metrics_curves_and_checkpoints(run):
    out, last = run
    rows = [json.loads(line) for line in open(f"{out}/metrics.jsonl")]
    assert [r["step"] for r in rows] == [2, 4] and np.isfinite(last["val_rmse_mm"])
    assert ckpt.latest_step(f"{out}/ckpt") == 4
    assert (f"{out}/curves.png") and open(f"{out}/curves.png", "rb").read(4) == b"\x89PNG"


def test_speed_leaves_out_the_first_step_and_pauses(monkeypatch):
    """samples/s on a fake clock: the first step (compilation) and the paused spans (validation, checkpoints) are
    not training time."""
    clock = iter([10.0, 13.0, 50.0, 54.0])  # start after step 1; pause; resume; pause
    monkeypatch.setattr(time, "perf_counter", lambda: next(clock))
    speed, params = _Speed(batch=8), np.zeros(2)
    speed.stepped(params)
    assert speed.samples_per_s() is None
    speed.stepped(params)
    speed.stepped(params)
    speed.pause(params)  # 2 timed steps in 3 s
    speed.resume()
    speed.stepped(params)
    speed.pause(params)  # 1 more in 4 s
    assert speed.samples_per_s() == pytest.approx(3 * 8 / 7)


@pytest.mark.slow  # trains the module's run (72 s on the 2-core CPU): CI's second tier
def test_resumed_run_equals_an_uninterrupted_one(shards, run, tmp_path):
    """Stop on the time limit after step 1 (a checkpoint there), leave a metrics line past it as a kill would,
    resume to 4: the same parameters as the uninterrupted run."""
    out, _ = run
    train(CFG, shards, str(tmp_path), progress=False, max_minutes=0.0)
    assert ckpt.latest_step(tmp_path / "ckpt") == 1
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 3, "train_rmse_mm": 0.0}) + "\n")  # written after the checkpoint, then killed
    with pytest.raises(ValueError, match="another TrainConfig"):
        train(dataclasses.replace(CFG, steps=4, lr=0.5), shards, str(tmp_path), progress=False)
    train(CFG, shards, str(tmp_path), progress=False)
    resumed, _, _ = ckpt.load_module(tmp_path / "ckpt", build_model)
    straight, _, _ = ckpt.load_module(f"{out}/ckpt", build_model)
    for a, b in zip(jax.tree.leaves(nnx.state(resumed)), jax.tree.leaves(nnx.state(straight)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert [json.loads(line)["step"] for line in open(tmp_path / "metrics.jsonl")] == [1, 2, 4]


def test_eval_reports_every_method_and_resolution(run, shards, tmp_path):
    out, _ = run
    result = eval_dynamics.main(["--ckpt", f"{out}/ckpt", "--data", shards, "--out", str(tmp_path),
                                 "--omegas", "2", "8", "--windows", "6"])
    assert set(result["omegas"]) == {"2", "8"} and result["windows"] == 4  # the held-out episodes hold 4 windows
    for r in result["omegas"].values():
        for method in eval_dynamics.METHODS:
            assert len(r[method]) == CFG.horizon and all(np.isfinite(r[method]))
        assert r["nothing moves"][0] > 0, "pushes through the pile must move some particles"
        for key in ("per_kind", "per_region"):  # the subsets split the particles: their weighted mean is the whole
            subsets = r[key].values()
            for method in eval_dynamics.METHODS:
                mean = sum(e[method] * e["particles"] for e in subsets) / sum(e["particles"] for e in subsets)
                assert mean == pytest.approx(r[method][0], rel=1e-4)
        assert set(r["per_region"]) <= set(SWEEP_REGIONS) and "swept" in r["per_region"]
    assert (tmp_path / "eval.md").read_text().startswith("| ω |")


def test_held_out_windows_are_distinct_and_too_many_are_refused(shards, monkeypatch, tmp_path, capsys):
    """eval_dynamics' windows: every (episode, start frame) pair at most once (it drew with replacement: "256
    held-out windows" held repeats); asking more than the held-out episodes hold is one line before the folder."""
    val = targets.load_shards(shards, "val")
    starts = val.pushes - CFG.horizon + 1
    drawn = []
    monkeypatch.setattr(targets, "windows", lambda data, rows, first, horizon: drawn.append((rows, first)))
    targets.random_windows(val, np.random.default_rng(0), len(val) * starts, CFG.horizon)
    pairs = set(zip(drawn[0][0].tolist(), drawn[0][1].tolist(), strict=True))
    assert len(pairs) == len(val) * starts and all(0 <= s < starts for _, s in pairs)
    with pytest.raises(ValueError, match="different windows"):
        targets.random_windows(val, np.random.default_rng(0), len(val) * starts + 1, CFG.horizon)


def test_eval_table_marks_held_out_kinds_and_weighs_omegas_by_particles():
    """The per-kind rows average the ω's one-step errors weighted by their particle counts (by hand here)."""
    per_method = {m: [1.0, 2.0] for m in eval_dynamics.METHODS}
    result = {"horizon": 2, "held_out_kinds": ["candy"], "omegas": {
        "10": {**per_method, "per_kind": {"candy": {"model": 2.0, "nothing moves": 9.0, "sweep heuristic": 4.0,
                                                    "particles": 10},
                                          "coffee": {"model": 1.0, "nothing moves": 9.0, "sweep heuristic": 2.0,
                                                     "particles": 5}}},
        "50": {**per_method, "per_kind": {"candy": {"model": 5.0, "nothing moves": 9.0, "sweep heuristic": 4.0,
                                                    "particles": 30}}}}}
    rows = {line.split(" | ")[0].lstrip("| "): line for line in eval_dynamics.table(result).splitlines()}
    model, heuristic = (2.0 * 10 + 5.0 * 30) / 40, 4.0
    share = model * 40 / (model * 40 + 1.0 * 5)  # of the model's summed error
    assert rows["candy (held out)"] == (f"| candy (held out) | 89% | {share:.0%} | {model:.2f} | 9.00 | 4.00 | "
                                        f"{model / heuristic:.2f} |")
    assert rows["coffee"] == f"| coffee | 11% | {1 - share:.0%} | 1.00 | 9.00 | 2.00 | 0.50 |"
    assert not any("| where |" in line for line in rows), "no region rows in a result without them"


def test_bad_config_names_the_problem():
    with pytest.raises(ValueError, match="omega_min"):
        TrainConfig(omega_min=0)
    with pytest.raises(ValueError, match="loss must be one of"):
        TrainConfig(loss="huber")
    with pytest.raises(ValueError, match="held_out_kinds: unknown piece kind"):
        TrainConfig(held_out_kinds=("pebble",))
    with pytest.raises(ValueError, match="batch = 0 must be at least 1"):
        TrainConfig(batch=0)


def test_rollout_errors_equal_a_loop_over_samples_and_particles(shards):
    """Both losses against a NumPy loop over the model's own rollouts: valid particles of samples whose perception
    worked, every step."""
    train_set = targets.load_shards(shards, "train")
    cfg = dataclasses.replace(CFG, batch=3)
    graphdef, params = nnx.split(Dynamics(cfg.model, rngs=nnx.Rngs(3)))
    frames = resident(train_set)
    windows, omegas, keys = draw(frames, jax.random.PRNGKey(5), cfg)
    samples = jax.vmap(lambda w, o, k: targets.make_sample(w, o, k, train_set.camera, cfg.n_max,
                                                        max_points=cfg.max_points))(windows, omegas, keys)
    got = rollout_errors(graphdef, params, samples)
    model, sq, dist = nnx.merge(graphdef, params), [], []
    for b in range(cfg.batch):
        s = jax.tree.map(lambda x, b=b: np.asarray(x[b]), samples)
        pred = np.asarray(model.rollout(s.positions[0], s.mask, s.action, resolution_code(s.radius)))
        for t in range(cfg.horizon):
            for i in np.flatnonzero(s.mask & (s.error == 0)):
                e2 = float(np.sum((pred[t, i].astype(np.float64) - s.positions[t + 1, i]) ** 2))
                sq.append(e2)
                dist.append(np.sqrt(e2 + DISTANCE_EPS**2))
    assert sq, "the batch must hold valid particles"
    np.testing.assert_allclose(float(got["mse"]), np.mean(sq), rtol=1e-4)
    np.testing.assert_allclose(float(got["distance"]), np.mean(dist), rtol=1e-4)
    _, evaluate = make_step(graphdef, None, train_set.camera, cfg)  # the jitted evaluation gives the same errors
    np.testing.assert_allclose(float(evaluate(params, frames, jax.random.PRNGKey(5))["distance"]), np.mean(dist),
                               rtol=1e-4)


@pytest.mark.parametrize("recipe, shipped", [("shipped", "SHIPPED_DYNAMICS"), ("cnn", "SHIPPED_CNN_DYNAMICS")])
def test_a_recipe_is_its_shipped_checkpoints_config(recipe, shipped, monkeypatch):
    """``train_dynamics --recipe NAME`` trains the config the shipped checkpoint's card records (model and every
    training field the card has), and a flag beside the recipe overrides it."""
    import dataclasses

    from dynres_jax.commands import train_dynamics
    from dynres_jax.learn.train import RECIPES
    from dynres_jax.models import registry

    meta = ckpt.load_module(getattr(registry, shipped), build_model)[1]
    cfg = RECIPES[recipe]
    model, recorded_model = dataclasses.asdict(cfg.model), meta["dynamics"]
    assert {k: v for k, v in model.items() if k in recorded_model} == recorded_model
    defaults = dataclasses.asdict(type(cfg.model)())  # fields added since the card was written: their defaults
    assert all(model[k] == defaults[k] for k in model if k not in recorded_model)
    recorded = {k: v for k, v in meta["train"].items() if k != "model"}
    assert {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(cfg).items()
            if k in recorded} == recorded
    seen = []
    monkeypatch.setattr(train_dynamics, "train", lambda c, *a, **k: seen.append(c) or {})
    monkeypatch.setattr(train_dynamics, "check_data", lambda *a: None)  # no data and no folder: the config alone
    monkeypatch.setattr(train_dynamics.checks, "claim", lambda *a, **k: False)
    train_dynamics.main(["--data", "d", "--out", "o", "--recipe", recipe, "--steps", "7"])
    assert seen[0] == dataclasses.replace(cfg, steps=7)



FOUR_DEVICES = """
import dataclasses, json, sys
import jax
from dynres_jax.learn import train
from tests.test_train import CFG
assert len(jax.devices()) == 4, jax.devices()
try:
    train.train(dataclasses.replace(CFG, batch=6), sys.argv[1], sys.argv[2] + "-bad", progress=False)
except ValueError as e:
    print("BAD-BATCH:", e)
print(json.dumps(train.train(CFG, sys.argv[1], sys.argv[2], progress=False)))
"""


def max_gap(a, b) -> float:
    return max(jax.tree.leaves(jax.tree.map(lambda x, y: float(np.max(np.abs(np.asarray(x) - np.asarray(y)))), a, b)))


@pytest.mark.slow
def test_four_devices_train_as_one(shards, run, tmp_path):
    """Data-parallel: the same run on 4 forced CPU devices (each batch split 1 + 1 + 1 + 1) gives the one-device
    run's parameters and metrics to float tolerance, and its checkpoint restores on one device; a batch that does not
    split over the devices is named before any work."""
    out = str(tmp_path / "four")
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", FOUR_DEVICES, shards, out], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "BAD-BATCH: batch 6 must be a multiple of the 4 devices" in proc.stdout
    assert not os.path.exists(out + "-bad")
    four = json.loads(proc.stdout.strip().splitlines()[-1])
    one_dir, one = run
    assert four["devices"] == 4 and one["devices"] == 1
    for key in ("train_rmse_mm", "val_rmse_mm", "val_distance_mm"):
        np.testing.assert_allclose(four[key], one[key], rtol=1e-4, err_msg=key)
    abstract = {"module": nnx.split(build_model(ckpt.load_meta(f"{one_dir}/ckpt")))[1]}
    a, b = ckpt.restore(f"{one_dir}/ckpt", abstract)[0], ckpt.restore(f"{out}/ckpt", abstract)[0]
    assert max_gap(a, b) < 1e-5
    assert max_gap(ckpt.restore(f"{one_dir}/ckpt", abstract, step=2)[0], a) > 1e-4  # training moved them


@pytest.mark.slow
def test_quick_data_trains_with_the_quick_recipe(tmp_path, capsys):
    """``generate_data --quick``'s data train as they are with ``--recipe quick``; the default recipe's horizon is
    refused in one line that names the quick recipe."""
    from dynres_jax.commands import train_dynamics

    data.generate(data.quick_config(backend="mujoco"), str(tmp_path / "data"), progress=False)  # quick sizes, C engine
    with pytest.raises(SystemExit):
        train_dynamics.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / "default")])
    assert "--recipe quick" in capsys.readouterr().err
    train_dynamics.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / "quick"), "--recipe", "quick",
                         "--steps", "2", "--quiet"])
    metrics = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert metrics["step"] == 2 and np.isfinite(metrics["val_rmse_mm"])  # the 10th episode held out


def test_metrics_survive_a_torn_last_line_and_a_rerun(tmp_path):
    """A crash mid-append leaves a last line cut short: it reads as absent, and a resume rewrites the file with one
    row per step up to its checkpoint (a step written twice keeps its last row); a damaged line before the last is
    named."""
    from dynres_jax.errors import InputError
    from dynres_jax.learn.train import read_metrics

    path = tmp_path / "metrics.jsonl"
    rows = [{"step": 2, "v": 1}, {"step": 4, "v": 2}, {"step": 2, "v": 3}, {"step": 6, "v": 4}]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"step": 8, "v"')
    assert read_metrics(str(path)) == rows
    _trim_metrics(str(path), 4)
    assert [json.loads(line) for line in path.read_text().splitlines()] == [{"step": 2, "v": 3}, {"step": 4, "v": 2}]
    _trim_metrics(str(path), 0)  # a fresh start: nothing kept
    assert path.read_text() == ""
    path.write_text('{"step": 2}\n{"ste\n{"step": 4}\n')
    with pytest.raises(InputError, match="line 2 is not JSON"):
        read_metrics(str(path))


def _dataset(**change) -> targets.Dataset:
    """Two tiny episodes of one frame pair, every piece in view: trainable unless ``change`` breaks it."""
    e, f, n = 2, 2, 3
    piece = np.full((e, f, 4, 4), -1, np.int16)
    piece[:, :, 1, 1] = 0
    arrays = dict(depth=np.ones((e, f, 4, 4), np.float16), piece=piece, pos=np.zeros((e, f, n, 3), np.float32),
                  mat=np.broadcast_to(np.eye(3, dtype=np.float32), (e, f, n, 3, 3)).copy(),
                  piece_mask=np.ones((e, n), bool), kind=np.zeros((e, n), np.int16),
                  action=np.zeros((e, f - 1, 4), np.float32), broken=np.zeros((e, f), bool), episode=np.arange(e))
    return targets.Dataset(**{**arrays, **change}, camera=None)


def test_degenerate_data_is_refused_before_training():
    from dynres_jax.learn.train import check_data

    check_data(_dataset(), "train", "d")
    with pytest.raises(InputError, match="'train' split: every episode is broken"):
        check_data(_dataset(broken=np.ones((2, 2), bool)), "train", "d")
    with pytest.raises(InputError, match="no frame shows a piece"):
        check_data(_dataset(piece=np.full((2, 2, 4, 4), -1, np.int16)), "train", "d")
    pos = np.zeros((2, 2, 3, 3), np.float32)
    pos[1, 0, 2, 0] = np.inf
    with pytest.raises(InputError, match="--data d: the 'val' split: episode 1 has a piece position that is not fin"):
        check_data(_dataset(pos=pos), "val", "d")


def test_a_diverged_run_stops_and_saves_nothing(shards, tmp_path, monkeypatch):
    from dynres_jax.learn import train as train_module

    real = train_module.make_step

    def poisoned(*args, **kwargs):  # every step's parameters NaN from step 1 on: a loss that diverged
        step_fn, eval_fn = real(*args, **kwargs)

        def step(*step_args):
            params, opt_state, errors = step_fn(*step_args)
            return jax.tree.map(lambda x: x * np.nan, params), opt_state, errors

        return step, eval_fn

    monkeypatch.setattr(train_module, "make_step", poisoned)
    out = str(tmp_path / "run")
    with pytest.raises(InputError, match="training diverged at step 2 .*the last checkpoint is none"):
        train(CFG, shards, out, progress=False)
    assert ckpt.latest_step(os.path.join(out, "ckpt")) is None
    assert not os.path.exists(os.path.join(out, "metrics.jsonl"))
