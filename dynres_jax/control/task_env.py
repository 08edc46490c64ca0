"""A task as an environment in mujoco_playground's conventions, for code written against them (RL, CEM, MPPI):

    env = TaskEnv(SimConfig(), goal_mask=None)          # Gather at a disc of 8 cm at the centre; MJX engine
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))  # State: data, obs, reward, done, metrics, info
    state = jax.jit(env.step)(state, action)            # action [4]: a push (x_start, y_start, x_end, y_end), m

``reset`` and ``step`` are pure JAX on the MJX engine: jit them, vmap them over worlds. The reward of a step is how
much it lowered the task's distance d (pixels; ``objective.distribution_distance``), so an episode's rewards sum to
d at the start less d at the end; ``metrics`` holds d and the share of pieces inside the goal; ``done`` is 1 once
``success`` of the pieces are inside, after ``episode_length`` steps, or when the world broke. A push outside the
action space is projected onto it (``sim.pushes.project``, as the planner's are). There is no automatic reset: a done
state steps on, as playground's own environments do without their wrappers.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from dynres_jax.config import SimConfig
from dynres_jax.control.goals import Goal, disc_goal, make_goal
from dynres_jax.control.objective import distribution_distance, inside_share
from dynres_jax.sim import env as sim_env
from dynres_jax.sim.camera import Observation


@struct.dataclass
class State:
    """mujoco_playground's State: data (the simulator's world: MuJoCo state and piece poses), obs (the top-down
    RGBD Observation), reward [] (d before the step less d after, pixels), done [] (0 or 1), metrics (distance [],
    inside []), info (step []: pushes so far)."""

    data: sim_env.State
    obs: Observation
    reward: jax.Array
    done: jax.Array
    metrics: dict[str, jax.Array]
    info: dict[str, Any]


class TaskEnv:
    """One task's environment: piles of ``sim`` (default ``SimConfig()``) pushed towards ``goal_mask`` [H, W] bool
    (default: Gather's disc of 8 cm at the bin's centre), ``episode_length`` pushes at most, done at ``success`` of
    the pieces inside. ``backend`` "mjx" (jit and vmap) or "mujoco" (C MuJoCo, one world, not traceable)."""

    def __init__(self, sim: SimConfig | None = None, goal_mask=None, *, backend: str = "mjx",
                 episode_length: int = 20, success: float = 0.9):
        if (isinstance(episode_length, bool) or not isinstance(episode_length, int | np.integer) or episode_length < 1
                or not 0 < success <= 1):
            raise ValueError(f"episode_length must be a whole number >= 1 and success in (0, 1], got "
                             f"{episode_length!r}, {success!r}")
        self.pile = sim_env.PileEnv(sim or SimConfig(), backend=backend)
        camera = self.pile.camera
        mask = disc_goal(camera, np.zeros(2), 0.08) if goal_mask is None else np.asarray(goal_mask, bool)
        if mask.shape != (camera.height, camera.width):
            raise ValueError(f"goal_mask must be the camera's [{camera.height}, {camera.width}], got {mask.shape}")
        self.goal: Goal = make_goal(mask, camera)
        self.episode_length, self.success = episode_length, success

    @property
    def action_size(self) -> int:
        """A push: (x_start, y_start, x_end, y_end), metres."""
        return 4

    @property
    def observation_size(self) -> dict[str, tuple[int, ...]]:
        """The shapes of an observation's images (the Observation's rgb, depth and kind)."""
        c = self.pile.camera
        return {"rgb": (c.height, c.width, 3), "depth": (c.height, c.width), "kind": (c.height, c.width)}

    def reset(self, rng) -> State:
        """A new settled pile drawn from ``rng``."""
        data = self.pile.reset(rng)
        distance, inside = self._score(data)
        zero = jnp.zeros((), jnp.float32)
        return State(data, data.obs, zero, zero, dict(distance=distance, inside=inside),
                     dict(step=jnp.zeros((), jnp.int32)))

    def step(self, state: State, action) -> State:
        """One push ``action`` [4] (m) from ``state``."""
        data = self.pile.push(state.data, jnp.asarray(action, jnp.float32))
        distance, inside = self._score(data)
        step = state.info["step"] + 1
        done = (inside >= self.success - 1e-6) | (step >= self.episode_length) | data.broken
        return state.replace(data=data, obs=data.obs, reward=state.metrics["distance"] - distance,
                             done=done.astype(jnp.float32), metrics=dict(distance=distance, inside=inside),
                             info=dict(state.info, step=step))

    def _score(self, data: sim_env.State) -> tuple[jax.Array, jax.Array]:
        """d of the foreground to the goal (pixels) and the share of pieces inside it."""
        camera = self.pile.camera
        return (distribution_distance(data.obs, self.goal, camera),
                inside_share(data.pos, jnp.ones(data.pos.shape[0], bool), self.goal, camera))
