"""What the planner sees at each MPC step (``mpc.run``'s view): the simulator's frames through the true camera, or a
real depth camera's frames through the camera the robot believes in."""

from __future__ import annotations

import jax
import numpy as np

from dynres_jax.control.decision import episode, fold
from dynres_jax.perception import calibrate
from dynres_jax.sim.env import PileEnv, State
from dynres_jax.sim.sensor import DepthSensor


class ExactView:
    """The planner sees the simulator's frames through the true camera."""

    def __init__(self, camera):
        self.camera = camera

    def __call__(self, t: int, states: State, keys) -> tuple:
        return states.obs, self.camera


class SensorView:
    """The planner sees a real depth camera's frames (``sim.sensor.DepthSensor``: noise drawn from each step's keys)
    through the camera it believes in, refined from episode 0's first frame as a robot checks its calibration
    (``perception.calibrate``)."""

    def __init__(self, sensor: DepthSensor, env: PileEnv, log=print):
        self.sense = jax.jit(jax.vmap(sensor.observe))
        self.camera, self.scene, self.log = sensor.believed_camera(env.camera), env.config.scene, log

    def __call__(self, t: int, states: State, keys) -> tuple:
        seen = self.sense(states.obs, fold(keys, 1))
        if t == 0:
            refined = calibrate(episode(seen), self.camera, bin_half_width=self.scene.bin_half_width,
                                wall_height=self.scene.wall_height)
            turn = np.degrees(np.arccos(np.clip((np.trace(refined.rotation @ self.camera.rotation.T) - 1) / 2, -1, 1)))
            self.log(f"camera pose refined from the first frame: moved "
                     f"{1000 * np.linalg.norm(refined.centre - self.camera.centre):.1f} mm, turned {turn:.2f}°")
            self.camera = refined
        return seen, self.camera
