"""dynres-jax: dynamic-resolution particle models for pushing object piles, in JAX (Wang et al., RSS 2023).

The stages, each one module away from the paper's symbols (README, "Paper to code"):

- ``dynres_jax.sim``: the MuJoCo pile simulator and its top-down RGBD camera (observations y);
- ``dynres_jax.perception``: h(y, ω), ω particles by farthest point sampling;
- ``dynres_jax.models``: the dynamics f(z, u, ω) (graph network; CNN baseline; sweep heuristic) and its registry;
- ``dynres_jax.control``: the task objective c, the planner, resolution buckets and time budget, one decision, the
  choosers of ω and goals (fixed, the regressor g, the oracle, Sort's A*), the MPC loop, Bayesian optimisation,
  a task as a mujoco_playground-style environment (``TaskEnv``);
- ``dynres_jax.learn``: data generation and training of f, labels and training of g;
- ``dynres_jax.io``: files, checkpoints, recorded frames, pictures of an episode;
- ``dynres_jax.commands``: the command line (``dynres NAME`` or ``python -m experiments.NAME``), the exported
  planner.

What the quick start and the notebooks use is importable from here.
"""

from dynres_jax.config import CameraConfig, PileConfig, PushConfig, SceneConfig, SimConfig
from dynres_jax.control.choosers import AdaptiveOmega, FixedOmega, OracleOmega
from dynres_jax.control.decision import goal_cost
from dynres_jax.control.goals import disc_goal, make_goal, text_goal
from dynres_jax.control.mpc import MPCConfig, run, run_episode
from dynres_jax.control.objective import distribution_distance, inside_share, objective
from dynres_jax.control.planner import PlannerConfig, plan
from dynres_jax.control.task_env import TaskEnv
from dynres_jax.models.registry import SHIPPED_DYNAMICS, SHIPPED_REGRESSOR, load_dynamics
from dynres_jax.perception import sample_particles
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.pool import EnvWorlds

__all__ = [
    "SHIPPED_DYNAMICS", "SHIPPED_REGRESSOR", "AdaptiveOmega", "CameraConfig", "EnvWorlds", "FixedOmega", "MPCConfig",
    "OracleOmega", "PileConfig", "PileEnv", "PlannerConfig", "PushConfig", "SceneConfig", "SimConfig", "TaskEnv",
    "disc_goal",
    "distribution_distance", "goal_cost", "inside_share", "load_dynamics", "make_goal", "objective", "plan", "run",
    "run_episode", "sample_particles", "text_goal",
]
