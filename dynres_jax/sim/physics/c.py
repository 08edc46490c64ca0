"""C MuJoCo, one world on the host (the reference physics): one ``mujoco.rollout`` call a plate trajectory, no Python
per step. A pool steps its worlds in worker processes, one a core (``sim.pool.WorldPool``)."""

from __future__ import annotations

import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import rollout

from dynres_jax.sim.physics import Poses

FULL_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
PLATE_CONTROL = mujoco.mjtState.mjSTATE_MOCAP_POS | mujoco.mjtState.mjSTATE_MOCAP_QUAT


def c_rollout(model, data, plate, nthread_data=None):
    """C MuJoCo along plate trajectories: plate [B, K, 7] (mocap pos, quat per step), starting from ``data``'s
    state for every world. Returns full physics states [B, K, nstate]. ``nthread_data``: a list of MjData, one per
    thread, to run the B worlds on several cores."""
    state0 = np.empty(mujoco.mj_stateSize(model, FULL_STATE))
    mujoco.mj_getState(model, data, state0, FULL_STATE)
    states, _ = rollout.rollout(model, nthread_data or data, state0[None], plate, control_spec=PLATE_CONTROL)
    return states


class CPhysics:
    """The C engine on one MjData of ``scene``'s model (worlds and contact_jacobian: the protocol's, unused)."""

    name, traced, workers, per_batch = "mujoco", False, True, False

    def __init__(self, scene, worlds: int = 1, contact_jacobian: str = "dense"):
        self.model, self.gid = scene.model, scene.geom_id
        self.data = mujoco.MjData(self.model)

    def run(self, qpos, qvel, plate_pos, plate_quat) -> Poses:
        return self.run_drawn(qpos, qvel, plate_pos, plate_quat)[0]

    def run_drawn(self, qpos, qvel, plate_pos, plate_quat, frames_at=()) -> tuple[Poses, list]:
        """``run``, and (piece pos, piece mat, plate pos, plate quat) after each step index in ``frames_at``."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
        plate = np.concatenate([plate_pos, plate_quat], axis=1).astype(np.float64)
        try:
            states = c_rollout(m, d, plate[None])[0]
        except mujoco.FatalError:  # an unstable world overflowed MuJoCo's arena: report it as NaN (broken)
            states = np.full((len(plate), mujoco.mj_stateSize(m, FULL_STATE)), np.nan)

        def poses(state):
            mujoco.mj_setState(m, d, state, FULL_STATE)
            mujoco.mj_kinematics(m, d)
            return d.geom_xpos[self.gid].copy(), d.geom_xmat[self.gid].reshape(-1, 3, 3).copy()

        frames = [(*poses(states[i]), plate[i, :3], plate[i, 3:]) for i in frames_at]
        pos, mat = poses(states[-1])
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        return Poses(f32(d.qpos), f32(d.qvel), f32(pos), f32(mat)), frames

    @staticmethod
    def check_batch(overflow, n_pieces: int) -> None:
        """The C engine grows its arena as needed (a world that overflows it comes back NaN, broken)."""
