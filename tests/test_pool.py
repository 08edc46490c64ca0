"""WorldPool: C MuJoCo worlds in worker processes behave as PileEnv's C backend world by world."""

import os
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.config import PushConfig, SceneConfig, SimConfig
from dynres_jax.sim import engines
from dynres_jax.sim.env import PileEnv, make_env
from dynres_jax.sim.physics import Poses
from dynres_jax.sim.physics.c import CPhysics
from dynres_jax.sim.physics.mjx import MJXPhysics, mjx
from dynres_jax.sim.pool import MJXPool, WorldPool, make_pool, process_pool

SIM = SimConfig(scene=SceneConfig(pieces=(6,)), push=PushConfig(max_length=0.08, settle_time=0.04))


@pytest.fixture(scope="module")
def processes():
    with process_pool(2) as p:
        yield p


def test_pool_reset_and_push_equal_one_world_at_a_time(processes):
    pool, env = WorldPool(SIM, processes), PileEnv(SIM, backend="mujoco")
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    states = pool.reset(keys)
    centre = np.asarray(states.pos)[:, :, :2].mean(1)  # push through each pile, along x, y and a diagonal
    actions = np.concatenate([centre - [[0.04, 0], [0, 0.04], [0.03, 0.03]],
                              centre + [[0.03, 0], [0, 0.03], [0.02, 0.02]]], 1).astype(np.float32)
    pushed = pool.push(states, actions)
    for i, key in enumerate(keys):
        one = env.reset(key)
        np.testing.assert_array_equal(np.asarray(states.pos[i]), np.asarray(one.pos))
        one = env.push(one, actions[i])
        for name in ("qpos", "pos", "mat", "broken"):
            np.testing.assert_array_equal(np.asarray(getattr(pushed, name)[i]), np.asarray(getattr(one, name)))
        np.testing.assert_array_equal(np.asarray(pushed.obs.depth[i]), np.asarray(one.obs.depth))
    assert np.abs(np.asarray(pushed.pos) - np.asarray(states.pos)).max() > 0.005  # the pushes moved pieces


def test_pool_names_a_bad_action():
    pool = WorldPool(SIM)
    states = pool.reset(jax.random.split(jax.random.PRNGKey(0), 1))
    with pytest.raises(ValueError, match="outside the workspace"):
        pool.push(states, np.array([[0.0, 0.0, 0.5, 0.0]]))


@pytest.mark.slow
def test_mjx_pool_equals_one_mjx_world_at_a_time():
    """MJXPool: one vmapped reset and push of 2 worlds equal PileEnv's MJX backend world by world (to float32 rounding
    of a batched program: 590 contact steps amplify it to tens of micrometres; a world mixed up with another would be
    centimetres off), poses and rendered observations, and the pushes moved pieces; make_pool names an unknown
    engine."""
    pool, env = make_pool(SIM, "mjx"), PileEnv(SIM, backend="mjx")
    assert isinstance(pool, MJXPool)
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    states = pool.reset(keys)
    centre = np.asarray(states.pos)[:, :, :2].mean(1)
    actions = np.concatenate([centre - [[0.04, 0], [0, 0.04]], centre + [[0.03, 0], [0, 0.03]]], 1).astype(np.float32)
    pushed = pool.push(states, actions)
    for i, key in enumerate(keys):
        one = env.push(env.reset(key), actions[i])
        np.testing.assert_allclose(np.asarray(pushed.pos[i]), np.asarray(one.pos), atol=1e-4)
        same = np.asarray(pushed.obs.piece[i]) == np.asarray(one.obs.piece)
        assert same.mean() > 0.99
        np.testing.assert_allclose(np.asarray(pushed.obs.depth[i])[same], np.asarray(one.obs.depth)[same], atol=1e-3)
    assert np.abs(np.asarray(pushed.pos) - np.asarray(states.pos)).max() > 0.005
    with pytest.raises(ValueError, match="outside the workspace"):
        pool.push(states, np.full((2, 4), 1.0, np.float32))
    with pytest.raises(ValueError, match="backend must be one of"):
        make_pool(SIM, "flex")


def test_fast_engine_and_auto_choice():
    """"mjx-fast" simulates SceneConfig.fast's physics for the config's kinds; "auto" is C MuJoCo without a GPU."""
    assert engines.resolve("auto") == ("mjx-fast" if jax.default_backend() == "gpu" else "mujoco")
    fast = make_pool(SIM, "mjx-fast").config.scene
    assert fast == SceneConfig.fast(SIM.scene.kinds, SIM.scene.pieces) and fast != SIM.scene
    assert make_pool(SIM, "mjx").config.scene == SIM.scene
    env = make_env(SIM, "mjx-fast", render=False)  # one world: the same physics as the batch
    assert env.backend == "mjx" and env.config.scene == fast
    assert make_env(SIM, "mujoco", render=False).config.scene == SIM.scene


