"""Data generation: shards and summary, resume after a kill, multi-device sharding, training targets, bad input.

One tiny generation (6 coffee beans, 48 x 48, 2 short pushes, 7 episodes in 2 shards of 4 worlds) compiles once and
serves every test; the 4-device run is a subprocess started first, so it runs beside the main process's work.
"""

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import textwrap
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.config import CameraConfig, SceneConfig, SimConfig
from dynres_jax.errors import InputError
from dynres_jax.io import files, shards
from dynres_jax.learn import data, targets
from dynres_jax.perception import sample_particles
from dynres_jax.sim import engines
from dynres_jax.sim.camera import Observation
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import process_pool

QUICK = data.quick_config(episodes=7)  # shard 0: 4 episodes, shard 1: 3 (the last shard is cut to fit)
N_MAX = 24
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

MULTI_DEVICE_SCRIPT = textwrap.dedent("""
    import sys
    import jax
    from dynres_jax.learn import data
    from dynres_jax.commands.generate_data import main
    assert len(jax.devices()) == 4, jax.devices()
    try:
        data.generate(data.quick_config(worlds=6), sys.argv[1] + "/bad", progress=False)
    except ValueError as e:
        print("BAD-WORLDS:", e)
    main(["--quick", "--episodes", "4", "--no-progress", "--out", sys.argv[1] + "/run"])
""")


