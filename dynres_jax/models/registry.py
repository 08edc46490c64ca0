"""The model registry: build a dynamics model f(z, u, ω) from its config or checkpoint card, load the shipped one,
and adapt it (or the sweep heuristic) to what the planner calls: ``radius -> (positions, mask, actions) -> [T, N, 3]``.
The one place where ω becomes what a model is conditioned on (``resolution_code`` of the particles' radius)."""

from __future__ import annotations

import functools
import os
import warnings
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.tree_util import Partial

from dynres_jax.config import OMEGA_MAX
from dynres_jax.errors import InputError
from dynres_jax.io import ckpt
from dynres_jax.models.cnn_dynamics import CNNDynamics, CNNDynamicsConfig
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig, edge_table, resolution_code, rollout
from dynres_jax.models.graph import sweep_rollout

SHIPPED = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "checkpoints")  # package data
SHIPPED_DYNAMICS = os.path.join(SHIPPED, "dynamics")  # the graph network f every command plans with by default
SHIPPED_SORT_DYNAMICS = os.path.join(SHIPPED, "sort_dynamics")  # Sort's f: the one before the ranking fine-tune
SHIPPED_CNN_DYNAMICS = os.path.join(SHIPPED, "cnn_dynamics")  # the paper's CNN-dynamics baseline
SHIPPED_REGRESSOR = os.path.join(SHIPPED, "regressor")  # the resolution regressor g of adaptive ω
SWEEP_NAME = "sweep heuristic"  # LoadedDynamics.name of the heuristic
MODEL_CLASSES = {"gnn": (DynamicsConfig, Dynamics), "cnn": (CNNDynamicsConfig, CNNDynamics)}  # card name -> classes


def shipped_dynamics(task: str) -> str:
    """The shipped checkpoint a task plans with by default: Sort keeps the model from before the fine-tune on
    Gather's candidates (checkpoints/dynamics/CARD.md), which lifted M&M Gather but lowered Sort on every kind pair
    (docs/dynamics_scale/rounds.md); Gather and Redistribute plan with the fine-tuned one."""
    return SHIPPED_SORT_DYNAMICS if task == "sort" else SHIPPED_DYNAMICS


def model_class(config) -> str:
    """The card's name ("gnn" or "cnn") of a model config; a ValueError for anything else."""
    for name, (config_type, _) in MODEL_CLASSES.items():
        if isinstance(config, config_type):
            return name
    raise ValueError(f"TrainConfig.model must be a DynamicsConfig or a CNNDynamicsConfig, got {type(config).__name__}")


def make_model(config: DynamicsConfig | CNNDynamicsConfig, seed: int = 0) -> Dynamics | CNNDynamics:
    """A fresh model of the class its config names, parameters drawn from ``seed``."""
    return MODEL_CLASSES[model_class(config)][1](config, rngs=nnx.Rngs(seed))


def build_model(meta: dict) -> Dynamics | CNNDynamics:
    """A fresh model from a checkpoint card (``ckpt.load_module``'s ``build``): ``meta["model_class"]`` ("gnn", the
    default for cards written before the CNN existed, or "cnn") and its config ``meta["dynamics"]``."""
    if "dynamics" not in meta:
        raise ValueError(f"it holds {describe(meta)}, not a dynamics model")
    name = meta.get("model_class", "gnn")
    if name not in MODEL_CLASSES:
        raise ValueError(f"checkpoint card names model_class {name!r}; known: {', '.join(MODEL_CLASSES)}")
    fields = dict(meta["dynamics"])
    if name == "gnn" and "steps" in fields:  # cards written before the field was named propagation_steps
        fields["propagation_steps"] = fields.pop("steps")
    return make_model(MODEL_CLASSES[name][0](**fields))


def describe(meta: dict) -> str:
    """What a checkpoint card holds, in words: "a gnn dynamics model", "a cnn dynamics model", "an ω regressor"."""
    if "dynamics" in meta:
        return f"a {meta.get('model_class', 'gnn')} dynamics model"
    return "an ω regressor" if "width" in meta else "no model this package knows"


EDGE_DTYPES = ("float32", "bfloat16")  # ``learned_dynamics``'s choices for the GNN's per-edge network


@dataclass(frozen=True)
class _Learned:
    """A trained model's rollout as a planner dynamics, called with ``(graphdef, state, code)`` bound by
    ``learned_dynamics``' Partial. With ``pair_table`` it offers the planner's per-plan hook ``prepare``: the pair
    table of each re-sampling, built once per plan instead of once per Adam step (XLA does not hoist it out of the
    step loop itself: the table is larger than its inputs). Instances compare by value, so equal options share one
    compiled plan."""

    edge_dtype: str
    pair_table: bool

    def __call__(self, graphdef, state, code, positions, mask, actions, context=None):
        return rollout(graphdef, state, positions, mask, actions, code, edge_dtype=self.edge_dtype,
                       pair_table=self.pair_table, table=context)

    def prepare(self, graphdef, state, code, positions, mask):
        """positions [N, 3], mask [N] -> the context of ``__call__``: the pair table [N, N, H], or None."""
        if not self.pair_table:
            return None
        return edge_table(graphdef, state, positions, mask, code, edge_dtype=self.edge_dtype)


def _sweep(plate_half_width, positions, mask, actions):
    return sweep_rollout(positions, mask, actions, plate_half_width)