def test_every_command_offers_the_engine_table(capsys):
    """One table of engines (``sim.engines``): every command's --backend offers each engine by the same name."""
    from dynres_jax.commands import evaluate, gather, generate_data, label_resolution, simulate, sort

    choices = "(choosefrom" + ",".join(f"'{name}'" for name in engines.NAMES) + ")"  # the one-line error's list
    for command in (evaluate, gather, generate_data, label_resolution, simulate, sort):
        with pytest.raises(SystemExit):
            command.main(["--backend", "flex"])
        err = capsys.readouterr().err
        assert "--backend" in err and choices in err.replace(" ", ""), (command.__name__, err)


def test_an_engine_on_an_existing_physics_is_one_row(monkeypatch):
    """A new engine on a physics the package has (here the C engine on the fast scene's physics) is one row of
    ``engines.ENGINES``: worlds, commands' process pools and data's device checks read the row, not the name."""
    from dynres_jax.learn import data

    row = engines.Engine("mujoco-fast", CPhysics, True, None, "C MuJoCo on the fast scene's physics")
    monkeypatch.setitem(engines.ENGINES, row.name, row)
    monkeypatch.setattr(engines, "NAMES", (*engines.NAMES, row.name))
    pool = make_pool(SIM, "mujoco-fast")
    assert isinstance(pool, WorldPool) and pool.config.scene == SceneConfig.fast(SIM.scene.kinds, SIM.scene.pieces)
    assert engines.uses_workers("mujoco-fast") and not engines.uses_workers("mjx")
    config = data.DataConfig(backend="mujoco-fast", worlds=3)
    cpu = jax.devices()[0]
    assert data.check_devices(config, [cpu, cpu]) == [cpu, cpu]  # host workers: worlds need not divide the devices
    with pytest.raises(ValueError, match="multiple of the device count"):
        data.check_devices(data.DataConfig(backend="mjx", worlds=3), [cpu, cpu])


class Frozen(MJXPhysics):
    """A physics a user adds (a toy): nothing moves; the pieces' poses are their state's."""

    name = "frozen"

    def run(self, qpos, qvel, plate_pos, plate_quat) -> Poses:
        d = mjx.kinematics(self.mx, self.data0().replace(qpos=qpos, qvel=jnp.zeros_like(qvel)))
        return Poses(d.qpos, d.qvel, d.geom_xpos[self.gid], d.geom_xmat[self.gid])


def test_a_new_physics_is_one_module_and_one_row(monkeypatch, capsys):
    """A new physics is a ``sim.physics.Physics`` class and one ``engines.ENGINES`` row: PileEnv takes its name as
    the backend, the pools and every command's --backend take the engine (here a toy in which nothing moves)."""
    from dynres_jax.commands import simulate

    row = engines.Engine("frozen", Frozen, False, None, "a toy: nothing moves")
    monkeypatch.setitem(engines.ENGINES, row.name, row)
    monkeypatch.setattr(engines, "NAMES", (*engines.NAMES, row.name))
    env = PileEnv(SIM, backend="frozen", render=False)
    state = env.reset(jax.random.PRNGKey(0))
    pushed = env.push(state, env.sample_push(jax.random.PRNGKey(1), state.pos))
    np.testing.assert_array_equal(pushed.pos, state.pos)
    pool = make_pool(SIM, "frozen")
    assert isinstance(pool.env.physics, Frozen)
    states = pool.reset(jax.random.split(jax.random.PRNGKey(0), 2))
    actions = jax.vmap(env.sample_push)(jax.random.split(jax.random.PRNGKey(1), 2), states.pos)
    np.testing.assert_array_equal(pool.push(states, actions).pos, states.pos)
    moved = WorldPool(SIM).push(states, actions)  # C MuJoCo from the same states: the pieces move
    assert float(np.abs(np.asarray(moved.pos) - np.asarray(states.pos)).max()) > 1e-3
    with pytest.raises(SystemExit):  # the command line knows it: its --backend parses, then --pieces is refused
        simulate.main(["--backend", "frozen", "--pieces", "0"])
    err = capsys.readouterr().err
    assert "--pieces" in err and "--backend" not in err, err


def _running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie waiting to be reaped."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_a_killed_parent_takes_its_busy_worker_with_it(tmp_path):
    """kill -9 of the process that holds a pool, while a worker is mid-task: the worker ends within seconds, not
    when its task does (a killed evaluation leaves no simulator workers behind)."""
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent("""
        import os, time
        from dynres_jax.sim.pool import process_pool
        if __name__ == "__main__":
            pool = process_pool(1)
            print(pool.apply(os.getpid), flush=True)
            pool.apply(time.sleep, (120,))
    """))
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                              cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    worker = int(parent.stdout.readline())
    time.sleep(1.0)  # the worker is inside its two-minute task
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 15
    while _running(worker) and time.monotonic() < deadline:
        time.sleep(0.2)
    survived = _running(worker)
    if survived:
        os.kill(worker, 9)
    assert not survived