@pytest.fixture(scope="module")
def multi_device(tmp_path_factory):
    """The quick run's first shard made on 4 forced host devices, in a subprocess started before anything else."""
    out = tmp_path_factory.mktemp("multi")
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    proc = subprocess.Popen([sys.executable, "-c", MULTI_DEVICE_SCRIPT, str(out)], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    yield proc, out
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


@pytest.fixture(scope="module")
def generated(tmp_path_factory, multi_device):
    out = str(tmp_path_factory.mktemp("gen") / "run")
    return out, data.generate(QUICK, out, progress=False)


def read(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


# ----------------------------------------------------------------------------------------------------------------
# Generation
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_generation_writes_shards_and_summary(generated):
    out, summary = generated
    assert sorted(os.listdir(out)) == ["config.json", "shard_00000.npz", "shard_00001.npz", "summary.json"]
    with open(os.path.join(out, "summary.json")) as f:
        written = json.load(f)
    assert written.pop("shards_by_engine") == summary["shards_by_engine"] == {"mjx": 2}
    assert written == pytest.approx({k: v for k, v in summary.items() if k != "shards_by_engine"})
    assert summary["shards"] == 2 and summary["episodes"] == 7 and summary["frames"] == 7 * 3
    assert summary["broken_dropped"] == 0 and summary["shards_written"] == 2 and summary["samples_per_s"] > 0
    env = PileEnv(data.shard_sim_config(QUICK, 0), backend="mujoco", render=False)
    for i, e in enumerate((4, 3)):
        s = read(shards.shard_path(out, i))
        expect = dict(depth=((e, 3, 48, 48), np.float16), piece=((e, 3, 48, 48), np.int16),
                      pos=((e, 3, 6, 3), np.float32), mat=((e, 3, 6, 3, 3), np.float32),
                      action=((e, 2, 4), np.float32), broken=((e, 3), np.bool_), episode=((e,), np.int64),
                      kind=((6,), np.int16))
        for name, (shape, dtype) in expect.items():
            assert s[name].shape == shape and s[name].dtype == dtype, name
        np.testing.assert_array_equal(s["episode"], 4 * i + np.arange(e))
        assert int(s["shard"]) == i and int(s["simulated"]) == e and int(s["dropped"]) == 0
        assert s["kind_names"].tolist() == ["coffee"] and not s["broken"].any()
        assert SimConfig.from_json(str(s["sim_config"])) == data.shard_sim_config(QUICK, i)
        # rotations orthonormal; every piece seen in every frame; table at 1 m, wall tops at 0.96 m, pieces between
        gram = np.einsum("...ji,...jk->...ik", s["mat"], s["mat"])
        np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-5)
        for ep in range(e):
            for f in range(3):
                assert set(np.unique(s["piece"][ep, f])) == set(range(-1, 6))
        fg = s["piece"] >= 0
        assert np.all(s["depth"][~fg] >= 0.959) and np.all((s["depth"][fg] > 0.98) & (s["depth"][fg] < 0.999))
        # pushes end in the workspace and start there or outside a wall, lengths within the push config; the pile moved
        a = s["action"]
        assert np.all(np.abs(a[..., 2:]) <= env.action_bound + 1e-6)
        start = np.abs(a[..., :2])
        assert np.all((start <= env.action_bound + 1e-6) | (np.abs(start - env.reach) < 1e-6))
        length = np.linalg.norm(a[..., 2:] - a[..., :2], axis=-1)
        assert np.all(length <= QUICK.sim.push.max_length + 1e-6)
        assert np.abs(s["pos"][:, -1] - s["pos"][:, 0]).max() > 0.005


def test_finish_shard_cuts_and_drops_broken():
    w, f = 4, 3
    arrays = dict(broken=np.zeros((w, f), bool), episode=np.arange(w), pos=np.arange(w * 2.0).reshape(w, 2),
                  kind=np.zeros(5, np.int16))
    arrays["broken"][1, 2] = arrays["broken"][3, 1:] = True  # world 3 broke but is past the cut
    kept = data.finish_shard(arrays, n_keep=3, drop_broken=True)
    np.testing.assert_array_equal(kept["episode"], [0, 2])
    np.testing.assert_array_equal(kept["pos"], arrays["pos"][[0, 2]])
    assert kept["kind"].shape == (5,) and int(kept["dropped"]) == 1 and int(kept["simulated"]) == 3
    flagged = data.finish_shard(arrays, n_keep=3, drop_broken=False)
    np.testing.assert_array_equal(flagged["episode"], [0, 1, 2])
    assert int(flagged["dropped"]) == 0 and flagged["broken"][1, 2]


@pytest.mark.slow  # 93 s on the 2-core CPU: CI's second tier
def test_resume_rewrites_missing_shard_identically(generated, tmp_path):
    original, _ = generated
    out = str(tmp_path / "run")
    shutil.copytree(original, out)  # copy2: mtimes kept
    first, second = shards.shard_path(out, 0), shards.shard_path(out, 1)
    with open(second, "rb") as f:
        second_bytes = f.read()
    os.unlink(second)  # the run was killed before shard 1 ...
    leftover = os.path.join(out, files.tmp_prefix(second) + "x7k2")
    with open(leftover, "wb") as f:  # ... while writing it
        f.write(b"half a zip")
    mtime = os.stat(first).st_mtime_ns
    summary = data.generate(QUICK, out, progress=False)
    assert summary["shards_written"] == 1 and summary["shards_skipped"] == 1 and summary["episodes"] == 7
    assert not os.path.exists(leftover) and os.stat(first).st_mtime_ns == mtime
    with open(second, "rb") as f:
        assert f.read() == second_bytes  # byte-identical: same arrays, fixed zip timestamps
    for name, value in read(second).items():
        np.testing.assert_array_equal(value, read(shards.shard_path(original, 1))[name], err_msg=name)
    before = {name: open(os.path.join(out, name), "rb").read() for name in sorted(os.listdir(out))}
    assert data.generate(QUICK, out, progress=False)["shards_written"] == 0  # complete: nothing to do ...
    assert {name: open(os.path.join(out, name), "rb").read() for name in sorted(os.listdir(out))} == before
    # ... and no file changed, summary.json's timings neither: the folder's hash (a training run's input) holds
    with pytest.raises(ValueError, match="another DataConfig"):
        data.generate(data.replace(QUICK, seed=1), out, progress=False)
    with open(os.path.join(out, "config.json")) as f:
        begun = json.load(f)
    del begun["scenes"]  # a run begun before DataConfig.scenes existed resumes, as of the field's default only
    with open(os.path.join(out, "config.json"), "w") as f:
        json.dump(begun, f)
    assert data.generate(QUICK, out, progress=False)["shards_written"] == 0
    with pytest.raises(ValueError, match="another DataConfig"):
        data.generate(data.replace(QUICK, scenes=2), out, progress=False)


def test_a_part_makes_only_its_shards_bit_for_bit(generated, tmp_path):
    """Part (1, 2) alone writes shard 1 exactly as the whole run did; part 0's half-written file is left alone."""
    original, _ = generated
    out = str(tmp_path / "parts")
    os.makedirs(out)
    other = os.path.join(out, files.tmp_prefix(shards.shard_path(out, 0)) + "a1b2")  # part 0 writes shard 0 now
    with open(other, "wb") as f:
        f.write(b"part 0 at work")
    summary = data.generate(QUICK, out, progress=False, part=(1, 2))
    assert sorted(os.listdir(out)) == sorted(["config.json", "shard_00001.npz", "summary.json",
                                              os.path.basename(other)])
    assert summary["shards_written"] == 1 and summary["shards_skipped"] == 0
    with open(shards.shard_path(out, 1), "rb") as a, open(shards.shard_path(original, 1), "rb") as b:
        assert a.read() == b.read()


def test_multi_device_run_matches_single_device(generated, multi_device):
    proc, out = multi_device
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr[-3000:]
    assert "BAD-WORLDS: DataConfig.worlds=6 must be a multiple of the device count 4" in stdout
    summary = json.loads(stdout[stdout.index("{"):])
    assert summary["devices"] == 4 and summary["episodes"] == 4
    many, one = read(shards.shard_path(str(out / "run"), 0)), read(shards.shard_path(generated[0], 0))
    assert many.keys() == one.keys()
    for name in ("episode", "kind", "kind_names", "sim_config", "broken", "simulated", "dropped"):
        np.testing.assert_array_equal(many[name], one[name], err_msg=name)
    for name in ("depth", "piece", "pos", "mat"):  # the reset piles: bit-identical
        np.testing.assert_array_equal(many[name][:, 0], one[name][:, 0], err_msg=name)
    # After pushes, not bit-identical: XLA compiles another per-device batch (1 world, not 4), float32 rounding
    # differs and contacts amplify it (measured: 6e-5 m after 2 pushes).
    np.testing.assert_allclose(many["action"], one["action"], atol=1e-6)
    np.testing.assert_allclose(many["pos"], one["pos"], atol=1e-3)
    np.testing.assert_allclose(many["mat"], one["mat"], atol=1e-2)
    np.testing.assert_allclose(many["depth"].astype(np.float32), one["depth"].astype(np.float32), atol=3e-3)
    assert np.mean(many["piece"] == one["piece"]) > 0.99


# ----------------------------------------------------------------------------------------------------------------
# Training targets
# ----------------------------------------------------------------------------------------------------------------
def random_rotation(rng):
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.fixture(scope="module")
def placed():
    """Almonds and candies (rotated capsules and boxes) placed apart by hand, settled and rendered (C MuJoCo)."""
    cfg = SimConfig(scene=SceneConfig(kinds=("almond", "candy"), pieces=(3, 3)),
                    camera=CameraConfig(width=64, height=64))
    env = PileEnv(cfg, backend="mujoco")
    xy = np.array([[-0.1, -0.1], [0.0, -0.1], [0.1, -0.1], [-0.1, 0.08], [0.0, 0.08], [0.1, 0.08]])
    state = env.place(xy, yaw=np.array([0.3, 1.2, -0.7, 0.5, -1.0, 2.0]))
    return env, state


def test_attach_and_trajectory_match_numpy_rigid_motion(placed):
    env, state = placed
    pos0, mat0 = np.asarray(state.pos), np.asarray(state.mat)
    p = sample_particles(state.obs, env.camera, 20, jax.random.PRNGKey(0), N_MAX)
    particles = np.array(p.positions)
    # add a particle over bare table (nearest centre: piece 4) and a masked one
    particles[20] = pos0[4] + np.array([0.0, -0.05, 0.0])
    mask = np.asarray(p.mask).copy()
    mask[20] = True
    u, v = np.floor(np.asarray(env.camera.world_to_pixel(particles[20])[0])).astype(int)
    assert state.obs.piece[v, u] == -1
    index, local = targets.attach_particles(particles, mask, pos0, mat0, state.obs.piece, env.camera)
    index, local = np.asarray(index), np.asarray(local)

    # independent: pieces are 10 cm apart, so a particle's piece is the one with the nearest centre
    nearest = np.argmin(np.linalg.norm(particles[:, None, :2] - pos0[None, :, :2], axis=-1), axis=1)
    np.testing.assert_array_equal(index[mask], nearest[mask])
    assert np.all(index[~mask] == -1) and np.all(local[~mask] == 0)
    assert set(index[:20]) == set(range(6))  # 20 FPS particles cover every piece
    footprint = env.scene.footprint[index[:20]]
    assert np.all(np.linalg.norm(particles[:20, :2] - pos0[index[:20], :2], axis=-1) <= footprint + 0.004)

    # known rigid motions: piece i at step k rotated by Q[k, i] about its centre and moved by T[k, i]
    rng = np.random.default_rng(0)
    k_steps = 4
    Q = np.array([[np.eye(3) if k == 0 else random_rotation(rng) for _ in range(6)] for k in range(k_steps)])
    T = np.concatenate([np.zeros((1, 6, 3)), rng.uniform(-0.05, 0.05, (k_steps - 1, 6, 3))])
    pos_seq = pos0[None] + T
    mat_seq = np.einsum("kiab,ibc->kiac", Q, mat0)
    traj = np.asarray(targets.particle_trajectory(index, local, pos_seq.astype(np.float32), mat_seq.astype(np.float32)))
    m = mask
    expect = np.einsum("knab,nb->kna", Q[:, nearest[m]], particles[m] - pos0[nearest[m]]) + pos_seq[:, nearest[m]]
    np.testing.assert_allclose(traj[:, m], expect, atol=1e-5)
    np.testing.assert_allclose(traj[0, m], particles[m], atol=1e-6)
    assert np.all(traj[:, ~m] == 0)

    # padding pieces are never chosen, even where one sits right under a background particle
    pad_pos = np.concatenate([pos0, particles[20:21]])
    pad_mat = np.concatenate([mat0, np.eye(3)[None]])
    index_pad, _ = targets.attach_particles(particles, mask, pad_pos, pad_mat, state.obs.piece, env.camera,
                                         piece_mask=np.arange(7) < 6)
    np.testing.assert_array_equal(np.asarray(index_pad), index)


def test_attach_is_vmappable_and_masked_entries_are_inert(placed):
    env, state = placed
    p = sample_particles(state.obs, env.camera, 10, jax.random.PRNGKey(1), N_MAX)
    junk = p.positions.at[10:].set(jax.random.uniform(jax.random.PRNGKey(2), (N_MAX - 10, 3)))
    attach = lambda x: targets.attach_particles(x, p.mask, state.pos, state.mat, state.obs.piece, env.camera)
    index, local = jax.vmap(attach)(jnp.stack([p.positions, junk]))
    np.testing.assert_array_equal(index[0], index[1])
    np.testing.assert_array_equal(local[0], local[1])
    assert np.all(index[0, 10:] == -1) and np.all(index[0, :10] >= 0)


def test_several_folders_load_as_one_data_set(generated, tmp_path):
    """load_shards of [A, B] is A's episodes then B's (here B is a copy of A with its second shard missing)."""
    out, _ = generated
    other = tmp_path / "other"
    shutil.copytree(out, other)
    os.unlink(other / "shard_00001.npz")
    config = json.loads((other / "config.json").read_text())
    (other / "config.json").write_text(json.dumps(dict(config, episodes=config["worlds"])))  # one shard promised
    one, both = targets.load_shards(out), targets.load_shards([out, str(other)])
    assert len(both) == len(one) + 4
    np.testing.assert_array_equal(both.episode, np.concatenate([one.episode, one.episode[:4]]))
    np.testing.assert_array_equal(both.pos, np.concatenate([one.pos, one.pos[:4]]))
    val = targets.load_shards([out, str(other)], "val", val_every=3)
    np.testing.assert_array_equal(val.episode, [2, 5, 2])


def test_load_split_and_samples(generated):
    out, _ = generated
    everything = targets.load_shards(out)
    train, val = targets.load_shards(out, "train", val_every=3), targets.load_shards(out, "val", val_every=3)
    assert len(everything) == 7 and everything.pushes == 2 and everything.camera.width == 48
    np.testing.assert_array_equal(val.episode, [2, 5])
    np.testing.assert_array_equal(np.sort(np.concatenate([train.episode, val.episode])), np.arange(7))
    assert everything.kind.shape == (7, 6) and np.all(everything.kind == data.KIND_NAMES.index("coffee"))
    assert everything.piece_mask.all()

    horizon, rows, t = 2, np.array([0, 3, 4, 6]), np.zeros(4, int)
    win = targets.windows(everything, rows, t, horizon)
    assert win.pos.shape == (4, 3, 6, 3) and win.action.shape == (4, 2, 4) and win.depth.dtype == np.float32
    # 6 beans at 48 x 48 pixels make 7 to 13 foreground points, so ω stays at most 6
    omegas, keys = jnp.array([2, 3, 5, 6]), jax.random.split(jax.random.PRNGKey(0), 4)
    make = jax.jit(jax.vmap(lambda w, o, k: targets.make_sample(w, o, k, everything.camera, N_MAX)))
    sample = jax.tree.map(np.asarray, make(win, omegas, keys))
    assert sample.positions.shape == (4, 3, N_MAX, 3) and np.all(sample.error == 0)
    np.testing.assert_array_equal(sample.mask.sum(1), omegas)
    np.testing.assert_array_equal(sample.action, everything.action[rows, :2])
    coffee = data.KIND_NAMES.index("coffee")
    assert np.all(sample.kind[sample.mask] == coffee) and np.all(sample.kind[~sample.mask] == -1)
    reach = 0.007 + 1.5 * 0.46 / 48  # a bean's radius plus a pixel diagonal
    for b in range(4):
        m = sample.mask[b]
        # frame t: the particles h gives
        obs = Observation(win.depth[b], win.piece[b], np.zeros_like(win.piece[b]), np.zeros((48, 48, 3), np.uint8))
        direct = sample_particles(obs, everything.camera, int(omegas[b]), keys[b], N_MAX)
        np.testing.assert_allclose(sample.positions[b, 0][m], np.asarray(direct.positions)[m], atol=1e-6)
        assert np.all(sample.positions[b][:, ~m] == 0)
        # later frames: each particle carried rigidly by one of the pieces it lies over (NumPy, R_k R_0^T)
        for p0, track in zip(sample.positions[b, 0][m], sample.positions[b][:, m].transpose(1, 0, 2), strict=True):
            near = np.flatnonzero(np.linalg.norm(win.pos[b, 0, :, :2] - p0[:2], axis=-1) <= reach)
            rigid = [np.einsum("kab,cb,c->ka", win.mat[b, :, j], win.mat[b, 0, j], p0 - win.pos[b, 0, j])
                     + win.pos[b, :, j] for j in near]
            assert any(np.allclose(track, r, atol=1e-5) for r in rigid)


def test_an_empty_split_is_named(generated):
    with pytest.raises(ValueError, match="'val' split .* is empty"):
        targets.load_shards(generated[0], "val", val_every=100)


def test_load_pads_shards_with_fewer_pieces(generated, tmp_path):
    """A shard of 4 almonds beside shards of 6 coffee beans: pieces padded, masked, kinds mapped to KIND_NAMES."""
    out = str(tmp_path / "mixed")
    shutil.copytree(generated[0], out)
    s = read(shards.shard_path(out, 1))
    sim = SimConfig.from_json(str(s["sim_config"]))
    sim = data.replace(sim, scene=data.replace(sim.scene, kinds=("almond",), pieces=(4,)))
    s.update(pos=s["pos"][:, :, :4], mat=s["mat"][:, :, :4], kind=s["kind"][:4], kind_names=np.array(["almond"]),
             piece=np.where(s["piece"] < 4, s["piece"], -1).astype(np.int16), episode=s["episode"] + 100,
             sim_config=np.array(json.dumps(dataclasses.asdict(sim))))
    shards.save_npz(os.path.join(out, "shard_00002.npz"), s)
    with pytest.raises(ValueError, match="shard_00002.npz lies beyond the 2 shards"):
        targets.load_shards(out)
    with open(os.path.join(out, "config.json")) as f:
        config = json.load(f)
    with open(os.path.join(out, "config.json"), "w") as f:  # the set now promises three shards
        json.dump(dict(config, episodes=config["episodes"] + config["worlds"]), f)
    d = targets.load_shards(out)
    assert len(d) == 10 and d.pos.shape[2] == 6
    assert d.piece_mask[:7].all() and np.all(d.piece_mask[7:] == (np.arange(6) < 4))
    assert np.all(d.kind[7:, :4] == data.KIND_NAMES.index("almond")) and np.all(d.kind[7:, 4:] == -1)
    assert np.all(d.pos[7:, :, 4:] == 0) and np.all(d.mat[7:, :, 4:] == np.eye(3))
    np.testing.assert_array_equal(d.pos[7:, :, :4], s["pos"])
    win = targets.windows(d, [8], [0], horizon=2)
    sample = targets.make_sample(jax.tree.map(lambda x: x[0], win), 3, jax.random.PRNGKey(0), d.camera, N_MAX)
    assert int(sample.error) == 0 and np.all(np.asarray(sample.kind)[:3] == data.KIND_NAMES.index("almond"))

    # Holding a kind out keeps exactly the episodes with no piece of it (an episode loop as the reference).
    for held, kept in ((("almond",), "coffee"), (("coffee",), "almond"), ((), None)):
        rest = targets.without_kinds(d, held)
        want = [e for e in range(len(d)) if not any(data.KIND_NAMES[k] in held for k in d.kind[e] if k >= 0)]
        np.testing.assert_array_equal(rest.episode, d.episode[want])
        np.testing.assert_array_equal(rest.pos, d.pos[want])
        np.testing.assert_array_equal(rest.action, d.action[want])
        if kept:
            assert {data.KIND_NAMES[k] for k in np.unique(rest.kind[rest.piece_mask])} == {kept}
    with pytest.raises(ValueError, match="nothing is left"):
        targets.without_kinds(d, ("coffee", "almond"))
    with pytest.raises(ValueError, match="unknown piece kind"):
        targets.without_kinds(d, ("pebble",))


# ----------------------------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad, message", [
    (dict(episodes=0), "episodes"), (dict(episodes=-3), "episodes"), (dict(worlds=0), "worlds"),
    (dict(pushes=0), "pushes"), (dict(pieces=(50, 40)), "pieces"), (dict(kinds=("pebble",)), "kinds"),
    (dict(layouts=("heap",)), "layouts"), (dict(kinds=("coffee",), two_kinds=0.5), "two_kinds"),
    (dict(image_size=4), "image_size"), (dict(scenes=-1), "scenes"),
])
def test_bad_config_names_the_field(bad, message):
    with pytest.raises(ValueError, match=message):
        data.DataConfig(**bad)


