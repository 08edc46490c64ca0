"""The dynamics f(z, u, ω) of the paper: one PropNet-style graph network for every resolution ω, as encode (steps
1-3 below), process (4) and decode (5): ``Dynamics.encode``, ``process``, ``decode``.

A state z is a padded particle set: positions [N, 3] (metres, world frame) with a mask [N]; an action u is a push
(x_start, y_start, x_end, y_end) in metres. One call predicts the positions after the push:

1. Sweep heuristic (``graph.sweep_displacement``): every particle gets a guessed displacement from the action.
2. Edges (``graph.build_edges``) on the guessed positions: j -> i when |p_i - p_j| < r_edge and j is among i's k
   nearest particles.
3. Encoders. Node: [guessed displacement (3), attribute (1), resolution code (1)] -> MLP 5 -> H -> H. Edge:
   [attribute of receiver, attribute of sender, p_r - p_s (3, on the current, un-displaced positions), resolution
   code (1)] -> MLP 6 -> H -> H -> H. The attribute is 1 for a particle. ReLU after every encoder layer.
4. Propagation, ``propagation_steps`` times (PropNet): edge effect = ReLU(W_e [edge code, receiver effect, sender
   effect, code]); node effect = ReLU(W_n [node code, sum of incoming edge effects, code] + node effect), starting
   from the node code.
5. Predictor H -> H -> 3: a displacement added to the current position.

Options (``DynamicsConfig``; all off by default, which is the architecture above). ``push_frame``: everything is
expressed in the push's frame (axes: along the push, its left normal, up; origin at the push start), so the model is
invariant to the push's direction and every particle, not only the swept ones, knows where the plate passes. Node
input: [guess along the push (1), s, t, s - L, L (1 each; s along and t sideways from the start, L the push length),
attribute (1), resolution code (1)] -> MLP 7 -> H -> H; edge p_r - p_s in the push frame; the predicted displacement
is rotated back to the world frame. ``world_edges`` (with ``push_frame``): the edges' p_r - p_s stay in the world
frame, so edge codes do not depend on the push (the shipped model: as accurate, and the planner builds its edge codes
once per plan, "Pair table" below). ``residual``: the network predicts a correction added to the sweep's guess; the
predictor's last layer starts at zero, so an untrained model is exactly the sweep heuristic. ``bin_position``: the
node input also holds where the particle is in the bin, before and after the sweep's guess (x, y of each over
``bin_half_width``: 4 more inputs), so the model can learn where the walls stop a pile; the push frame alone does not
say where the walls are. Options studied and dropped: ``docs/history.md``.

Processor ``"gns"`` (``DynamicsConfig.processor``; default ``"propnet"``, steps 3-4 above): the encode-process-decode
network of GNS (Sanchez-Gonzalez et al. 2020) on the same graph and inputs. Encoders: node input -> MLP -> LayerNorm;
edge input [p_r - p_s (3), |p_r - p_s| (1), resolution code (1)] -> MLP -> LayerNorm (the constant attribute is
dropped). Then ``propagation_steps`` message-passing steps, each with weights of its own: an edge's message
m_ij = LN(MLP([e_ij, v_i, v_j])), e_ij <- e_ij + m_ij; a node's update v_i <- v_i + LN(MLP([v_i, Σ_j m_ij])). Every
MLP has two layers (H -> H, ReLU between). The decoder is the predictor above. The first layer of the edge MLP is
split as PropNet's propagator is (receiver and sender terms per node, gathered), so the per-edge work of a step is two
H x H products. It has no pair table and computes in float32 only.

The reference's architecture (``REFERENCE``: H = 64, 3 propagation steps, the four options off) has 38,403
parameters, the reference's "about 38k"; the defaults are the shipped model's (the four options on).

Resolution code. Like the reference, the model is conditioned on the particle density 1/r², r the FPS covering radius
of the sample (``perception.Particles.radius``): it says how much material one particle stands for, which the
particle count ω alone does not (ω particles over a spread-out pile are sparser than over a compact one). The code is
the normalised log-density ``resolution_code(r) = log(R_REF / r) = ½ log(ρ / ρ_ref)``, ρ = 1/r², ρ_ref = 1/R_REF²,
with R_REF = 2 cm. Piles in the 0.4 m bin at ω in [2, 100] have r from about 5 mm to 20 cm, so codes lie in about
[-2.3, 1.4]. The code is a scalar per scene, fed to every encoder and propagator.

Normalisation: fixed scales only. Guessed displacements and relative positions are divided by ``length_scale``
(5 cm, about a plate half-width; the pushes of up to 25 cm give inputs of at most about 5) and the predicted
displacement is multiplied by it. No data statistics are stored.

Masks: masked particles are inert. Their positions are replaced by zeros before anything is computed (so garbage, even
NaN, goes nowhere), they have no edges, masked edge effects are excluded from the sums, and their output equals their
input.

Evaluation: the propagators are linear layers on concatenated inputs, as in PropNet, but evaluated by splitting their
kernels: the terms that do not change across steps (edge code, node code, resolution code, bias) are computed once,
and the receiver and sender terms per node before gathering, so propagation does no per-edge matrix product.

Pair table (``pair_table=True``; the same result): an edge's code depends on the particles' positions before the
push, and on the push only through which pairs are edges (the kNN on the swept positions) unless the edges are in the
push frame. The planner scores many pushes from the same particles, so it computes the edge encoder and the edge
propagator's constant terms once on all N x N pairs (they depend on the positions and the resolution only, and
``jax.vmap`` over pushes leaves them unbatched) and each push gathers its [N, k] rows from that table: the per-push
cost of the edge encoder is gone. A table is N / k = 10 times the edges of one push, so training and single
predictions do without it.

Mixed precision (``edge_dtype``, float32 by default): the per-edge tensors, N·k rows against N for everything else,
carry almost all of the memory traffic and matrix products, so they may be bfloat16. With ``edge_dtype=bfloat16``
the edge encoder (its inputs and parameters cast), the edge propagator's per-edge constant and the per-edge effects
are bfloat16; the sum over incoming edges accumulates in float32, and the sweep heuristic, the edges, the relative
positions (until the encoder's input), every per-node tensor, the predictor and the output stay float32, as do the
gradients the gathers send back to the nodes. On the shipped checkpoint (random pushes through random piles of 20
to 100 particles) predictions move by about 0.03 mm on average and at most about 0.5 mm, and gradients w.r.t. the
push by about 0.5 % (median). bfloat16 nodes as well cost 0.15 mm on average and up to 1 cm (node inputs of up to
about 8 length scales keep only 8 significant bits) for tensors a tenth the size, so the nodes stay float32.

For hot loops use the pure functions ``predict`` and ``rollout`` of ``nnx.split(model)``; both jit and vmap over
scenes, actions and resolution codes.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
from flax import nnx

from dynres_jax.config import SceneConfig, check_fields
from dynres_jax.models.graph import K_NEIGHBOURS, R_EDGE, build_edges, push_geometry, sweep_displacement
from dynres_jax.models.propagation import GNSStep, gather_rows, incoming_effects, mlp

LENGTH_SCALE = 0.05  # m: displacements and relative positions are divided by this inside the model
LIMITS = dict(hidden=4096, propagation_steps=64, k=64)  # the most of each a model may have: a card beyond is refused
# at once, not after minutes of building it (k: neighbours among at most 100 particles)
R_REF = 0.02  # m: covering radius whose resolution code is 0
R_MIN = 1e-3  # m: radii below this (including the 0 of bad perception input) are clipped in ``resolution_code``
NODE_IN = 5  # guessed displacement (3), attribute (1), resolution code (1)
NODE_IN_PUSH_FRAME = 7  # push_frame: guess along the push, s, t, s - L, L (1 each), attribute (1), code (1)
EDGE_IN = 6  # receiver attribute (1), sender attribute (1), p_r - p_s (3), resolution code (1)
GNS_EDGE_IN = 5  # processor "gns": p_r - p_s (3), |p_r - p_s| (1), resolution code (1)
PROCESSORS = ("propnet", "gns")  # DynamicsConfig.processor


@dataclass(frozen=True)
class DynamicsConfig:
    """Static configuration of f; the defaults are the shipped model's (``train.RECIPES["shipped"]``). hidden: width
    H of every layer; propagation_steps: message-passing rounds; plate_half_width (m): the sweep heuristic's plate;
    edge_radius (m) and k: the graph; length_scale (m): the model's unit of length; bin_half_width (m): the unit of
    the ``bin_position`` inputs. The flags: module docstring, "Options"; all four off is the reference's
    architecture (``REFERENCE``). processor: "propnet" (the reference's propagation) or "gns" (module docstring,
    "Processor")."""

    hidden: int = 64
    propagation_steps: int = 3
    plate_half_width: float = SceneConfig.plate_half_width
    edge_radius: float = R_EDGE
    k: int = K_NEIGHBOURS
    length_scale: float = LENGTH_SCALE
    push_frame: bool = True
    residual: bool = True
    world_edges: bool = True
    bin_position: bool = True
    bin_half_width: float = SceneConfig.bin_half_width
    processor: str = "propnet"

    def __post_init__(self):
        check_fields(self)
        for name, most in LIMITS.items():
            if not 1 <= getattr(self, name) <= most:
                raise ValueError(f"DynamicsConfig.{name} must be at least 1 and at most {most}, got "
                                 f"{getattr(self, name)!r}")
        for name in ("plate_half_width", "edge_radius", "length_scale", "bin_half_width"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"DynamicsConfig.{name} must be positive and at most 1 m, got {getattr(self, name)!r}")
        if self.processor not in PROCESSORS:
            raise ValueError(f"DynamicsConfig.processor must be one of {', '.join(PROCESSORS)}, got {self.processor!r}")

    @property
    def node_inputs(self) -> int:
        """Width of the node encoder's input."""
        return (NODE_IN_PUSH_FRAME if self.push_frame else NODE_IN) + (4 if self.bin_position else 0)

    @property
    def edges_in_push_frame(self) -> bool:
        """Whether the edge encoder sees p_r - p_s rotated into the push frame (push_frame without world_edges), so
        its codes depend on the push and cannot come from a ``pair_table``."""
        return self.push_frame and not self.world_edges

    @property
    def pair_table(self) -> bool:
        """Whether the planner may take the first push's edge codes from a pair table (PropNet with edges that do not
        depend on the push)."""
        return self.processor == "propnet" and not self.edges_in_push_frame


