"""Several processes, one job (jax.distributed): two local CPU processes make the shards one process makes, byte for
byte, and share an evaluation's episodes; bad flag combinations are named before any work."""

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from dynres_jax import distributed
from dynres_jax.io import shards
from dynres_jax.learn import data

pytestmark = pytest.mark.slow  # end to end: CI's second tier (python -m pytest -m slow)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUICK = data.quick_config(episodes=7)  # 2 shards: 4 episodes, then 3


def free_port() -> int:
    """A port P with P + 1 free too (the job's coordinator and its rendezvous, ``distributed._rendezvous``)."""
    while True:
        with socket.socket() as s, socket.socket() as t:
            s.bind(("localhost", 0))
            try:
                t.bind(("localhost", s.getsockname()[1] + 1))
            except OSError:
                continue
            return s.getsockname()[1]


def _job(i: int, port: int, out: str, *flags: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "experiments.generate_data", "--quick", "--no-progress", "--out",
                             out, "--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", str(i),
                             *flags], cwd=REPO, env=dict(os.environ, JAX_PLATFORMS="cpu"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def test_a_peer_that_never_joins_is_named_within_the_join_timeout(tmp_path):
    """Process 0 of two, alone: one line naming process 1 after --join-timeout, exit 1, no folder made (JAX alone
    would wait 300 s and abort, blaming "another task")."""
    t0 = time.monotonic()
    proc = _job(0, free_port(), str(tmp_path / "out"), "--join-timeout", "3")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1, err[-2000:]
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1 and "process(es) 1 of 2 never joined the job" in lines[0], err[-2000:]
    assert time.monotonic() - t0 < 60 and not (tmp_path / "out").exists()


def test_a_peer_killed_mid_run_is_named_at_once(tmp_path):
    """kill -9 of process 1 once the job has met (its folder claimed): process 0 names it (id and pid) in one line
    within seconds, not after JAX's 100 s heartbeat, and exits 1 (the shards finished before a kill stay: the
    resume tests)."""
    port, out = free_port(), str(tmp_path / "out")
    procs = [_job(i, port, out, "--episodes", "400") for i in range(2)]
    try:
        deadline = time.monotonic() + 120
        while not os.path.exists(os.path.join(out, "run.json")) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert os.path.exists(os.path.join(out, "run.json"))
        procs[1].kill()
        t0 = time.monotonic()
        _, err = procs[0].communicate(timeout=60)
        assert procs[0].returncode == 1 and time.monotonic() - t0 < 20, err[-2000:]
        lines = [line for line in err.splitlines() if "error:" in line]
        assert len(lines) == 1 and f"process 1 (pid {procs[1].pid}) of the job was lost mid-run" in lines[0], err
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()


def launch(module_args: list[str], processes: int = 2, timeout: int = 600) -> list[str]:
    """Run ``python -m MODULE ARGS`` as a job of ``processes`` local CPU processes joined by hand; their stdouts."""
    port, env = free_port(), dict(os.environ, JAX_PLATFORMS="cpu")
    procs = [subprocess.Popen([sys.executable, "-m", *module_args, "--coordinator", f"localhost:{port}",
                               "--num-processes", str(processes), "--process-id", str(i)], cwd=REPO, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(processes)]
    ends = [p.communicate(timeout=timeout) for p in procs]
    for p in procs:
        assert p.returncode == 0, "\n".join(f"process {j}: {err[-1500:]}" for j, (_, err) in enumerate(ends))
    return [out for out, _ in ends]


@pytest.fixture(scope="module")
def two_process_data(tmp_path_factory):
    """The quick run made by a job of two processes (started first, so it runs beside the one-process run)."""
    out = str(tmp_path_factory.mktemp("job") / "run")
    port, env = free_port(), dict(os.environ, JAX_PLATFORMS="cpu")
    procs = [subprocess.Popen([sys.executable, "-m", "experiments.generate_data", "--quick", "--episodes", "7",
                               "--no-progress", "--out", out, "--coordinator", f"localhost:{port}",
                               "--num-processes", "2", "--process-id", str(i)], cwd=REPO, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    yield out, procs
    for p in procs:
        if p.poll() is None:
            p.kill()


def test_two_processes_write_the_shards_of_one_byte_for_byte(two_process_data, tmp_path):
    one = str(tmp_path / "one")
    data.generate(QUICK, one, progress=False)
    out, procs = two_process_data
    summaries = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=600)
        assert p.returncode == 0, stderr[-3000:]
        summaries.append(json.loads(stdout[stdout.index("{"):]))
    assert [(s["process"], s["processes"], s["shards_written"]) for s in summaries] == [(0, 2, 1), (1, 2, 1)]
    assert sorted(f for f in os.listdir(out) if f.endswith(".npz")) == ["shard_00000.npz", "shard_00001.npz"]
    for shard in (0, 1):
        with open(shards.shard_path(out, shard), "rb") as a, open(shards.shard_path(one, shard), "rb") as b:
            assert a.read() == b.read(), f"shard {shard} differs"
    with open(os.path.join(out, "summary.json")) as f:  # written once, after both, over both shards
        summary = json.load(f)
    assert summary["episodes"] == 7 and summary["shards"] == 2


def test_two_processes_share_an_evaluation(tmp_path):
    """Process I runs episodes I, I + 2, ...; process 0 merges the parts in episode order. Episode 0 (a batch of one
    in both) is what one process alone makes of it: piles, goals and keys are seeded by episode, not by process."""
    common = ["--quick", "--task", "gather", "--mpc-steps", "1", "--methods", "50", "--samples", "4",
              "--adam-steps", "2", "--workers", "1", "--dynamics", "sweep"]
    job, alone = str(tmp_path / "job"), str(tmp_path / "alone")
    launch(["experiments.evaluate", *common, "--episodes", "2", "--out", job])
    subprocess.run([sys.executable, "-m", "experiments.evaluate", *common, "--episodes", "1", "--out", alone],
                   cwd=REPO, check=True, env=dict(os.environ, JAX_PLATFORMS="cpu"), capture_output=True)
    read = lambda *path: json.load(open(os.path.join(*path)))  # noqa: E731
    shared, single = read(job, "50.json"), read(alone, "50.json")
    parts = [read(job, "parts", f"50.{i}-of-2.json") for i in range(2)]
    assert [p["episode"] for p in parts] == [[0], [1]] and shared["processes"] == 2
    assert shared["final_distance"] == [p["distance"][-1][0] for p in parts]
    assert shared["final_distance"][0] == single["final_distance"][0]
    assert read(job, "summary.json")["methods"]["50"]["episodes"] == 2


TRAIN_IN_A_JOB = """
import json, sys
from dynres_jax import distributed
distributed.initialize(sys.argv[1], 2, int(sys.argv[2]))
import jax
from dynres_jax.learn import train
from dynres_jax.learn.train import TrainConfig
from dynres_jax.models.dynamics import DynamicsConfig
cfg = TrainConfig(steps=4, batch=4, horizon=2, n_max=8, max_points=256, eval_every=2, ckpt_every=2, val_batches=1,
                  model=DynamicsConfig(hidden=16))
assert len(jax.devices()) == 4 and len(jax.local_devices()) == 2
print(json.dumps(train.train(cfg, sys.argv[3], sys.argv[4], progress=False)))
"""


def test_training_spans_two_processes_and_resumes_in_both(tmp_path):
    """Two processes of two CPU devices each train one model (each batch split over all four): both end with the same
    metrics, process 0 alone writes the checkpoints and metrics, and with the last checkpoint deleted both restore the
    one before and train on to the same result (a batch depends on (seed, step) only)."""
    shards, out = str(tmp_path / "data"), str(tmp_path / "run")
    data.generate(data.quick_config(episodes=20, pushes=3, backend="mujoco"), shards, progress=False)  # C MuJoCo

    def job() -> list[dict]:
        port = free_port()
        env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=2")
        procs = [subprocess.Popen([sys.executable, "-c", TRAIN_IN_A_JOB, f"localhost:{port}", str(i), shards, out],
                                  cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for i in range(2)]
        results = []
        for p in procs:
            stdout, stderr = p.communicate(timeout=600)
            assert p.returncode == 0, stderr[-3000:]
            results.append(json.loads(stdout.strip().splitlines()[-1]))
        for r in results:
            r.pop("samples_per_s")  # each process's own clock
        return results

    first = job()
    assert first[0] == first[1] and first[0]["devices"] == 4 and first[0]["step"] == 4
    assert sorted(os.listdir(os.path.join(out, "ckpt"))) == ["2", "4"]
    with open(os.path.join(out, "metrics.jsonl")) as f:
        assert [json.loads(line)["step"] for line in f] == [2, 4]  # one writer: no line twice
    shutil.rmtree(os.path.join(out, "ckpt", "4"))
    kept = os.path.join(out, "ckpt", "2", "manifest.json")
    stamp = os.stat(kept).st_mtime_ns
    again = job()
    assert os.stat(kept).st_mtime_ns == stamp  # step 2 was restored, not trained and written again
    assert sorted(os.listdir(os.path.join(out, "ckpt"))) == ["2", "4"]
    assert again[0] == again[1]
    for key in ("train_rmse_mm", "val_rmse_mm", "val_distance_mm"):
        assert again[0][key] == pytest.approx(first[0][key], rel=1e-5), key


@pytest.mark.parametrize("flags, message", [
    (dict(coordinator="localhost:1234"), "missing --num-processes, --process-id"),
    (dict(coordinator="localhost:1234", num_processes=2, process_id=2), "must lie in"),
    (dict(coordinator="localhost", num_processes=2, process_id=0), "HOST:PORT"),
])
def test_bad_job_flags_are_named(flags, message):
    with pytest.raises(ValueError, match=message):
        distributed.initialize(**flags)


def test_a_lone_process_is_part_zero_of_one():
    assert distributed.initialize() == (0, 1) and distributed.is_writer()
    parser = argparse.ArgumentParser()
    distributed.add_args(parser)
    with pytest.raises(SystemExit):
        distributed.from_args(parser, parser.parse_args(["--process-id", "1"]))


REGRESSOR_ON_FOUR = """
import json, sys
import jax
import numpy as np
sys.path.insert(0, "tests")
from test_distributed import regressor_run

assert len(jax.devices()) == 4
print(json.dumps(regressor_run()))
"""


def regressor_run() -> dict:
    """g trained on 60 synthetic scenes (labels a function of the inputs' mean), 30 steps of batch 8, on every
    device: its metrics and a checksum of its parameters."""
    import jax

    from dynres_jax.learn.regressor import train_regressor

    rng = np.random.default_rng(0)
    inputs = rng.normal(size=(60, 16, 16, 6)).astype(np.float32)
    labels = np.clip(50 + 400 * inputs.mean(axis=(1, 2, 3)), 2, 100).astype(np.int32)
    d = dict(inputs=inputs, label=labels, pile=np.arange(60) // 2, shard=np.zeros(60, np.int64))
    params, metrics, _, _ = train_regressor(d, steps=30, batch=8, width=4, val_every=10)
    metrics["checksum"] = float(sum(np.abs(np.asarray(x)).sum() for x in jax.tree.leaves(params)))
    return metrics


def test_regressor_on_four_devices_trains_as_on_one():
    """g data-parallel: 4 forced CPU devices (each batch of 8 split 2 + 2 + 2 + 2) give one device's run to float
    tolerance, and training moved the parameters away from their start (steps=0 would keep them)."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", REGRESSOR_ON_FOUR], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    four, one = json.loads(proc.stdout.strip().splitlines()[-1]), regressor_run()
    for key in ("mae", "validation_mse", "checksum", "best_step"):
        assert four[key] == pytest.approx(one[key], rel=1e-4), key
    assert one["best_step"] > 0