def test_worlds_must_divide_by_devices(tmp_path):
    cpu = jax.devices()[0]
    with pytest.raises(ValueError, match="worlds=3 must be a multiple of the device count 2"):
        data.generate(data.quick_config(worlds=3), str(tmp_path), devices=[cpu, cpu])
    assert not os.listdir(tmp_path)


def test_bad_windows_and_split(generated):
    d = targets.load_shards(generated[0])
    with pytest.raises(ValueError, match="horizon"):
        targets.windows(d, [0], [0], horizon=3)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        targets.windows(d, [0], [2], horizon=1)
    with pytest.raises(ValueError, match="split"):
        targets.load_shards(generated[0], "test")
    with pytest.raises(ValueError, match="no config.json, so no data or label set"):
        targets.load_shards(os.path.dirname(generated[0]) + "/nothing")


def test_cli_rejects_bad_flags(capsys):
    from dynres_jax.commands.generate_data import main

    with pytest.raises(SystemExit):
        main(["--out", "/nonexistent/x", "--quick", "--episodes", "0"])
    assert "DataConfig.episodes must be a positive int" in capsys.readouterr().err


@pytest.mark.slow
def test_c_backend_in_worker_processes_equals_in_process():
    """Backend "mujoco": episodes run in spawned worker processes equal the same episodes run here, frame by frame
    (poses, renders, pushes), and every frame is a settled, unbroken pile inside the bin."""
    cfg = data.quick_config(backend="mujoco", worlds=2, pushes=1)
    here = data.simulate_shard(cfg, 0)
    with process_pool(2) as pool:
        there = data.simulate_shard(cfg, 0, pool=pool)
    for name in ("pos", "mat", "depth", "piece", "action", "broken"):
        np.testing.assert_array_equal(here[name], there[name], err_msg=name)
    assert here["depth"].shape == (2, 2, 48, 48) and not here["broken"].any()
    assert np.abs(here["pos"][..., :2]).max() < cfg.sim.scene.bin_half_width
    with pytest.raises(ValueError, match="backend"):
        data.DataConfig(backend="flex")