REFERENCE = DynamicsConfig(push_frame=False, residual=False, world_edges=False, bin_position=False)  # the paper's f


def resolution_code(radius):
    """FPS covering radius r (m, any shape) -> resolution code log(R_REF / r) (same shape, float32): half the log of
    the density 1/r² relative to 1/R_REF². Radii below R_MIN are clipped, so the code is always finite."""
    radius = jnp.asarray(radius, jnp.float32)
    return jnp.log(R_REF / jnp.maximum(radius, R_MIN))


def _push_frame(action):
    """action [4] -> (frame [3, 3] whose rows are the unit push direction, its left normal and +z; start [2];
    length []). The rows are orthonormal, so ``v @ frame.T`` maps world vectors to the push frame and ``w @ frame``
    maps them back. A zero-length push gets a finite (arbitrary) frame."""
    start, along, length = push_geometry(action)
    frame = jnp.array([[along[0], along[1], 0.0], [-along[1], along[0], 0.0], [0.0, 0.0, 1.0]])
    return frame, start, length


def _cast(module: nnx.Module, dtype) -> nnx.Module:
    """module with its parameters cast to dtype (a copy; float32: the module itself)."""
    if jnp.dtype(dtype) == jnp.float32:
        return module
    graphdef, state = nnx.split(module)
    return nnx.merge(graphdef, jax.tree.map(lambda x: x.astype(dtype), state))


