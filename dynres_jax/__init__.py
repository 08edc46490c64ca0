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

import importlib

_HOMES = {  # name -> the module it lives in; imported on first use, so ``import dynres_jax.config`` stays light
    **dict.fromkeys(("CameraConfig", "PileConfig", "PushConfig", "SceneConfig", "SimConfig"), "config"),
    **dict.fromkeys(("AdaptiveOmega", "FixedOmega", "OracleOmega"), "control.choosers"),
    "goal_cost": "control.decision",
    **dict.fromkeys(("disc_goal", "make_goal", "text_goal"), "control.goals"),
    **dict.fromkeys(("MPCConfig", "run", "run_episode"), "control.mpc"),
    **dict.fromkeys(("distribution_distance", "inside_share", "objective"), "control.objective"),
    **dict.fromkeys(("PlannerConfig", "plan"), "control.planner"),
    "TaskEnv": "control.task_env",
    **dict.fromkeys(("SHIPPED_DYNAMICS", "SHIPPED_REGRESSOR", "load_dynamics"), "models.registry"),
    "sample_particles": "perception",
    "PileEnv": "sim.env",
    "EnvWorlds": "sim.pool",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str):
    if name not in _HOMES:
        raise AttributeError(f"module 'dynres_jax' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"dynres_jax.{_HOMES[name]}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_HOMES))