def test_engines_of_a_run():
    """C MuJoCo by default; "auto" resolves before the run (config.json names the engine used); "mjx-fast" shards
    carry the fast scene's physics for their kinds, the rest of the scene as drawn."""
    assert data.DataConfig().backend == "mujoco"
    assert data.concrete(data.DataConfig(backend="auto")).backend == (
        "mjx-fast" if jax.default_backend() == "gpu" else "mujoco")
    cfg = data.DataConfig(backend="mjx-fast", kinds=("candy", "coffee"), two_kinds=0.0)
    for shard in range(4):
        fast = data.shard_sim_config(cfg, shard)
        plain = data.shard_sim_config(data.replace(cfg, backend="mujoco"), shard)
        assert fast.scene == SceneConfig.fast(plain.scene.kinds, plain.scene.pieces)
        assert (fast.pile, fast.camera) == (plain.pile, plain.camera)


def test_a_run_of_few_scenes_cycles_them_and_meets_each_in_one_stretch(generated, tmp_path, monkeypatch):
    """DataConfig.scenes = S: shard i takes scene i mod S (S of at least the shard count draws what a scene per shard
    draws); generate hands its engine the shards grouped by scene, in shard order within a scene, so a JAX engine
    builds and compiles each scene once."""
    cfg = data.DataConfig(episodes=48, worlds=4, scenes=3)
    drawn = [data.shard_sim_config(cfg, i) for i in range(12)]
    assert all(drawn[i] == drawn[i % 3] for i in range(12)) and len({s.to_json() for s in drawn}) == 3
    per_shard = [data.shard_sim_config(data.replace(cfg, scenes=0), i) for i in range(12)]
    assert per_shard == [data.shard_sim_config(data.replace(cfg, scenes=12), i) for i in range(12)]
    assert len({s.to_json() for s in per_shard}) > 3
    assert data.by_scene(cfg, [1, 2, 3, 4, 5, 7, 9]) == [1, 4, 7, 2, 5, 3, 9]  # scenes 1, 2, 0 by first shard

    order, canned = [], read(shards.shard_path(generated[0], 0))

    def simulate(config, i, *args, **kwargs):  # the order shards are made in; every one the same four worlds
        order.append(i)
        return dict(canned)

    monkeypatch.setattr(data, "simulate_shard", simulate)
    two = data.quick_config(episodes=24, kinds=("coffee", "almond"), pieces=(6, 12), pieces_step=6, scenes=2, seed=1)
    assert data.shard_sim_config(two, 0) != data.shard_sim_config(two, 1)
    data.generate(two, str(tmp_path / "two"), progress=False)
    assert order == [0, 2, 4, 1, 3, 5]