def learned_dynamics(model: Dynamics, edge_dtype: str = "float32"):
    """radius (m) -> planner dynamics ``(positions, mask, actions [T, 4]) -> [T, N, 3]`` of a trained model. edge_dtype:
    "float32", or "bfloat16" for a GNN's per-edge network (predictions within about half a millimetre, ``dynamics``
    module docstring, "Mixed precision"; no faster on the H100 and H200: docs/performance.md, "Planner speed"). A GNN
    whose edges are not in the push frame takes the first push's edge codes from a pair table (``dynamics`` module
    docstring, "Pair table"): the planner's pushes all start from the same particles, so the table is built once per
    plan, not per push and Adam step."""
    edge_dtype = jnp.dtype(edge_dtype).name
    if edge_dtype not in EDGE_DTYPES:
        raise ValueError(f"edge_dtype must be one of {EDGE_DTYPES}, got {edge_dtype!r}")
    if edge_dtype != "float32" and not isinstance(model, Dynamics):
        raise ValueError(f"edge_dtype={edge_dtype!r} needs the graph network (Dynamics), got {type(model).__name__}")
    pair_table = isinstance(model, Dynamics) and model.config.pair_table
    graphdef, state = nnx.split(model)
    return lambda radius: Partial(_Learned(edge_dtype, pair_table), graphdef, state,
                                  resolution_code(_checked_radius(radius)))


def _checked_radius(radius):
    """radius itself; InputError for a concrete one that is not a positive finite number of metres (a NaN radius gave
    a NaN code and a NaN push). A traced radius is not checked."""
    if not isinstance(radius, jax.core.Tracer):
        value = np.asarray(radius)
        if value.dtype.kind not in "fiu" or not np.all(np.isfinite(value) & (value > 0)):
            raise InputError(f"radius must be the particles' spacing, a positive number of metres, got {radius!r}")
    return radius


@functools.cache
def sweep_dynamics(plate_half_width: float):
    """radius -> planner dynamics of the sweep heuristic alone (the resolution is irrelevant to it); one function per
    plate, so a second run in one process reuses the planner compiled for the first."""
    return lambda radius: Partial(_sweep, jnp.float32(plate_half_width))


class LoadedDynamics(NamedTuple):
    """``load_dynamics``' answer. dynamics: radius -> the planner's model; n_max: the particles the model was trained
    for; name: what to call it in logs and results (the checkpoint and its step, or "sweep heuristic")."""

    dynamics: object
    n_max: int
    name: str


def trained_n_max(meta: dict, where) -> int:
    """A checkpoint card's ``train.n_max`` (the most particles the model was trained on), checked: a
    ``ckpt.CheckpointError`` naming the folder ``where`` when the card has no train section or n_max is not a whole
    number in [1, OMEGA_MAX] (a resealed card is read, not trusted)."""
    train = meta.get("train")
    n_max = train.get("n_max") if isinstance(train, dict) else None
    if isinstance(n_max, bool) or not isinstance(n_max, int) or not 1 <= n_max <= OMEGA_MAX:
        found = f"got {n_max!r}" if isinstance(train, dict) else "the card has no train section"
        raise ckpt.CheckpointError(f"checkpoint {str(where)!r}: its card's train.n_max must be a whole number in "
                                   f"[1, {OMEGA_MAX}]; {found}")
    return n_max


def load_dynamics(choice: str, ckpt_dir: str, plate_half_width: float, edge_dtype: str = "float32"):
    """The planner's model. choice: "learned" (the checkpoint in ``ckpt_dir``), "sweep" (the heuristic), or "auto"
    (the checkpoint; the heuristic, with a warning, only when ``ckpt_dir`` is the shipped one and it is missing, as in
    a checkout without its checkpoints: a checkpoint asked for by name is never replaced); edge_dtype: a learned
    model's (``learned_dynamics``; the sweep has no network). Returns a ``LoadedDynamics``. FileNotFoundError for a
    missing checkpoint, ``ckpt.CheckpointError`` for a damaged one."""
    if choice not in ("auto", "learned", "sweep"):
        raise ValueError(f"dynamics must be 'auto', 'learned' or 'sweep', got {choice!r}")
    if isinstance(plate_half_width, bool) or not (np.ndim(plate_half_width) == 0 and np.isfinite(plate_half_width)
                                                  and plate_half_width > 0):
        raise ValueError(f"plate_half_width must be a positive number of metres, got {plate_half_width!r}")
    if choice == "auto" and ckpt.latest_step(ckpt_dir) is None and os.path.abspath(ckpt_dir) in (
            SHIPPED_DYNAMICS, SHIPPED_SORT_DYNAMICS):
        warnings.warn(f"no shipped checkpoint in {ckpt_dir}: planning with the sweep heuristic", stacklevel=2)
        choice = "sweep"
    if choice != "sweep":
        model, meta, _ = ckpt.load_module(ckpt_dir, build_model)
        n_max = trained_n_max(meta, ckpt_dir)
        dynamics = learned_dynamics(model, edge_dtype)
        edges = "" if jnp.dtype(edge_dtype) == jnp.float32 else f", {jnp.dtype(edge_dtype).name} edges"
        tuned = meta.get("rank_finetune")  # a fine-tune's step counts from its base: say so
        step = (f"fine-tune step {meta.get('step')} of the step-{tuned['base'].split('step ')[-1].split()[0]} model"
                if tuned and "step " in str(tuned.get("base")) else f"step {meta.get('step')}")
        return LoadedDynamics(dynamics, n_max, f"learned ({ckpt_dir}, {step}{edges})")
    return LoadedDynamics(sweep_dynamics(plate_half_width), OMEGA_MAX, SWEEP_NAME)