class Dynamics(nnx.Module):
    """f(z, u, ω) as a flax NNX module; see the module docstring for the architecture."""

    def __init__(self, config: DynamicsConfig = DynamicsConfig(), *, rngs: nnx.Rngs):
        h = config.hidden
        self.config = config
        if config.processor == "gns":
            self.node_encoder = nnx.Sequential(mlp((config.node_inputs, h, h), rngs, final_relu=False),
                                               nnx.LayerNorm(h, rngs=rngs))
            self.edge_encoder = nnx.Sequential(mlp((GNS_EDGE_IN, h, h), rngs, final_relu=False),
                                               nnx.LayerNorm(h, rngs=rngs))
            # one GNSStep per message-passing step; a Sequential only holds them (``_gns`` calls each by hand)
            self.steps = nnx.Sequential(*(GNSStep(h, rngs) for _ in range(config.propagation_steps)))
        else:
            self.node_encoder = mlp((config.node_inputs, h, h), rngs, final_relu=True)
            self.edge_encoder = mlp((EDGE_IN, h, h, h), rngs, final_relu=True)
            self.edge_propagator = nnx.Linear(3 * h + 1, h, rngs=rngs)  # [edge code, receiver, sender, code]
            self.node_propagator = nnx.Linear(2 * h + 1, h, rngs=rngs)  # [node code, summed edge effects, code]
        self.predictor = mlp((h, h, 3), rngs, final_relu=False)
        if config.residual:  # the correction starts at zero: an untrained model is the sweep heuristic
            last = self.predictor.layers[-1]
            last.kernel[...] = jnp.zeros_like(last.kernel[...])
            last.bias[...] = jnp.zeros_like(last.bias[...])

    def __call__(self, positions, mask, action, code, *, edge_dtype=jnp.float32, pair_table=False, table=None):
        """positions [N, 3] m, mask [N] bool, action [4] m, code [] (``resolution_code``) -> next positions [N, 3] m
        (float32). Masked rows are returned unchanged. edge_dtype: float32 or bfloat16, the per-edge network's
        dtype (module docstring, "Mixed precision"). pair_table: edge codes gathered from a table over all N x N
        pairs (module docstring, "Pair table"); the same result, for edges not in the push frame only. table: that
        table, already built by ``edge_table`` for these positions, mask, code and edge_dtype (implies pair_table)."""
        if pair_table or table is not None:
            self._check_pair_table()
        positions, mask = jnp.asarray(positions, jnp.float32), jnp.asarray(mask, bool)
        code, action = jnp.asarray(code, jnp.float32), jnp.asarray(action, jnp.float32)
        clean = jnp.where(mask[:, None], positions, 0.0)
        node_code, guess, frame, graph = self.encode(clean, mask, action, code, table is None and not pair_table)
        effect = self.process(node_code, graph, clean, mask, code, table, pair_table, jnp.dtype(edge_dtype))
        return self.decode(effect, guess, frame, positions, mask)

    def encode(self, clean, mask, action, code, relative: bool = True):
        """Steps 1-3 on masked positions clean [N, 3] m (zeros where masked): (node codes [N, H], the sweep's guess
        [N, 3] m, the push frame [3, 3] or None, the graph: neighbours [N, k], edge mask [N, k] and p_r - p_s
        [N, k, 3] in length units, in the push frame where the config says; None unless ``relative``)."""
        cfg, n = self.config, clean.shape[0]
        guess = sweep_displacement(clean, mask, action, cfg.plate_half_width)
        neighbours, edge_mask = build_edges(clean + guess, mask, cfg.edge_radius, cfg.k)
        attr, frame = mask.astype(jnp.float32)[:, None], None  # attr [N, 1]: 1 for a particle
        if cfg.push_frame:
            frame, start, length = _push_frame(action)  # frame [3, 3]: rows along, side, up
            local = (clean - jnp.concatenate([start, jnp.zeros(1, start.dtype)])) @ frame.T / cfg.length_scale  # [N, 3]
            s, t = local[:, :1], local[:, 1:2]
            ell = jnp.broadcast_to(length / cfg.length_scale, (n, 1))
            node_in = [(guess @ frame.T)[:, :1] / cfg.length_scale, s, t, s - ell, ell]
            node_in = [jnp.where(mask[:, None], x, 0.0) for x in node_in]
        else:
            node_in = [guess / cfg.length_scale]
        if cfg.bin_position:
            node_in += [xy[:, :2] / cfg.bin_half_width for xy in (clean, clean + guess)]  # 0 where masked, as both are
        node_code = self.node_encoder(jnp.concatenate(node_in + [attr, jnp.broadcast_to(code, (n, 1))], axis=-1))
        rel = (clean[:, None, :] - gather_rows(clean, neighbours)) / cfg.length_scale if relative else None
        if rel is not None and cfg.edges_in_push_frame:
            rel = rel @ frame.T
        return node_code, guess, frame, (neighbours, edge_mask, rel)

    def process(self, node_code, graph, clean, mask, code, table, pair_table: bool, dt):
        """Step 4: the node codes [N, H] after message passing on ``encode``'s graph, by the config's processor."""
        neighbours, edge_mask, rel = graph
        if self.config.processor == "gns":
            if dt != jnp.float32:
                raise ValueError("the gns processor computes in float32 only (edge_dtype)")
            return self._gns(node_code, rel, code, neighbours, edge_mask)
        attr = mask.astype(jnp.float32)[:, None]
        return self._propnet(node_code, rel, attr, code, neighbours, edge_mask, clean, table, pair_table, dt)

    def decode(self, effect, guess, frame, positions, mask):
        """Step 5: node effects [N, H] -> positions after the push [N, 3] m, masked rows unchanged."""
        cfg = self.config
        displacement = self.predictor(effect) * cfg.length_scale
        if cfg.push_frame:
            displacement = displacement @ frame  # push frame -> world frame
        if cfg.residual:
            displacement = displacement + guess  # the network predicts the correction to the sweep heuristic
        return jnp.where(mask[:, None], positions + displacement, positions)

    def _gns(self, node_code, rel, code, neighbours, edge_mask):
        """GNS's processor (module docstring, "Processor"): node codes [N, H], rel [N, k, 3] (p_r - p_s in length
        units), code [], the graph -> the latent nodes after the message-passing steps [N, H]."""
        length = jnp.sqrt(jnp.sum(jnp.square(rel), -1, keepdims=True) + 1e-12)
        edges = self.edge_encoder(jnp.concatenate([rel, length, jnp.broadcast_to(code, length.shape)], -1))
        nodes, valid = node_code, edge_mask[..., None]
        for gns_step in self.steps.layers:
            nodes, edges = gns_step(nodes, edges, neighbours, valid)
        return nodes

    def _propnet(self, node_code, rel, attr, code, neighbours, edge_mask, clean, table, pair_table, dt):
        """PropNet's propagation (module docstring, steps 3-4): -> the node effects after the steps [N, H]."""
        cfg, h = self.config, self.config.hidden
        w_e = self.edge_propagator.kernel[...]
        w_n, b_n = self.node_propagator.kernel[...], self.node_propagator.bias[...]
        if table is None and pair_table:
            table = self._table(clean, attr, code, dt)
        if table is not None:
            edge_const = table  # [N, N, H] dt: incoming_effects gathers each edge's row
        else:
            edge_const = self._edge_constant(rel, attr, attr[neighbours], code, dt)  # [N, k, H] dt
        node_const = node_code @ w_n[:h] + code * w_n[2 * h] + b_n  # [N, H]
        w_terms = jnp.concatenate([w_e[h:2 * h], w_e[2 * h:3 * h]], axis=1)  # [H, 2H]: receiver | sender
        effect = node_code
        for _ in range(cfg.propagation_steps):
            node_terms = effect @ w_terms  # [N, 2H]: receiver and sender terms
            incoming = incoming_effects(table is not None, edge_const, neighbours, edge_mask, node_terms)  # [N, H]
            effect = nnx.relu(node_const + incoming @ w_n[h:2 * h] + effect)
        return effect

    def _check_pair_table(self):
        if not self.config.pair_table:
            raise ValueError("pair_table needs PropNet edge codes that do not depend on the push: the gns processor "
                             "has none, and a model with push_frame=True and world_edges=False rotates its edges into "
                             "the push frame")

    def _edge_constant(self, rel, receiver_attr, sender_attr, code, dt):
        """rel [R, S, 3] (p_r - p_s in length units), receiver_attr [R, 1], sender_attr [R, S, 1], code [] -> the
        edge propagator's terms that do not change across propagation steps [R, S, H] in dt: the edge code, the
        resolution code's and the bias."""
        h, w_e, b_e = self.config.hidden, self.edge_propagator.kernel[...], self.edge_propagator.bias[...]
        edge_code = _cast(self.edge_encoder, dt)(jnp.concatenate(
            [jnp.broadcast_to(receiver_attr[:, None], sender_attr.shape), sender_attr, rel,
             jnp.broadcast_to(code, sender_attr.shape)], axis=-1).astype(dt))
        return edge_code @ w_e[:h].astype(dt) + (code * w_e[3 * h]).astype(dt) + b_e.astype(dt)

    def edge_table(self, positions, mask, code, *, edge_dtype=jnp.float32):
        """The pair table (module docstring, "Pair table"): positions [N, 3] m, mask [N], code [] -> the edge
        propagator's constant terms for every pair, [N, N, H] in edge_dtype (receiver i, sender j). Edges in the
        push frame have no table (ValueError)."""
        self._check_pair_table()
        mask = jnp.asarray(mask, bool)
        clean = jnp.where(mask[:, None], jnp.asarray(positions, jnp.float32), 0.0)
        return self._table(clean, mask.astype(jnp.float32)[:, None], jnp.asarray(code, jnp.float32),
                           jnp.dtype(edge_dtype))

    def _table(self, clean, attr, code, dt):
        """``edge_table`` of masked positions clean [N, 3] (zeros where masked) with attributes attr [N, 1]."""
        rel = (clean[:, None, :] - clean[None, :, :]) / self.config.length_scale
        return self._edge_constant(rel, attr, jnp.broadcast_to(attr[None], rel.shape[:2] + (1,)), code, dt)

    def rollout(self, positions, mask, actions, code, *, edge_dtype=jnp.float32):
        """positions [N, 3] m, mask [N], actions [T, 4] m, code [] -> positions after each action [T, N, 3] m."""
        return rollout(*nnx.split(self), positions, mask, actions, code, edge_dtype=edge_dtype)


