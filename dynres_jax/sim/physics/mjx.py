"""MuJoCo XLA (MJX, ``impl="jax"``): ``run`` is pure JAX, so ``jax.jit`` and ``jax.vmap`` over worlds work."""

from __future__ import annotations

import functools

import jax
from mujoco import mjx

from dynres_jax.sim.physics import Poses, mjx_step


def run_steps(mx, data0, step, gid, qpos, qvel, plate_pos, plate_quat):
    """``step`` (MJX's signature) once per row of plate_pos [K, 3], plate_quat [K, 4] from ``data0()`` at qpos,
    qvel; the final Data and its pieces' geom poses pos [N, 3], mat [N, 3, 3] (geoms ``gid``)."""
    def one(d, plate):
        d = d.replace(mocap_pos=plate[0][None], mocap_quat=plate[1][None])
        return step(mx, d), None

    d, _ = jax.lax.scan(one, data0().replace(qpos=qpos, qvel=qvel), (plate_pos, plate_quat))
    d = mjx.kinematics(mx, d)
    return d, d.geom_xpos[gid], d.geom_xmat[gid]


class MJXPhysics:
    """MJX on the first local JAX device. contact_jacobian "sparse": ``mjx_step.step`` (contact Jacobians built on the
    few dofs a contact can move; it reaches into MJX's internals, so it runs only on the tested MuJoCo version);
    "dense": the public ``mujoco.mjx.step``."""

    name, traced, workers, per_batch = "mjx", True, False, False

    def __init__(self, scene, worlds: int = 1, contact_jacobian: str = "dense"):
        model, device = scene.model, jax.local_devices()[0]
        self.mx, self.gid = mjx.put_model(model, device=device, impl="jax"), scene.geom_id
        self.data0 = mjx_step.traced_template(mjx.make_data(self.mx, device=device, impl="jax"))
        if contact_jacobian == "sparse":
            mjx_step.check_version()
            mjx_step.check_supported(model)
            self.step = functools.partial(mjx_step.step, dofs=mjx_step.chain_dofs(model))
        else:
            self.step = mjx.step

    def run(self, qpos, qvel, plate_pos, plate_quat) -> Poses:
        d, pos, mat = run_steps(self.mx, self.data0, self.step, self.gid, qpos, qvel, plate_pos, plate_quat)
        return Poses(d.qpos, d.qvel, pos, mat)

    @staticmethod
    def check_batch(overflow, n_pieces: int) -> None:
        """MJX has no fixed capacities: nothing to check."""
