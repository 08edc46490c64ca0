"""Learning to rank the planner's candidates (issue 48): ListNet's listwise loss beside the position loss, and a
fine-tune of a dynamics model on ranking sets (``dynres_jax.learn.ranking``: closed-loop states, each with the
planner's candidate pushes pushed in C MuJoCo).

The position loss alone teaches where particles go; the planner needs the order of its candidates, which small
errors decide. The listwise loss (ListNet's top-one: the cross-entropy between the softmax of -c_true / τ and of
-c_pred / τ over a state's C candidates, τ in pixels) trains that order directly. Fine-tuning the shipped model with
it on the candidates of Gather states lifted M&M Gather from 60 to 81 % on fresh seeds (docs/dynamics_scale/rounds.md);
the position loss alone on the same candidates did not move the closed loop.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from dynres_jax.control.objective import objective
from dynres_jax.learn import ranking
from dynres_jax.learn.train import DISTANCE_EPS
from dynres_jax.models.dynamics import LENGTH_SCALE, predict, resolution_code


def listwise(pred_c, true_c, temperature: float):
    """ListNet's top-one loss of one state: pred_c, true_c [C] (pixels; lower is better) -> []."""
    target = jax.nn.softmax(-true_c / temperature)
    return -jnp.sum(target * jax.nn.log_softmax(-pred_c / temperature))


def state_losses(graphdef, params, state, camera, temperature: float):
    """One state's (listwise loss, position loss in length units): state = (positions [N, 3], mask [N], radius [],
    goal, candidates [C, 4], true_c [C], true_positions [C, N, 3])."""
    positions, mask, radius, goal, candidates, true_c, true_positions = state
    code = resolution_code(radius)
    final = jax.vmap(lambda a: predict(graphdef, params, positions, mask, a, code))(candidates)  # [C, N, 3]
    pred_c = jax.vmap(lambda p: objective(p, mask, goal, camera))(final)
    error = jnp.sqrt(jnp.sum(jnp.square(final - true_positions), -1) + DISTANCE_EPS**2) / LENGTH_SCALE  # [C, N]
    position = jnp.sum(error * mask) / jnp.maximum(jnp.sum(mask) * len(candidates), 1)
    return listwise(pred_c, true_c, temperature), position


def arrays(s: ranking.RankingSet):
    """A set as the tuple ``state_losses`` takes, batched over states (goals rebuilt from their masks)."""
    return (jnp.asarray(s.positions), jnp.asarray(s.mask), jnp.asarray(s.radius), ranking.goals(s),
            jnp.asarray(s.candidates), jnp.asarray(s.true_c), jnp.asarray(s.true_positions))


def finetune(model, train: ranking.RankingSet, *, steps: int, batch: int, lr: float, temperature: float,
             rank_weight: float, position_weight: float, seed: int = 0, log=print):
    """The model fine-tuned on ``train`` (a copy; Adam, ``batch`` states a step drawn uniformly; the loss
    rank_weight x listwise + position_weight x position)."""
    graphdef, params = nnx.split(model)
    data, camera = arrays(train), train.camera
    optimizer = optax.adam(lr)
    opt_state = optimizer.init(params)

    @jax.jit
    def step(params, opt_state, rows):
        def loss(p):
            rank, position = jax.vmap(lambda *x: state_losses(graphdef, p, x, camera, temperature))(
                *jax.tree.map(lambda x: x[rows], data))
            total = rank_weight * jnp.mean(rank) + position_weight * jnp.mean(position)
            return total, (jnp.mean(rank), jnp.mean(position))

        (_, parts), grads = jax.value_and_grad(loss, has_aux=True)(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, parts

    rng = np.random.default_rng(seed)
    for i in range(steps):
        params, opt_state, (rank, position) = step(params, opt_state, rng.integers(0, len(train.group), batch))
        if (i + 1) % max(1, steps // 5) == 0:
            log(f"step {i + 1}: listwise {float(rank):.4f}, position {float(position) * LENGTH_SCALE * 1000:.2f} mm")
    return nnx.merge(graphdef, params)
