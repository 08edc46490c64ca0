# ruff: noqa: E501  (a table of cases, one line each)
"""Every command refuses bad input the same way (issue 39): exit status 2, one line naming the argument or file, no
traceback, and no output folder created or changed. A table of a few hundred bad inputs over every command; each is
refused before any work (no episode, no compile of a planner), so the whole table runs in about a minute."""

import importlib
import json
import os
import shutil

import cv2
import jax
import numpy as np
import pytest

from dynres_jax.config import SceneConfig, SimConfig
from dynres_jax.control.budget import BUCKETS, TimingTable
from dynres_jax.io import frames
from dynres_jax.io.shards import save_npz
from dynres_jax.models.registry import SHIPPED_DYNAMICS, SHIPPED_REGRESSOR
from dynres_jax.sim.env import PileEnv


def _flipped(src: str, dst: str) -> str:
    """A copy of checkpoint folder ``src`` with one byte of its largest file flipped."""
    shutil.copytree(src, dst)
    path = max((os.path.join(r, n) for r, _, ns in os.walk(dst) for n in ns), key=os.path.getsize)
    data = bytearray(open(path, "rb").read())
    data[len(data) // 3] ^= 0x10
    open(path, "wb").write(bytes(data))
    return dst


def _shard_set(folder, config: dict, shards: dict[int, dict | bytes]) -> str:
    os.makedirs(folder)
    with open(os.path.join(folder, "config.json"), "w") as f:
        json.dump(config, f)
    for i, arrays in shards.items():
        path = os.path.join(folder, f"shard_{i:05d}.npz")
        if isinstance(arrays, bytes):
            open(path, "wb").write(arrays)
        else:
            save_npz(path, arrays)
    return folder


def _run_json(folder, command: str, config: dict) -> str:
    os.makedirs(folder)
    with open(os.path.join(folder, "run.json"), "w") as f:
        json.dump(dict(command=command, config=config), f)
    return folder


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    """Paths every case may name: a good frame and goal, damaged variants, checkpoints, shard sets, folders."""
    root = tmp_path_factory.mktemp("bad")
    p = {}
    env = PileEnv(SimConfig(scene=SceneConfig(pieces=(20,))), backend="mujoco")
    p.update({k.split(".")[0]: v for k, v in frames.save_frame(str(root / "frame"), env.reset(
        jax.random.PRNGKey(0)).obs, env.camera).items()})
    h, w = env.camera.height, env.camera.width
    goal = np.zeros((h, w), np.uint8)
    goal[50:70, 50:70] = 255
    for name, image in {"goal": goal, "empty_goal": np.zeros_like(goal), "small_goal": goal[:64, :64],
                        "corner_goal": np.pad(np.full((6, 6), 255, np.uint8), ((0, h - 6), (0, w - 6))),
                        "depth_metres": np.ones((h, w), np.uint16), "zero_depth": np.zeros((h, w), np.uint16),
                        "bare_table": np.full((h, w), 1000, np.uint16),
                        "small_rgb": np.zeros((64, 64, 3), np.uint8), "wide_goal": np.pad(goal, ((0, 0), (0, w))),
                        "full_goal": np.full((h, w), 255, np.uint8)}.items():
        p[name] = str(root / f"{name}.png")
        cv2.imwrite(p[name], image)
    replay = root / "replay_damaged"  # frame 000 good, frame 001's depth not an image
    shutil.copytree(root / "frame", replay / "000")
    shutil.copytree(root / "frame", replay / "001")
    open(replay / "001" / "depth.png", "wb").write(b"\x89PNG damaged")
    p["replay_damaged"] = str(replay)
    p["text"] = str(root / "notes.txt")
    open(p["text"], "w").write("not an image\n")
    good = json.load(open(p["camera"]))
    cameras = {
        "cam_negative_f": {**good, "K": [[-278.0, 0, 64], [0, 278.0, 64], [0, 0, 1]]},
        "cam_not_rotation": {**good, "rotation": [[1, 0, 0], [0, 2, 0], [0, 0, -1]]},
        "cam_mirror": {**good, "rotation": [[-1, 0, 0], [0, -1, 0], [0, 0, -1]]},
        "cam_looks_up": {**good, "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        "cam_below": {**good, "centre": [0, 0, -1.0]},
        "cam_principal_out": {**good, "K": [[278.0, 0, 640], [0, 278.0, 64], [0, 0, 1]]},
        "cam_bad_last_row": {**good, "K": [[278.0, 0, 64], [0, 278.0, 64], [0, 1, 1]]},
        "cam_missing": {k: v for k, v in good.items() if k != "K"},
        "cam_size": {**good, "width": 64},
        "cam_strings": {**good, "centre": ["a", "b", "c"]},
    }
    for name, cam in cameras.items():
        p[name] = str(root / f"{name}.json")
        json.dump(cam, open(p[name], "w"))
    p["cam_truncated"] = str(root / "cam_truncated.json")
    open(p["cam_truncated"], "w").write(json.dumps(good)[:40])
    p["flipped_dynamics"] = _flipped(SHIPPED_DYNAMICS, str(root / "flipped_dynamics"))
    p["flipped_regressor"] = _flipped(SHIPPED_REGRESSOR, str(root / "flipped_regressor"))
    p["timing"] = str(root / "timing.json")
    TimingTable("cpu", 50, 1, {b: 0.5 for b in BUCKETS}, {b: 0.01 for b in BUCKETS}).save(p["timing"])
    p["timing20"] = str(root / "timing20.json")
    TimingTable("cpu", 20, 1, {b: 0.5 for b in BUCKETS}, {b: 0.01 for b in BUCKETS}).save(p["timing20"])
    p["garbage_json"] = str(root / "garbage.json")
    open(p["garbage_json"], "w").write("{not json")
    episodes = lambda n, pushes: dict(action=np.zeros((n, pushes, 4), np.float32), episode=np.arange(n))  # noqa: E731
    data = {"episodes": 8, "worlds": 4}
    p["data_missing"] = _shard_set(str(root / "data_missing"), data, {0: episodes(4, 6)})
    p["data_damaged"] = _shard_set(str(root / "data_damaged"), data, {0: episodes(4, 6), 1: b"PK\x03\x04 damaged"})
    p["data_short"] = _shard_set(str(root / "data_short"), {"episodes": 20, "worlds": 20}, {0: episodes(20, 2)})
    p["data_few"] = _shard_set(str(root / "data_few"), data, {0: episodes(4, 6), 1: episodes(4, 6)})
    p["data_ok"] = _shard_set(str(root / "data_ok"), {"episodes": 20, "worlds": 20}, {0: episodes(20, 6)})
    p["no_config"] = str(root / "no_config")
    os.makedirs(p["no_config"])
    labels = {"scenes": 8, "batch": 4}
    p["labels_missing"] = _shard_set(str(root / "labels_missing"), labels, {1: dict(label=np.arange(4))})
    p["labels_damaged"] = _shard_set(str(root / "labels_damaged"), labels, {0: b"garbage", 1: b"garbage"})
    p["labels"] = _shard_set(str(root / "labels"), labels, {i: dict(label=np.arange(4), shard=np.asarray(i), pile=np.arange(4), inputs=np.zeros((4, 8, 8, 6), np.float32))
                                                            for i in range(2)})
    p["labels_other_seed"] = _shard_set(str(root / "labels_other_seed"), dict(labels, seed=7), {i: dict(label=np.arange(4), shard=np.asarray(i)) for i in range(2)})
    p["file"] = str(root / "a_file")
    open(p["file"], "w").write("x")
    p["other_run"] = _run_json(str(root / "other_run"), "train_regressor", {"steps": 3000})
    p["gather_run"] = _run_json(str(root / "gather_run"), "gather", {"seed": 7})
    p["train_run"] = _run_json(str(root / "train_run"), "train_dynamics", {"data": "/elsewhere/piles"})
    p["evaluate_run"] = _run_json(str(root / "evaluate_run"), "evaluate", {"seed": 1, "mpc_steps": 5})
    p["foreign"] = str(root / "foreign")
    os.makedirs(p["foreign"])
    open(os.path.join(p["foreign"], "thesis.tex"), "w").write("x")
    p["dynamics"], p["regressor"] = SHIPPED_DYNAMICS, SHIPPED_REGRESSOR
    return p


G = [  # gather (and the flags every closed-loop task shares)
    (["--pieces", "0"], "--pieces"), (["--pieces", "-5"], "--pieces"), (["--pieces", "abc"], "--pieces"),
    (["--pieces", "1"], "--pieces"), (["--pieces", "2", "--resolution", "100"], "--pieces"),  # too few points for ω
    (["--pieces", "100000"], "--pieces"), (["--kind", "almond", "--pieces", "100"], "--pieces"),
    (["--kind", "pebble"], "--kind"), (["--seed", "-1"], "--seed"), (["--seed", "1.5"], "--seed"),
    (["--seed", "99999999999"], "--seed"), (["--mpc-steps", "0"], "--mpc-steps"), (["--mpc-steps", "-3"], "--mpc-steps"),
    (["--mpc-steps", "x"], "--mpc-steps"), (["--mpc-steps"], "--mpc-steps"), (["--resolution", "0"], "--resolution"),
    (["--resolution", "1"], "--resolution"), (["--resolution", "101"], "--resolution"),
    (["--resolution", "fast"], "--resolution"), (["--resolution", "-50"], "--resolution"),
    (["--resolution", "50.5"], "--resolution"), (["--samples", "0"], "--samples"), (["--samples", "2.5"], "--samples"),
    (["--adam-steps", "0"], "--adam-steps"), (["--adam-steps", "-1"], "--adam-steps"),
    (["--time-budget", "0"], "--time-budget"), (["--time-budget", "-1"], "--time-budget"),
    (["--time-budget", "nan"], "--time-budget"), (["--time-budget", "inf"], "--time-budget"),
    (["--time-budget", "abc"], "--time-budget"), (["--timing", "{timing}"], "--timing"),
    (["--time-budget", "0.25", "--timing", "/nonexistent.json"], "--timing"),
    (["--time-budget", "0.25", "--timing", "{garbage_json}"], "--timing"),
    (["--time-budget", "1e-6", "--timing", "{timing}"], "--time-budget"),
    (["--ckpt", "/nonexistent"], "--ckpt"), (["--ckpt", "{flipped_dynamics}"], "damaged"),
    (["--ckpt", "{regressor}"], "--ckpt"), (["--ckpt", "{file}"], "--ckpt"),
    (["--dynamics", "sweep", "--ckpt", "{regressor}"], "--ckpt"), (["--dynamics", "magic"], "--dynamics"),
    (["--backend", "warp"], "--backend"), (["--layout", "square"], "--layout"),
    (["--resolution", "adaptive", "--regressor", "/nonexistent"], "--regressor"),
    (["--resolution", "adaptive", "--regressor", "{dynamics}"], "--regressor"),
    (["--resolution", "adaptive", "--regressor", "{flipped_regressor}"], "--regressor"),
    (["--resolution", "40", "--regressor", "{regressor}"], "--regressor is for --resolution adaptive"),
    (["--ckpt", ""], "--ckpt: no checkpoint"),
    (["--out", "{file}/run"], "--out"), (["--out", "{file}"], "--out"), (["--out", "{other_run}"], "--out"),
    (["--out", "{foreign}"], "--out"), (["--out", "{gather_run}"], "--out"), (["--no-such-flag"], "unrecognized"),
    (["--samples", "100000000"], "--samples"), (["--adam-steps", "10000000"], "--adam-steps"),  # bounds from sense
    (["--time-budget", "1e308"], "--time-budget"), (["--objective", "paper", "hinge"], "--objective takes one value"),
]
R = [
    (["--letter", ""], "--letter"), (["--letter", "é"], "--letter"), (["--letter", "   "], "--letter"),
    (["--letter", "W" * 30], "--letter"), (["--letter", "T\n"], "--letter"), (["--pieces", "0"], "--pieces"),
    (["--kind", "sand"], "--kind"), (["--resolution", "0"], "--resolution"), (["--layout", "ring"], "--layout"),
    (["--seed", "-2"], "--seed"), (["--mpc-steps", "0"], "--mpc-steps"), (["--out", "{other_run}"], "--out"),
]
S = [
    (["--kind", "coffee", "coffee"], "--kind"), (["--kind", "coffee"], "--kind"),
    (["--kind", "coffee", "pebble"], "--kind"), (["--pieces", "40"], "--pieces"), (["--pieces", "0", "20"], "--pieces"),
    (["--pieces", "40", "x"], "--pieces"), (["--pieces", "5000", "5000"], "--pieces"), (["--grid-step", "0"], "--grid-step"),
    (["--grid-step", "-0.02"], "--grid-step"), (["--grid-step", "nan"], "--grid-step"), (["--grid-step", "5"], "--grid-step"),
    (["--resolution", "adaptive"], "--resolution"), (["--resolution", "0"], "--resolution"),
    (["--resolution", "101"], "--resolution"), (["--mpc-steps", "0"], "--mpc-steps"), (["--samples", "0"], "--samples"),
    (["--time-budget", "0"], "--time-budget"), (["--ckpt", "/nonexistent"], "--ckpt"), (["--out", "{file}"], "--out"),
    (["--out", "{gather_run}"], "--out"), (["--method", "best0"], "--method"), (["--method", "oracle"], "--method"),
    (["--stop-share", "0"], "--stop-share"), (["--objective", "hinged"], "--objective"),
    (["--objective", "paper", "hinge", "paper"], "--objective takes one value or one per kind"),
]
FRAME = ["--depth", "{depth}", "--rgb", "{rgb}", "--camera", "{camera}", "--goal", "{goal}"]
P = [  # plan: one frame of a real camera
    (["--depth", "/nonexistent"], "depth file"), (["--depth", "{rgb}"], "depth file"),
    (["--depth", "{depth_metres}"], "depth file"), (["--depth", "{zero_depth}"], "depth file"),
    (["--depth", "{bare_table}"], "shows no pile"),
    (["--depth", "{text}"], "depth file"), (["--rgb", "/nonexistent"], "colour file"), (["--rgb", "{text}"], "colour file"),
    (["--rgb", "{small_rgb}"], "colour"), (["--camera", "/nonexistent"], "camera file"),
    (["--camera", "{cam_negative_f}"], "focal"), (["--camera", "{cam_not_rotation}"], "rotation"),
    (["--camera", "{cam_mirror}"], "rotation"), (["--camera", "{cam_looks_up}"], "look down"),
    (["--camera", "{cam_below}"], "above the table"), (["--camera", "{cam_principal_out}"], "principal point"),
    (["--camera", "{cam_bad_last_row}"], "camera file"), (["--camera", "{cam_missing}"], "camera file"),
    (["--camera", "{cam_size}"], "camera"), (["--camera", "{cam_strings}"], "camera file"),
    (["--camera", "{cam_truncated}"], "camera file"), (["--camera", "{text}"], "camera file"),
    (["--goal", "/nonexistent"], "goal file"), (["--goal", "{empty_goal}"], "goal file"),
    (["--goal", "{small_goal}"], "goal file"), (["--goal", "{corner_goal}"], "--goal"), (["--goal", "{text}"], "goal file"),
    (["--resolution", "0"], "--resolution"), (["--resolution", "101"], "--resolution"), (["--resolution", "x"], "--resolution"),
    (["--bound", "0"], "--bound"), (["--bound", "nan"], "--bound"), (["--plate-half-width", "0"], "--plate-half-width"),
    (["--plate-half-width", "1"], "--plate-half-width"), (["--samples", "0"], "--samples"),
    (["--plate-half-width", "0.05"], "--plate-half-width is the sweep heuristic's"), (["--ckpt", ""], "--ckpt"),
    (["--adam-steps", "0"], "--adam-steps"), (["--seed", "-1"], "--seed"), (["--ckpt", "/nonexistent"], "--ckpt"),
    (["--ckpt", "{flipped_dynamics}"], "damaged"), (["--ckpt", "{regressor}"], "--ckpt"),
    (["--dynamics", "sweep", "--ckpt", "{regressor}"], "--ckpt"), (["--out", "{foreign}"], "--out"),
    (["--out", "push.txt"], "--out"), (["--out", "{file}/x.png"], "--out"), (["--sensor", "kinect"], "--sensor"),
    (["--bin-half-width", "0"], "--bin-half-width"), (["--wall-height", "-1"], "--wall-height"),
    (["--stop-share", "0"], "--stop-share"), (["--stop-share", "1.5"], "--stop-share"),
    (["--wall-height", "0.5"], "--wall-height is read by --calibrate only"),  # was silently unread
    (["--no-wall-pushes", "--bin-half-width", "0.3"], "nothing reads it"),
]
E = [  # evaluate
    (["--join-timeout", "5"], "--join-timeout is read when joining a job"),  # alone: silently unread
    (["--episodes", "0"], "--episodes"), (["--episodes", "x"], "--episodes"), (["--mpc-steps", "0"], "--mpc-steps"),
    (["--methods", "0"], "--methods"), (["--methods", "101"], "--methods"), (["--methods", "foo"], "--methods"),
    (["--methods", "best0"], "--methods"), (["--methods", "50", "50"], "--methods"), (["--methods", "sim", "sim"], "--methods"),
    (["--methods", "50", "050"], "names a method twice"), (["--lr", "1e308"], "--lr"),
    (["--methods", "reranked"], "--methods"), (["--stop-share", "nan"], "--stop-share"),
    (["--task", "sort", "--stop-share", "1.5"], "--stop-share"), (["--task", "sort", "--objective", "x"], "--objective"),
    (["--objective", "hinged"], "--objective"), (["--objective", "paper", "hinge"], "--objective takes one value"),
    (["--task", "redistribute", "--letters", "A B"], "--letters"), (["--letters", ""], "--letters"),
    (["--methods", "cnn", "--cnn-ckpt", "/nonexistent"], "--cnn-ckpt"),
    (["--methods", "cnn", "--cnn-ckpt", "{dynamics}"], "--cnn-ckpt"), (["--methods", "cnn", "--cnn-omega", "0"], "--cnn-omega"),
    (["--best-omega", "0"], "--best-omega"), (["--best-omega", "101"], "--best-omega"),
    (["--methods", "50", "--best-omega", "25"], "--best-omega is read by method bestK"),
    (["--methods", "50", "--cnn-omega", "25"], "--cnn-omega is read by method cnn"),
    (["--methods", "50", "--regressor", "{dynamics}"], "--regressor is read by method adaptive"),
    (["--methods", "50", "adaptive", "--regressor", "/nonexistent"], "--regressor"),
    (["--methods", "adaptive", "--regressor", "{dynamics}"], "--regressor"),
    (["--methods", "adaptive", "--regressor", "{flipped_regressor}"], "--regressor"), (["--kind", "x"], "--kind"),
    (["--sensor", "x"], "--sensor"), (["--task", "sort", "--methods", "oracle"], "--methods"), (["--pieces", "0"], "--pieces"),
    (["--pieces", "100000"], "--pieces"), (["--samples", "0"], "--samples"), (["--adam-steps", "0"], "--adam-steps"),
    (["--pieces", "3", "--methods", "50"], "foreground points"), (["--pieces", "5", "--methods", "10", "oracle"], "ω = 100"),
    (["--horizon", "0"], "--horizon"), (["--horizon", "11"], "--horizon"), (["--time-budget", "0"], "--time-budget"),
    (["--time-budget", "1e-6", "--timing", "{timing20}"], "--time-budget"),
    (["--time-budget", "0.25", "--timing", "{timing}"], "timing table"), (["--timing", "{timing20}"], "--timing"),
    (["--workers", "0"], "--workers"), (["--seed", "-1"], "--seed"), (["--ckpt", "/nonexistent"], "--ckpt"),
    (["--workers", "100000"], "--workers"), (["--backend", "mjx", "--workers", "2"], "--workers"),
    (["--task", "sort", "--letters", "AB"], "--letters"), (["--letters", "XY"], "--letters"),  # Gather draws discs
    (["--ckpt", "{flipped_dynamics}"], "damaged"), (["--dynamics", "x"], "--dynamics"), (["--out", "{file}/x"], "--out"),
    (["--out", "{other_run}"], "--out"), (["--out", "{foreign}"], "--out"), (["--out", "{evaluate_run}"], "--seed 1 there"),
    (["--num-processes", "2"], "--coordinator"), (["--coordinator", "localhost", "--num-processes", "2", "--process-id", "0"], "HOST:PORT"),
    (["--coordinator", "localhost:1", "--num-processes", "2", "--process-id", "0", "--join-timeout", "0"], "--join-timeout"),
]
L = [  # label_resolution
    (["--scenes", "0"], "--scenes"), (["--batch", "3"], "batch"), (["--batch", "1"], "--batch"), (["--evals", "2"], "evals"),
    (["--repeats", "0"], "--repeats"), (["--pieces", "0"], "--pieces"), (["--pieces", "100000"], "--pieces"),
    (["--kind", "x"], "--kind"), (["--seed", "-1"], "--seed"), (["--plan-seed", "-1"], "--plan-seed"),
    (["--mid-episode", "-1"], "--mid-episode"), (["--backend", "x"], "--backend"), (["--samples", "0"], "--samples"),
    (["--adam-steps", "0"], "--adam-steps"), (["--time-budget", "0"], "--time-budget"), (["--horizon", "0"], "--horizon"),
    (["--ckpt", "/nonexistent"], "--ckpt"), (["--ckpt", "{regressor}"], "--ckpt"),
    (["--ckpt", "{flipped_dynamics}"], "damaged"), (["--quick", "--scenes", "16"], "--quick"),
    (["--quick", "--samples", "3"], "--quick"), (["--workers", "0"], "--workers"), (["--out", "{file}"], "--out"),
    (["--out", "{other_run}"], "--out"),
]
D = [  # generate_data
    (["--episodes", "0"], "episodes"), (["--episodes", "-1"], "--episodes"), (["--episodes", "x"], "--episodes"),
    (["--pushes", "0"], "pushes"), (["--pushes", "1000000"], "GiB in memory"), (["--image-size", "100000"], "image_size"),
    (["--worlds", "0"], "worlds"), (["--kinds", "pebble"], "kinds"),
    (["--pieces", "5"], "pieces"), (["--pieces", "10", "5"], "pieces"), (["--pieces", "0", "5"], "pieces"),
    (["--pieces", "100000", "100000"], "pieces"), (["--layouts", "square"], "layouts"), (["--two-kinds", "2"], "two_kinds"),
    (["--two-kinds", "nan"], "--two-kinds"), (["--two-kinds", "0.5", "--kinds", "coffee"], "two_kinds"),
    (["--image-size", "4"], "image_size"), (["--backend", "x"], "backend"), (["--seed", "-1"], "--seed"),
    (["--pieces-step", "0"], "pieces_step"), (["--workers", "0"], "--workers"),
    (["--quick", "--workers", "2"], "--workers"), (["--cpu-workers", "100000"], "--cpu-workers"), (["--out", "{file}"], "--out"),
    (["--out", "{other_run}"], "--out"), (["--out", "{foreign}"], "--out"), (["--planned", "1.5"], "planned"),
    (["--planned", "0.5", "--policy", "/nonexistent"], "--policy"), (["--policy", "shipped"], "--planned above 0"),
]
T = [  # train_dynamics (the data folder is checked after the flags)
    (["--data", "/nonexistent"], "--data"), (["--data", "{data_missing}"], "--data"),
    (["--data", "{data_ok}", "/nonexistent"], "/nonexistent"), (["--data", "{data_damaged}"], "shard"),
    (["--data", "{labels}"], "--data"), (["--data", "{no_config}"], "--data"), (["--data", "{data_short}"], "--data"),
    (["--data", "{data_few}"], "--data"), (["--steps", "0"], "steps"), (["--batch", "0"], "batch"),
    (["--horizon", "0"], "horizon"), (["--lr", "nan"], "--lr"), (["--lr", "1e308"], "lr"), (["--lr", "0"], "lr"), (["--lr", "-1"], "lr"),
    (["--lr-final", "2"], "lr_final"), (["--eval-every", "0"], "eval_every"), (["--ckpt-every", "0"], "ckpt_every"),
    (["--val-batches", "0"], "val_batches"), (["--n-max", "0"], "n_max"), (["--omega-min", "0"], "omega_min"),
    (["--omega-min", "500"], "omega_min"), (["--loss", "huber"], "loss"), (["--held-out-kinds", "pebble"], "held_out_kinds"),
    (["--model", "x"], "--model"), (["--hidden", "0"], "--hidden"), (["--propagation-steps", "0"], "--propagation-steps"),
    (["--grid", "4"], "--grid"), (["--model", "cnn", "--hidden", "8"], "--hidden"), (["--max-minutes", "0"], "--max-minutes"),
    (["--max-minutes", "nan"], "--max-minutes"), (["--recipe", "x"], "--recipe"), (["--seed", "-1"], "--seed"),
    (["--max-points", "0"], "--max-points"), (["--batch", "x"], "--batch"), (["--warmup", "30000"], "warmup"),
    (["--noise", "1"], "noise"), (["--model", "cnn", "--processor", "gns"], "--processor"),
    (["--processor", "mlp"], "--processor"), (["--data", "{data_ok}", "{data_ok}"], "twice"), (["--data", "{data_ok}", "--out", "{train_run}"], "--data /elsewhere/piles there"),
]
TR = [  # train_regressor
    (["--labels", "/nonexistent"], "--labels"), (["--labels", "{labels_missing}"], "--labels"),
    (["--labels", "{labels_damaged}"], "shard"), (["--labels", "{data_few}"], "--labels"),
    (["--labels", "{labels}", "{labels}"], "--labels"), (["--steps", "0"], "--steps"), (["--batch", "0"], "--batch"),
    (["--lr", "nan"], "--lr"), (["--lr", "0"], "--lr"), (["--lr", "1e308"], "--lr"), (["--width", "0"], "--width"), (["--val-every", "0"], "--val-every"),
    (["--seed", "-1"], "--seed"), (["--out", "{other_run}"], "--out"),
]
TO = [  # tradeoff
    ([], "--labels"), (["--labels", "{labels}", "--surface"], "--labels"), (["--labels", "/nonexistent"], "--labels"),
    (["--labels", "{labels_missing}"], "--labels"), (["--labels", "{data_few}"], "--labels"),
    (["--reliability", "{labels}", "{labels}"], "--reliability"), (["--reliability", "{labels}", "/nonexistent"], "--reliability"),
    (["--reliability", "{labels}", "{labels_other_seed}"], "label different scenes"),
    (["--surface", "--scenes", "1"], "--scenes"), (["--surface", "--samples", "0"], "--samples"),
    (["--surface", "--pieces", "0"], "--pieces"), (["--surface", "--pieces", "100000"], "--pieces"),
    (["--surface", "--quick", "--scenes", "4"], "--quick"), (["--surface", "--ckpt", "/nonexistent"], "--ckpt"),
    (["--surface", "--ckpt", "{regressor}"], "--ckpt"), (["--surface", "--workers", "0"], "--workers"),
    (["--surface", "--seed", "-1"], "--seed"), (["--surface", "--out", "{other_run}"], "--out"),
]
SI = [  # simulate
    (["--kind", "pebble"], "--kind"), (["--kind", "coffee", "candy", "almond"], "--kind"), (["--pieces", "0"], "--pieces"),
    (["--pieces", "1", "2"], "--pieces"), (["--pieces", "100000"], "pieces"), (["--pushes", "0"], "--pushes"),
    (["--pushes", "-1"], "--pushes"), (["--layout", "x"], "--layout"), (["--joints", "x"], "--joints"),
    (["--backend", "x"], "--backend"), (["--image-size", "4"], "--image-size"), (["--image-size", "100000"], "--image-size"),
    (["--seed", "-1"], "--seed"), (["--out", "{file}"], "--out"), (["--out", "{other_run}"], "--out"),
]
ED = [  # eval_dynamics
    (["--ckpt", "/nonexistent"], "--ckpt"), (["--ckpt", "{flipped_dynamics}"], "damaged"), (["--ckpt", "{regressor}"], "--ckpt"),
    (["--omegas", "0"], "--omegas"), (["--omegas", "101"], "--omegas"), (["--omegas", "50", "50"], "--omegas"),
    (["--windows", "0"], "--windows"), (["--seed", "-1"], "--seed"), (["--data", "/nonexistent"], "--data"),
    (["--data", "{data_missing}"], "--data"),
]
X = [  # export
    (["--samples", "0"], "--samples"), (["--adam-steps", "0"], "--adam-steps"), (["--horizon", "0"], "--horizon"),
    (["--bound", "0"], "--bound"), (["--bound", "nan"], "--bound"), (["--min-length", "0"], "--min-length"),
    (["--min-length", "0.2", "--max-length", "0.1"], "min_length"), (["--lr", "0"], "--lr"), (["--lr", "nan"], "--lr"), (["--lr", "1e308"], "--lr"),
    (["--goal-samples", "0"], "--goal-samples"), (["--camera", "/nonexistent"], "camera file"),
    (["--camera", "{cam_negative_f}"], "camera file"), (["--platforms", "x"], "--platforms"),
    (["--ckpt", "/nonexistent"], "--ckpt"), (["--ckpt", "{flipped_dynamics}"], "damaged"), (["--ckpt", "{regressor}"], "--ckpt"),
    (["--judge", "/nonexistent"], "--judge"), (["--judge", "{regressor}"], "--judge"),
    (["--out", "{foreign}"], "--out"), (["--out", "planner.txt"], "--out"), (["--out", "{file}/x.jaxexport"], "--out"),
    (["--out", "{foreign}/" + "x" * 245 + ".jaxexport"], "260 bytes"),  # legal alone; its sidecar OUT.json is not
]
GO = [  # goal
    ([], "--disc"), (["--disc", "0", "0"], "--disc"), (["--disc", "0", "0", "0"], "radius"),
    (["--disc", "0", "0", "0.5"], "outside the bin"), (["--disc", "0", "0", "0.1", "--letter", "T"], "not allowed"),
    (["--letter", " "], "--letter"), (["--letter", "T", "--height", "0.9"], "outside"),
    (["--disc", "0", "0", "0.08", "--centre", "0.05", "0"], "--centre is --letter's"),  # was silently unread
    (["--disc", "0", "0", "0.08", "--height", "0.1"], "--height is --letter's"),
    (["--disc", "0", "0", "0.1995"], "outside the bin"),  # beyond the workspace plan accepts (the bin's 0.2 took it)
    (["--mask", "/nonexistent"], "--mask"), (["--mask", "{wide_goal}"], "aspect ratio"), (["--mask", "{empty_goal}"], "no goal"),
    (["--mask", "{full_goal}"], "outside the workspace"),  # goal pixels beyond the bin, as a disc there is refused
    (["--disc", "0", "0", "0.05", "--camera", "{cam_negative_f}"], "camera file"),
    (["--disc", "0", "0", "0.05", "--out", "goal.txt"], "--out"), (["--disc", "0", "0", "0.05", "--out", "{file}/g.png"], "--out"),
    (["--disc", "0", "0", "0.05", "--out", "{foreign}/" + "g" * 252 + ".png"], "256 bytes"),  # a name the file system refuses
]
RO = [  # robot: a goal of another size than the simulator's frames names --image-size, square or not
    (["--goal", "{small_goal}"], "--image-size 64"), (["--goal", "{wide_goal}"], "--goal"),
    (["--image-size", "8"], "--image-size"), (["--steps", "0"], "--steps"),
    (["--replay", "{replay_damaged}", "--goal", "{goal}"], "001"),  # refused before planning frame 000
    (["--replay", "{replay_damaged}", "--sensor", "realsense"], "a --replay's frames are read as they were recorded"),
    (["--replay", "{replay_damaged}", "--image-size", "256", "--pieces", "50"], "--pieces, --image-size: the"),
    (["--resolution", "oracle"], "--resolution"), (["--resolution", "best5"], "--resolution"),  # need the simulator
    (["--regressor", "{regressor}"], "--regressor"),  # a fixed ω reads no regressor
    (["--resolution", "adaptive", "--regressor", "/nonexistent"], "--regressor"), (["--judge", "/nonexistent"], "--judge"),
    # frames the camera's noise and holes thin below ω: refused before compiling (the exact frame shows more points)
    (["--pieces", "20", "--image-size", "64"], "--image-size"), (["--pieces", "20", "--image-size", "64", "--sensor",
                                                                   "none"], "--image-size"),
]
CASES = ([("gather", a, n) for a, n in G] + [("redistribute", a, n) for a, n in R] + [("sort", a, n) for a, n in S]
         + [("plan", FRAME + a, n) for a, n in P] + [("evaluate", a, n) for a, n in E]
         + [("label_resolution", a, n) for a, n in L] + [("generate_data", a, n) for a, n in D]
         + [("train_dynamics", ["--data", "{data_few}", *a], n) for a, n in T]
         + [("train_regressor", ["--labels", "{labels}", *a], n) for a, n in TR] + [("tradeoff", a, n) for a, n in TO]
         + [("simulate", a, n) for a, n in SI] + [("eval_dynamics", ["--ckpt", "{dynamics}", "--data", "{data_few}", *a], n)
                                                  for a, n in ED]
         + [("export", a, n) for a, n in X] + [("goal", a, n) for a, n in GO] + [("robot", a, n) for a, n in RO])
OUT_FILE = {"plan": "push.png", "export": "planner.jaxexport", "goal": "goal.png"}


def test_the_table_is_large():
    assert len(CASES) >= 250


def _snapshot(folder: str) -> dict:
    return {os.path.join(r, n): open(os.path.join(r, n), "rb").read() for r, _, ns in os.walk(folder) for n in ns}


@pytest.mark.parametrize("command, argv, named", CASES, ids=[f"{c}:{' '.join(a)[-60:]}" for c, a, _ in CASES])
def test_bad_input_is_one_line_naming_it_exit_2_and_writes_nothing(command, argv, named, fx, tmp_path, capsys):
    out = str(tmp_path / "out" / OUT_FILE.get(command, ""))
    argv = [a.format(**fx) for a in argv]
    if "--out" not in argv:
        argv += ["--out", out]
    before = {f: _snapshot(fx[f]) for f in ("other_run", "gather_run", "train_run", "evaluate_run", "foreign")}
    main = importlib.import_module(f"dynres_jax.commands.{command}").main
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2, err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith(("usage:", " "))]
    assert len(lines) == 1 and "error:" in lines[0], err
    assert named in lines[0], (named, lines[0])
    assert "Traceback" not in err
    assert not os.path.exists(tmp_path / "out")
    assert before == {f: _snapshot(fx[f]) for f in before}


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="needs a machine without CUDA")
def test_a_platform_that_cannot_start_inside_a_jitted_goal_is_one_line(fx, tmp_path):
    """plan meets JAX_PLATFORMS=cuda first inside a jitted function (the goal's fields), where JAX's traceback
    filtering hides the backend's frame: still the one line naming the variable, exit status 2 (it was a traceback)."""
    import subprocess
    import sys

    argv = [a.format(**fx) for a in FRAME] + ["--samples", "4", "--adam-steps", "2", "--out", str(tmp_path / "p.png")]
    done = subprocess.run([sys.executable, "-m", "experiments.plan", *argv], capture_output=True, text=True,
                          env={**os.environ, "JAX_PLATFORMS": "cuda"}, timeout=300,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1 and "JAX_PLATFORMS='cuda'" in lines[0], done.stderr[-2000:]