def predict(graphdef, state, positions, mask, action, code, *, edge_dtype=jnp.float32, pair_table=False, table=None):
    """Pure f of ``nnx.split(model)``: positions [N, 3] m, mask [N], action [4] m, code [] -> next positions [N, 3].
    edge_dtype, pair_table, table: ``Dynamics.__call__``'s; only the GNN takes them, so the defaults call any model
    of that signature."""
    model = nnx.merge(graphdef, state)
    options = {}
    if jnp.dtype(edge_dtype) != jnp.float32:
        options["edge_dtype"] = edge_dtype
    if pair_table:
        options["pair_table"] = True
    if table is not None:
        options["table"] = table
    return model(positions, mask, action, code, **options)


def edge_table(graphdef, state, positions, mask, code, *, edge_dtype=jnp.float32):
    """Pure ``Dynamics.edge_table`` of ``nnx.split(model)``: positions [N, 3] m, mask [N], code [] -> [N, N, H]."""
    return nnx.merge(graphdef, state).edge_table(positions, mask, code, edge_dtype=edge_dtype)


def rollout(graphdef, state, positions, mask, actions, code, *, edge_dtype=jnp.float32, pair_table=False,
            table=None):
    """Pure multi-step f (``lax.scan``): positions [N, 3] m, mask [N], actions [T, 4] m, code [] -> [T, N, 3] m,
    the positions after each action (the initial positions not included). edge_dtype: as in ``predict``;
    pair_table: the first push's edge codes from a table (``Dynamics.__call__``), the only push whose particles do
    not depend on the actions; table: that table, already built (``edge_table``; implies pair_table)."""
    if pair_table or table is not None:
        first = predict(graphdef, state, positions, mask, actions[0], code, edge_dtype=edge_dtype, pair_table=True,
                        table=table)
        rest = rollout(graphdef, state, first, mask, actions[1:], code, edge_dtype=edge_dtype)
        return jnp.concatenate([first[None], rest], axis=0)

    def step(current, action):
        nxt = predict(graphdef, state, current, mask, action, code, edge_dtype=edge_dtype)
        return nxt, nxt

    return jax.lax.scan(step, jnp.asarray(positions, jnp.float32), actions)[1]


def count_params(model: nnx.Module) -> int:
    """Number of trainable scalars in the model."""
    return sum(x.size for x in jax.tree.leaves(nnx.state(model, nnx.Param)))