def test_fill_makes_each_shard_once_and_stops_on_an_error():
    made, lock = [], threading.Lock()

    def producer(name, fail_at=None):
        def produce(i):
            time.sleep(0.01)
            if i == fail_at:
                raise RuntimeError(f"shard {i}")
            with lock:
                made.append((name, i))
        return produce

    shards.fill(list(range(12)), [producer("a"), producer("b")])
    assert sorted(i for _, i in made) == list(range(12)) and {n for n, _ in made} == {"a", "b"}
    made.clear()
    with pytest.raises(RuntimeError, match="shard 3"):
        shards.fill(list(range(40)), [producer("a", fail_at=3), producer("b", fail_at=3)])
    assert len(made) < 10  # the other producer stopped taking shards


@pytest.mark.slow  # about 25-40 s on a 2-core CPU: CI's second tier
def test_c_workers_fill_shards_beside_a_jax_engine_of_c_physics(generated, tmp_path, monkeypatch):
    """``cpu_workers``: C workers take shards from the same list as the JAX engine (here MJX, its row marked as of C's
    physics, as Warp's is). Each engine makes one of the two shards; each shard is what its engine makes alone (the
    MJX one bit for bit the plain run's, the C one the C engine's in this process), records its engine, and both
    carry the same scene. An engine of another physics is refused."""
    original, _ = generated
    monkeypatch.setitem(engines.ENGINES, "mjx", dataclasses.replace(engines.ENGINES["mjx"], c_physics=True))
    simulate = data.simulate_shard

    def slow(cfg, *args, **kwargs):  # every shard takes a second, so each producer takes one before the other ends
        time.sleep(1.0)
        return simulate(cfg, *args, **kwargs)

    monkeypatch.setattr(data, "simulate_shard", slow)
    out = str(tmp_path / "mixed")
    summary = data.generate(QUICK, out, progress=False, cpu_workers=1)
    assert summary["shards_by_engine"] == {"mjx": 1, "mujoco": 1} and summary["episodes"] == 7
    c_config = data.replace(QUICK, backend="mujoco")
    for i in range(2):
        made = read(shards.shard_path(out, i))
        plain = read(shards.shard_path(original, i))
        assert made["sim_config"] == plain["sim_config"]
        if str(made["engine"]) == "mjx":
            for name, value in plain.items():
                np.testing.assert_array_equal(made[name], value, err_msg=name)
        else:
            assert str(made["engine"]) == "mujoco"
            alone = data.finish_shard(simulate(c_config, i), len(made["episode"]), QUICK.drop_broken)
            for name in ("pos", "depth", "action", "episode"):
                np.testing.assert_array_equal(made[name], alone[name], err_msg=name)
    with pytest.raises(ValueError, match="C's physics"):
        data.generate(data.replace(QUICK, backend="mjx-fast"), str(tmp_path / "fast"), progress=False, cpu_workers=1)


