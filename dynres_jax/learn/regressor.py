"""Training of the resolution regressor g(y_0, y_g) -> ω (paper Sec. IV-C) on Bayesian-optimisation labels
(``experiments.label_resolution``); the command is ``experiments.train_regressor``.

Held out: every tenth pile (both of its goals), so no held-out pile was seen in training. Of the rest, every tenth pile
(at least one) is a validation set scored every ``val_every`` steps; the best is kept (early stopping; the held-out
piles are never used to choose). Loss: squared error of ω scaled to [0, 1]. Augmentation: every training sample goes
through one of the 8 rotations and reflections of the square grid, which leave the label unchanged (all six channels
are images of a square bin seen from above). Data-parallel as ``learn.train``: each batch split over a mesh axis
"batch" of every device (``dynres_jax.distributed``), the parameters replicated.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from dynres_jax import distributed, progress
from dynres_jax.config import OMEGA_MAX, OMEGA_MIN
from dynres_jax.io.shards import complete_shards, read_shard
from dynres_jax.resolution.regressor import Regressor


def load_labels(folders: list[str]) -> dict:
    """The label shards of every folder, in order; "shard" numbers them 0, 1, ... across the folders, so a pile is
    named by (shard, pile) even where two folders both have a shard 0."""
    shards = [read_shard(p, ("inputs", "label", "pile")) for folder in folders
              for p in complete_shards(folder, "--labels", "labels")]
    out = {k: np.concatenate([s[k] for s in shards]) for k in ("inputs", "label", "pile")}
    out["shard"] = np.concatenate([np.full(len(s["label"]), i) for i, s in enumerate(shards)])
    return out


def dihedral(images, turns, flip):
    """images [B, S, S, C] -> each turned by turns [B] (0-3) quarter turns, then mirrored left-right where flip [B]
    is 1: the 8 symmetries of the square grid, one per sample."""
    def one(image, k, f):
        turned = jax.lax.switch(k, [lambda m, j=j: jnp.rot90(m, j, axes=(0, 1)) for j in range(4)], image)
        return jnp.where(f == 1, turned[:, ::-1], turned)

    return jax.vmap(one)(images, turns, flip)


def train_regressor(d: dict, steps: int = 3000, batch: int = 64, lr: float = 1e-3, width: int = 16,
                    val_every: int = 100, seed: int = 0,
                    devices=None) -> tuple[nnx.State, dict, np.ndarray, np.ndarray]:
    """Train g on labels d (``load_labels``). Returns (the kept parameters, metrics: split sizes, held-out mean
    absolute error in ω against predicting the training labels' mean, correlation, best step; the held-out labels
    [n] and predictions [n]). devices: the data-parallel devices (default every device of every process); ValueError
    unless ``batch`` divides by their count."""
    mesh = distributed.batch_mesh(devices)
    distributed.check_batch(batch, mesh)
    pile_id = d["shard"] * 7919 + d["pile"]
    held = pile_id % 10 == 9
    val = ~held & np.isin(pile_id, np.unique(pile_id[~held])[::10])  # every tenth of the other piles, at least one
    x = np.asarray(d["inputs"])
    y = (np.asarray(d["label"], np.float32) - OMEGA_MIN) / (OMEGA_MAX - OMEGA_MIN)
    train_i, val_i, held_i = np.flatnonzero(~held & ~val), np.flatnonzero(val), np.flatnonzero(held)
    if min(len(train_i), len(val_i), len(held_i)) == 0:
        raise ValueError(f"{len(d['label'])} labels are too few to hold out and validate on a tenth of the piles "
                         "each; label more scenes")
    model = Regressor(width=width, rngs=nnx.Rngs(seed))
    graphdef, params = nnx.split(model)
    opt = optax.adam(optax.cosine_decay_schedule(lr, steps, alpha=0.05))
    params, state = distributed.replicated((params, opt.init(params)), mesh)
    whole = distributed.whole(mesh)

    def loss_fn(p, inputs, target):
        pred = (nnx.merge(graphdef, p)(inputs) - OMEGA_MIN) / (OMEGA_MAX - OMEGA_MIN)
        return jnp.mean(jnp.square(pred - target))

    @functools.partial(jax.jit, out_shardings=whole)
    def step(p, s, inputs, target, turns, flip):
        loss, grads = jax.value_and_grad(loss_fn)(p, dihedral(inputs, turns, flip), target)
        updates, s = opt.update(grads, s, p)
        return optax.apply_updates(p, updates), s, loss

    x_val, y_val = distributed.replicated((x[val_i], y[val_i]), mesh)
    validation_loss = jax.jit(lambda p: loss_fn(p, x_val, y_val), out_shardings=whole)
    rng = np.random.default_rng(seed)
    best, best_loss, best_step = params, float(distributed.host(validation_loss(params))), 0
    for i in progress.bar(range(1, steps + 1), desc="train regressor", unit="step"):
        idx = rng.choice(train_i, batch)
        turns, flip = rng.integers(0, 4, batch), rng.integers(0, 2, batch)
        params, state, _ = step(params, state, *distributed.sharded((x[idx], y[idx], turns, flip), mesh))
        if i % val_every == 0 or i == steps:
            loss = float(distributed.host(validation_loss(params)))
            if loss < best_loss:
                best, best_loss, best_step = params, loss, i
    params = distributed.host(best)
    predict = jax.jit(lambda p, xs: nnx.merge(graphdef, p)(xs))
    pred = np.asarray(predict(params, x[held_i]))
    truth = d["label"][held_i].astype(np.float64)
    mean_label = float(d["label"][train_i].mean())
    metrics = dict(train=len(train_i), validation=len(val_i), held_out=len(held_i),
                   mae=float(np.abs(pred - truth).mean()), mae_predict_mean=float(np.abs(mean_label - truth).mean()),
                   mean_label=mean_label,
                   correlation=float(np.corrcoef(pred, truth)[0, 1]) if truth.std() > 0 else float("nan"),
                   params=int(sum(v.size for v in jax.tree.leaves(params))), steps=steps, best_step=best_step,
                   validation_mse=best_loss)
    return params, metrics, truth, pred
