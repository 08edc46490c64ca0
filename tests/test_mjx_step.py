"""sim.physics.mjx_step: the step with sparse contact Jacobians equals mujoco.mjx.step; dof chains; what it
refuses."""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from dynres_jax.config import SceneConfig, SimConfig
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.physics import mjx_step
from dynres_jax.sim.physics.mjx import mjx

SCENES = {
    "coffee, Newton, condim 3 (default)": SceneConfig(pieces=(6,)),
    "coffee, fast (CG, condim 1)": SceneConfig.fast(pieces=(6,)),
    "almond (yaw hinges)": SceneConfig(kinds=("almond",), pieces=(6,)),
    "candy, elliptic cones": SceneConfig(kinds=("candy",), pieces=(6,), cone="elliptic"),
    "coffee, free joints": SceneConfig(pieces=(6,), joints="free"),
}


def _squeezed_world(env: PileEnv):
    """MJX data with the pieces in a row, each pressed 1 mm into the next, the plate pressing the first, and some
    velocity: every kind of contact row is active."""
    sc = env.scene
    half = float(np.max(np.where(sc.geom_type == 1, sc.size[:, 0] + sc.size[:, 1], sc.size[:, 0])))  # along x
    n = sc.n_pieces
    xy = np.stack([np.arange(n) * (2 * half - 0.001), 0.002 * np.sin(np.arange(n))], 1) - [half * n, 0]
    yaw = 0.05 * np.sin(np.arange(n))
    qpos = env._qpos_from(jnp.asarray(xy, jnp.float32), jnp.asarray(yaw, jnp.float32))
    qvel = 0.05 * jax.random.normal(jax.random.PRNGKey(0), (env.scene.model.nv,))
    plate = jnp.array([[xy[0, 0] - half - env.config.scene.plate_thickness / 2 + 0.001, 0.0, env.plate_z]])
    return env.physics.data0().replace(qpos=qpos, qvel=qvel, mocap_pos=plate, mocap_quat=jnp.array([[1.0, 0, 0, 0]]))


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SCENES))
def test_sparse_step_equals_mjx_step(name):
    env = PileEnv(SimConfig(scene=SCENES[name]), backend="mjx", render=False)
    d = _squeezed_world(env)
    ref = jax.jit(mjx.step)(env.physics.mx, d)
    ours = jax.jit(env.physics.step)(env.physics.mx, d)
    touching = np.asarray(ref._impl.contact.dist) < 0
    assert touching.sum() >= env.scene.n_pieces  # pairs in the row and the plate: real contact rows, not zeros
    for field in ("efc_J", "efc_D", "efc_aref", "efc_pos", "efc_frictionloss"):
        np.testing.assert_allclose(getattr(ours._impl, field), getattr(ref._impl, field), rtol=1e-5, atol=1e-6,
                                   err_msg=field)
    for field in ("qacc", "qvel", "qpos"):  # the solver's iterations amplify float32 rounding a little
        want = np.asarray(getattr(ref, field))
        np.testing.assert_allclose(getattr(ours, field), want, rtol=1e-4, atol=1e-5 * np.abs(want).max(),
                                   err_msg=field)


CHAIN_XML = """<mujoco><worldbody>
  <body name="a"><joint type="slide" axis="1 0 0"/><geom size="0.01"/>
    <body name="b" pos="0.1 0 0"><joint type="hinge" axis="0 0 1"/><geom size="0.01"/>
      <body name="c" pos="0.1 0.05 0"><joint type="slide" axis="0 1 0"/><geom size="0.01"/></body>
    </body>
  </body>
  <body name="d" pos="0 0.3 0"><freejoint/><geom size="0.01"/></body>
  <body name="e" pos="0.3 0.3 0"><geom size="0.01"/></body>
</worldbody></mujoco>"""


def test_chain_dofs_are_the_dofs_that_move_each_body():
    model = mujoco.MjModel.from_xml_string(CHAIN_XML)
    data = mujoco.MjData(model)
    data.qpos[:] = np.random.default_rng(0).uniform(0.1, 0.5, model.nq)
    mujoco.mj_forward(model, data)
    chains = mjx_step.chain_dofs(model)
    for b in range(model.nbody):
        jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        mujoco.mj_jacBody(model, data, jacp, jacr, b)
        moving = set(np.nonzero(np.abs(np.vstack([jacp, jacr])).sum(0) > 1e-9)[0].tolist())
        assert set(chains[b][chains[b] >= 0].tolist()) == moving, model.body(b).name


def test_unsupported_model_is_named():
    xml = """<mujoco><worldbody><body><joint type="slide" axis="1 0 0" limited="true" range="-1 1"/>
      <geom size="0.01"/></body></worldbody><actuator><motor joint="0"/></actuator></mujoco>"""
    with pytest.raises(ValueError, match="actuators, limited joints"):
        mjx_step.check_supported(mujoco.MjModel.from_xml_string(xml.replace('joint="0"', 'joint="j"').replace(
            '<joint type', '<joint name="j" type')))


def test_bad_contact_jacobian_names_the_choices():
    with pytest.raises(ValueError, match="contact_jacobian must be 'auto', 'sparse' or 'dense'"):
        PileEnv(SimConfig(scene=SceneConfig(pieces=(2,))), backend="mjx", render=False, contact_jacobian="fast")


def test_fast_scene_takes_newton_for_boxes_and_keeps_overrides():
    fast = SceneConfig.fast(kinds=("coffee", "almond"), pieces=(4, 4))
    assert (fast.solver, fast.condim, fast.contact_cap) == ("CG", 1, 2.0)
    assert SceneConfig.fast(kinds=("coffee", "candy"), pieces=(4, 4)).solver == "Newton"
    assert SceneConfig.fast(solver="Newton", contact_cap=3.0).contact_cap == 3.0
    with pytest.raises(ValueError, match="condim must be 1 or 3"):
        SceneConfig(condim=4)


def test_the_sparse_step_runs_only_on_the_tested_mujoco_and_auto_picks_it_for_frictionless_contacts():
    """The sparse step reaches into MJX's internals: another MuJoCo version is refused with the tested one named.
    "auto" steps the fast (frictionless) scene with it and the default scene with the public mujoco.mjx.step."""
    import mujoco

    from dynres_jax.sim.physics import mjx_step

    mjx_step.check_version(mjx_step.TESTED_MUJOCO)
    with pytest.raises(RuntimeError, match=f"written against MuJoCo MJX {mjx_step.TESTED_MUJOCO}.*3.99.0 is installed"):
        mjx_step.check_version("3.99.0")
    assert mujoco.__version__ == mjx_step.TESTED_MUJOCO  # the pinned pair (pyproject.toml)
    fast = PileEnv(SimConfig(scene=SceneConfig.fast(pieces=(2,))), backend="mjx", render=False)
    default = PileEnv(SimConfig(scene=SceneConfig(pieces=(2,))), backend="mjx", render=False)
    assert isinstance(fast.physics.step, functools.partial) and fast.physics.step.func is mjx_step.step
    assert default.physics.step is mujoco.mjx.step