def test_check_helpers(monkeypatch):
    """The C helpers' config: the run's with backend "mujoco" (nothing else changed), None for no helpers; refused
    beside an engine of other physics or of worker processes, for a negative count, and for on-policy data."""
    monkeypatch.setitem(engines.ENGINES, "mjx", dataclasses.replace(engines.ENGINES["mjx"], c_physics=True))
    helper = data.check_helpers(QUICK, 3)
    assert helper == data.replace(QUICK, backend="mujoco") and QUICK.backend == "mjx"
    assert data.check_helpers(QUICK, 0) is None
    for config, workers in ((data.replace(QUICK, backend="mjx-fast"), 1), (data.replace(QUICK, backend="mujoco"), 1),
                            (QUICK, -1)):
        with pytest.raises(ValueError, match="C's physics"):
            data.check_helpers(config, workers)
    with pytest.raises(ValueError, match="random pushes only"):
        data.check_helpers(data.replace(QUICK, planned=0.5), 2)
    assert data.check_helpers(data.replace(QUICK, planned=0.5), 0) is None



def test_a_damaged_or_other_config_json_is_refused_by_name(tmp_path):
    """A data folder whose config.json was edited (another DataConfig) or truncated: an InputError (one line at the
    command) naming it, before any shard is simulated."""
    for i, (text, words) in enumerate([('{"seed": 12345}', "another DataConfig"), ('{"seed": 0, "worl', "damaged")]):
        out = tmp_path / f"d{i}"
        out.mkdir()
        (out / "config.json").write_text(text)
        with pytest.raises(InputError, match=words):
            data.generate(QUICK, str(out), progress=False)
        assert not list(out.glob("shard_*"))
