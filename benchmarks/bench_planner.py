"""Planner benchmark: one gradient step of the shooting planner (paper Algorithm 1) against a PyTorch reference.

Batch: the reference code's demo, M = 50 pushes × R = 30 re-samplings of the particles = 1,500 candidates of one push
(T = 1) each, over N = 100 particles; every candidate is rolled out through the dynamics f, scored, differentiated
with respect to its push, and the pushes take one Adam step and are clamped to the workspace.

- PyTorch reference (``torch.nn``, eager, CUDA when available): one step of the reference code's planner
  (``PlannerGD.trajectory_optimization_ptcl_multi_traj``) with PAPER.md's PropNet ("Graph and dynamics") written in the
  reference code's style. The sweep heuristic and the edges (``cdist`` + ``topk`` + radius) are computed in torch for
  the whole batch; the edges become dense one-hot relation matrices Rr, Rs [B, n_rel, N] (n_rel = N·k, padded with zero
  rows) and every gather and sum is a ``bmm``: edge inputs ``Rr @ x`` and ``Rs @ x``, incoming effects ``Rr^T @
  effect``. Node encoder 5→64→64, edge encoder 6→64→64→64, 3 propagation steps with a residual, predictor 64→64→3. The
  predicted particles are scored with the task objective c exactly as the JAX planner scores them (the reference's
  ``config_reward_ptcl``: projected to pixels with our camera, the goal's signed distance field read by ``grid_sample``,
  plus the distance from each of the first 5 ω FPS goal samples to its nearest particle, over ω; the same disc goal;
  ``objective_px`` holds its values on the unpushed piles, with exact distances, so ``run`` can check them against JAX's
  c); a push's cost is the mean over its R re-samplings, the best push seen so far is kept, and the step is ``backward``
  to the actions (the model's weights are frozen), ``torch.optim.Adam`` and a clamp. The coverage term's distances are
  timed two ways, the reference's (``torch.norm`` of the broadcast differences) and ``torch.cdist``, and the faster one
  is the peer (``ms_per_step``). ``ms_per_step_network_only`` is the same step scored by the mean squared distance to a
  point instead of c, without the best-push record (the peer of earlier versions of this benchmark, kept so its figures
  can be compared). Time per step: the median of single steps after warm-up, with ``torch.cuda.synchronize`` around
  each. The reference's per-step host round trips (a Python loop over the batch to build its relation matrices and to
  keep the best push, ``.item()`` reads) are left out: they cost time without doing work. It is a speed peer, not
  numerically equal to our model (different weights).
- JAX: ``planner.plan`` with the real ``Dynamics`` (random weights) and the task objective c on a disc goal, on the
  device JAX sees. ``plan`` is timed (median of repeated calls after a compiling first call) at the full step count
  and at a tenth of it; the time per Adam step is the difference divided by the difference in steps, which removes
  the fixed cost of a call (sampling the pushes, the final evaluation, dispatch). The full plan's wall time is
  reported as is; compile time (first call minus the median) separately for both step counts.

Both sides use float32 with each library's default matmul precision. JAX is timed a second time with the model's
per-edge network in bfloat16 (``registry.learned_dynamics(model, "bfloat16")``, the ``dynamics`` module's "Mixed
precision"), the ``jax_bf16`` section; it also says how far that is from float32 on the same inputs: predicted
positions (mm) and the best cost of a full plan (pixels), measured on the shipped checkpoint when there is one (a
trained model's numbers; the timed random weights blow a pile metres apart). Speed-up = torch ms per step / JAX ms
per step (``speedup``, and ``speedup_bf16`` for the bfloat16 section). When a checkpoint is shipped, the
``jax_shipped`` section times the planner in float32 with it (its architecture may differ from the reference's, e.g.
push-frame inputs) and ``speedup_shipped`` is its ratio. ``jax_stages`` splits a step's time into its stages
(``_stage_times``). ``run(quick=True)`` uses tiny sizes so it finishes in seconds on a CPU; without torch the
reference is skipped (noted in the result).
"""

from __future__ import annotations

import functools
import os
import time

import numpy as np

PILE_RADIUS = 0.06  # m: particles uniform in a disc of this radius around the bin centre
PARTICLE_Z = 0.005  # m: particle height
PARTICLE_RADIUS = 0.01  # m: covering radius fed to the resolution code
GOAL_XY = (0.08, 0.05)  # m: centre of the disc goal (JAX) and the target point (torch)
GOAL_RADIUS = 0.04  # m
SPEEDUP_GOAL = 15.0  # the goal: JAX at least this many times faster per step than the reference
PLAN_GOAL_S = 1.0  # the goal: a full plan at the full batch under this many seconds

FULL = dict(particles=100, samples=50, resamples=30, steps=200, repeats=5, torch_repeats=20)
QUICK = dict(particles=16, samples=4, resamples=2, steps=10, repeats=5, torch_repeats=3)


def _piles(particles: int, resamples: int, seed: int = 0) -> np.ndarray:
    """[R, N, 3] float32: R independent re-samplings of N particles uniform in the pile's disc."""
    rng = np.random.default_rng(seed)
    r = PILE_RADIUS * np.sqrt(rng.uniform(size=(resamples, particles)))
    phi = rng.uniform(-np.pi, np.pi, size=(resamples, particles))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.full_like(r, PARTICLE_Z)], -1).astype(np.float32)


def _median_s(fn, repeats: int, sync) -> float:
    """Median wall time of ``repeats`` calls of fn (seconds), ``sync`` called before each clock read."""
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


# ---------------------------------------------------------------------------------------------------------------
# PyTorch reference
# ---------------------------------------------------------------------------------------------------------------

def _torch_reference(positions: np.ndarray, samples: int, repeats: int) -> dict:
    """Median ms of one planner step of the PyTorch reference on ``samples`` × R candidates (module docstring)."""
    import torch
    import torch.nn.functional as F
    from torch import nn

    from dynres_jax.config import SceneConfig
    from dynres_jax.control.objective import SAMPLES_PER_PARTICLE
    from dynres_jax.control.planner import PlannerConfig
    from dynres_jax.models.dynamics import LENGTH_SCALE, R_REF
    from dynres_jax.models.graph import K_NEIGHBOURS, R_EDGE, SWEEP_END_OFFSET, SWEEP_FALLOFF

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    planner = PlannerConfig()
    camera, goal = _camera_and_goal()

    def tensor(x):
        return torch.as_tensor(np.array(x, np.float32), device=device)

    rotation, centre = tensor(camera.rotation), tensor(camera.centre)
    focal, principal = tensor(np.diag(camera.K)[:2]), tensor(camera.K[:2, 2])
    image_size = tensor([camera.width, camera.height])
    sdf = tensor(goal.distance)[None, None]  # [1, 1, H, W] pixels
    n = positions.shape[1]
    first = np.asarray(goal.samples)[:SAMPLES_PER_PARTICLE * n]
    goal_samples = tensor(first[np.asarray(goal.sample_mask)[:SAMPLES_PER_PARTICLE * n]])  # Q' [min(5 ω, Q), 2]

    def smoothstep(x):
        x = x.clamp(0.0, 1.0)
        return x * x * (3.0 - 2.0 * x)

    def sweep(p, a):
        """Guessed displacements [B, N, 3] of particles p [B, N, 3] under pushes a [B, 4] (graph.sweep_displacement)."""
        start, delta = a[:, None, :2], a[:, 2:] - a[:, :2]
        length = delta.square().sum(-1).add(1e-12).sqrt()[:, None]
        along = delta[:, None] / length[..., None]
        side = torch.stack([-along[..., 1], along[..., 0]], -1)
        rel = p[..., :2] - start
        s, t = (rel * along).sum(-1), (rel * side).sum(-1)
        sideways = smoothstep((SceneConfig.plate_half_width + SWEEP_FALLOFF - t.abs()) / SWEEP_FALLOFF)
        gate = sideways * smoothstep((s + SWEEP_FALLOFF) / SWEEP_FALLOFF)
        push = gate * (length + SWEEP_END_OFFSET - s).clamp(min=0.0)
        return torch.cat([push[..., None] * along, torch.zeros_like(push[..., None])], -1)

    @torch.no_grad()
    def relations(p):
        """Dense one-hot Rr, Rs [B, N·k, N] of the radius + kNN edges on p [B, N, 3] (receiver i, sender j)."""
        b, n, _ = p.shape
        d2 = torch.cdist(p, p).square() + torch.eye(n, device=p.device) * 1e10
        dist, senders = torch.topk(d2, min(K_NEIGHBOURS, n - 1), dim=-1, largest=False)
        k = senders.shape[-1]
        valid = (dist < R_EDGE ** 2).to(p.dtype).reshape(b, n * k)
        rows = torch.arange(n * k, device=p.device)
        rr = torch.zeros(b, n * k, n, device=p.device)
        rr[:, rows, rows // k] = valid
        rs = torch.zeros(b, n * k, n, device=p.device).scatter_(2, senders.reshape(b, n * k, 1), valid[..., None])
        return rr, rs

    def mlp(*sizes, final_relu):
        layers = []
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            layers.append(nn.Linear(a, b))
            if final_relu or i < len(sizes) - 2:
                layers.append(nn.ReLU())
        return nn.Sequential(*layers)

    class PropNet(nn.Module):
        """PAPER.md's PropNet with dense relation matrices, as the reference code builds it."""

        def __init__(self, h=64, steps=3):
            super().__init__()
            self.steps = steps
            self.node_encoder = mlp(5, h, h, final_relu=True)
            self.edge_encoder = mlp(6, h, h, h, final_relu=True)
            self.edge_propagator = nn.Linear(3 * h + 1, h)
            self.node_propagator = nn.Linear(2 * h + 1, h)
            self.predictor = mlp(h, h, 3, final_relu=False)

        def forward(self, p, a, code):
            """p [B, N, 3] m, a [B, 4] m, code float -> positions after the push [B, N, 3] m."""
            guess = sweep(p, a)
            rr, rs = relations(p + guess)
            rr_t = rr.transpose(1, 2)
            b, n, _ = p.shape
            attr = torch.ones(b, n, 1, device=p.device)
            node_res = torch.full((b, n, 1), code, device=p.device)
            edge_res = torch.full((b, rr.shape[1], 1), code, device=p.device)
            node_code = self.node_encoder(torch.cat([guess / LENGTH_SCALE, attr, node_res], -1))
            rel = (rr.bmm(p) - rs.bmm(p)) / LENGTH_SCALE
            edge_code = self.edge_encoder(torch.cat([rr.bmm(attr), rs.bmm(attr), rel, edge_res], -1))
            effect = node_code
            for _ in range(self.steps):
                edge_effect = torch.relu(self.edge_propagator(
                    torch.cat([edge_code, rr.bmm(effect), rs.bmm(effect), edge_res], -1)))
                effect = torch.relu(self.node_propagator(torch.cat([node_code, rr_t.bmm(edge_effect), node_res], -1))
                                    + effect)
            return p + self.predictor(effect) * LENGTH_SCALE

    coverage_distances = {  # goal samples q [Q, 2], pixels uv [B, N, 2] -> [B, Q, N]
        "broadcast": lambda q, uv: torch.norm(q[None, :, None, :] - uv[:, None], dim=-1),  # the reference's
        "cdist": lambda q, uv: torch.cdist(q.expand(uv.shape[0], -1, -1), uv),
    }

    def task_cost(p, distances):
        """c of particles p [B, N, 3] (world, m) -> [B] pixels: objective.objective, the reference's way."""
        p_cam = (p - centre) @ rotation  # sim/camera.Camera.world_to_pixel
        uv = p_cam[..., :2] / p_cam[..., 2:] * focal + principal
        grid = (uv / image_size * 2 - 1)[:, None]  # [B, 1, N, 2]; align_corners=False: -1 is pixel 0's outer edge
        sdf_term = F.grid_sample(sdf.expand(p.shape[0], -1, -1, -1), grid, padding_mode="border",
                                 align_corners=False).sum((1, 2, 3))
        coverage_term = distances(goal_samples, uv).min(-1).values.sum(-1)
        return (sdf_term + coverage_term) / p.shape[1]

    torch.manual_seed(0)
    model = PropNet().to(device).requires_grad_(False)
    resamples = positions.shape[0]
    pile = torch.as_tensor(positions, device=device).repeat(samples, 1, 1)  # [M·R, N, 3], candidate i: pile i % R
    target = torch.tensor(GOAL_XY, device=device)
    code = float(np.log(R_REF / PARTICLE_RADIUS))
    gen = torch.Generator().manual_seed(0)
    start = (torch.rand(samples, 2, generator=gen) - 0.5) * 0.1 - 0.05
    actions = torch.cat([start, start + 0.1], -1).to(device).requires_grad_(True)
    optimiser = torch.optim.Adam([actions], lr=planner.lr)
    best, best_cost = actions.detach().clone()[0], torch.tensor(float("inf"), device=device)

    def step(distances):
        """One planner step; distances: a ``coverage_distances`` entry, or None for the network-only peer."""
        optimiser.zero_grad(set_to_none=True)
        final = model(pile, actions.repeat_interleave(resamples, 0), code)
        if distances is None:
            (final[..., :2] - target).square().sum(-1).mean().backward()
        else:
            costs = task_cost(final, distances).view(samples, resamples).mean(1)  # a push: mean over re-samplings
            costs.sum().backward()
            with torch.no_grad():  # the best push seen so far (planner.keep_best)
                i = torch.argmin(costs)
                better = costs[i] < best_cost
                best.copy_(torch.where(better, actions[i], best))
                best_cost.copy_(torch.where(better, costs[i], best_cost))
        optimiser.step()
        with torch.no_grad():
            actions.clamp_(-planner.bound, planner.bound)

    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    ms = {}
    for name, distances in [("network_only", None), *coverage_distances.items()]:
        for _ in range(3):  # warm-up: cuBLAS handles, allocator
            step(distances)
        ms[name] = 1e3 * _median_s(lambda distances=distances: step(distances), repeats, sync)
    with torch.no_grad():  # exact distances (cdist's matrix-product shortcut rounds them)
        objective_px = task_cost(torch.as_tensor(positions, device=device), coverage_distances["broadcast"])
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    if device.type == "cuda":
        torch.cuda.empty_cache()  # hand the memory back before JAX allocates
    peer = min(coverage_distances, key=ms.get)
    return dict(device=name, torch_version=torch.__version__, ms_per_step=ms[peer], coverage_distances=peer,
                ms_per_step_by_coverage={k: ms[k] for k in coverage_distances},
                ms_per_step_network_only=ms["network_only"], objective_px=objective_px.cpu().tolist(),
                params=sum(p.numel() for p in model.parameters()), relations_per_candidate=n * min(K_NEIGHBOURS, n - 1))


# ---------------------------------------------------------------------------------------------------------------
# JAX
# ---------------------------------------------------------------------------------------------------------------

def _quality_model(timed_model):
    """(model, its name) that the bfloat16 agreement is measured on: the shipped checkpoint when there is one (the
    random weights of the timed model blow a pile metres apart, so their errors say little), else the timed model."""
    from dynres_jax.io import ckpt
    from dynres_jax.models.registry import SHIPPED_DYNAMICS, build_model

    if ckpt.latest_step(SHIPPED_DYNAMICS) is None:
        return timed_model, "random weights (the timed model)"
    model, meta, _ = ckpt.load_module(SHIPPED_DYNAMICS, build_model)
    return model, f"shipped checkpoint (step {meta.get('step')})"


@functools.cache
def _camera_and_goal():
    """(camera, Goal): the default top-down camera and the disc goal both sides score against (built once: the goal's
    FPS samples are computed on the host)."""
    from dynres_jax.control.goals import disc_goal, make_goal
    from dynres_jax.sim.camera import Camera, CameraConfig

    camera = Camera.top_down(CameraConfig())
    return camera, make_goal(disc_goal(camera, GOAL_XY, GOAL_RADIUS), camera)


def _timed_model_and_cost():
    """(model, cost) that the JAX sections time: the GNN with the reference's architecture (random weights) and the
    task cost c on the disc goal."""
    from flax import nnx

    from dynres_jax.control.decision import goal_cost
    from dynres_jax.models.dynamics import REFERENCE, Dynamics

    camera, goal = _camera_and_goal()
    return Dynamics(REFERENCE, rngs=nnx.Rngs(0)), goal_cost(goal, camera)


def _stage_times(positions: np.ndarray, samples: int, repeats: int) -> dict:
    """Where a planner step's time goes: ms (median of ``repeats`` calls, each stage jitted alone, float32, the
    reference architecture) over the planner's batch of ``samples`` pushes x R re-samplings. edges: the sweep
    heuristic and the radius + kNN edges of every candidate; cost: the task cost c and its gradient w.r.t. the
    particles of every candidate; dynamics: f and its gradient w.r.t. the pushes, with the pair table built
    beforehand, as the planner builds it once per plan. A step also runs the chain rule between them, Adam and the
    projection."""
    import jax
    import jax.numpy as jnp

    from dynres_jax.control.planner import _prepared
    from dynres_jax.models.graph import build_edges, sweep_displacement
    from dynres_jax.models.registry import learned_dynamics
    from dynres_jax.sim.pushes import sample_actions

    model, cost = _timed_model_and_cost()
    dynamics = learned_dynamics(model)(PARTICLE_RADIUS)
    c, pile, mask, key = _plan_inputs(positions, samples)
    pushes = sample_actions(key, samples, 1, c.bound, c.min_length, c.max_length, jnp.zeros(2))

    def per_candidate(fn, *per_pile):  # fn(positions [N, 3], mask [N], push [1, 4], *per_pile[r]) over M x R
        return jax.vmap(lambda a: jax.vmap(lambda p, m, *x: fn(p, m, a, *x))(pile, mask, *per_pile))

    def edges(p, m, a):
        return build_edges(p + sweep_displacement(p, m, a[0], model.config.plate_half_width), m)

    with_context, context = _prepared(dynamics, pile, mask)  # the pair table of every re-sampling

    def moved(a, context):
        return jnp.sum(per_candidate(lambda p, m, a1, ctx: with_context(p, m, a1, ctx)[-1], context)(a))

    edges_fn, moved_fn = jax.jit(per_candidate(edges)), jax.jit(jax.value_and_grad(moved))
    cost_fn = jax.jit(jax.vmap(jax.vmap(jax.value_and_grad(cost))))
    piles, masks = jnp.broadcast_to(pile, (samples,) + pile.shape), jnp.broadcast_to(mask, (samples,) + mask.shape)
    stages = dict(edges=lambda: edges_fn(pushes), cost=lambda: cost_fn(piles, masks),
                  dynamics=lambda: moved_fn(pushes, context))
    out = {}
    for name, call in stages.items():
        jax.block_until_ready(call())  # compile
        out[f"{name}_ms"] = 1e3 * _median_s(lambda call=call: jax.block_until_ready(call()), repeats, lambda: None)
    return out


def _plan_inputs(positions: np.ndarray, samples: int):
    """(PlannerConfig, piles, mask, key) of a timed plan: ``samples`` pushes over the R re-samplings positions [R, N, 3]
    (all particles valid), on the device, PRNG key 0."""
    import jax

    from dynres_jax.control.planner import PlannerConfig

    config = PlannerConfig(samples=samples, resamples=positions.shape[0])
    return (config, jax.device_put(positions), jax.device_put(np.ones(positions.shape[:2], bool)),
            jax.random.PRNGKey(0))


def _plan_section(model, cost, edge_dtype, positions: np.ndarray, samples: int, steps: int, repeats: int) -> dict:
    """Time ``planner.plan`` of ``model`` (per-edge network in edge_dtype) scoring ``cost`` over ``samples`` pushes x
    the R re-samplings positions [R, N, 3], at ``steps`` and at a tenth of it -> a section of the result: ms per step
    from the difference, both plans' median wall time and compile time (first call less the median; the step count
    is traced, so the plan compiles at its first call, the short one: compile_s is the larger of the two)."""
    import jax

    from dynres_jax.control.planner import plan
    from dynres_jax.models.dynamics import count_params
    from dynres_jax.models.registry import learned_dynamics

    config, pile, mask, key = _plan_inputs(positions, samples)
    device, short = jax.devices()[0], max(1, steps // 10)
    dynamics = learned_dynamics(model, edge_dtype)(PARTICLE_RADIUS)

    def timed(n):
        """(compile s, median s) of a plan of n steps."""
        t0 = time.perf_counter()
        jax.block_until_ready(plan(dynamics, cost, pile, mask, key, config, adam_steps=n))
        first = time.perf_counter() - t0
        wall = _median_s(lambda: jax.block_until_ready(plan(dynamics, cost, pile, mask, key, config, adam_steps=n)),
                         repeats, lambda: None)
        return first - wall, wall

    compile_short, wall_short = timed(short)
    compile_full, wall_full = timed(steps)
    return dict(device=f"{device.platform}: {device.device_kind}", jax_version=jax.__version__, edge_dtype=edge_dtype,
                params=count_params(model), ms_per_step=1e3 * (wall_full - wall_short) / (steps - short),
                short_steps=short, short_plan_s=wall_short, steps=steps, plan_s=wall_full,
                plan_ms_per_step=1e3 * wall_full / steps, compile_s=max(compile_full, compile_short),
                compile_short_s=compile_short)


def _jax_planner(positions: np.ndarray, samples: int, steps: int, repeats: int) -> tuple[dict, dict, dict | None]:
    """Time ``planner.plan`` at ``steps`` and at a tenth of it, ms per step from the difference, with the model's
    per-edge network in float32 and in bfloat16 (``registry.learned_dynamics``'s edge_dtype) -> (float32 section,
    bfloat16 section, the shipped checkpoint's float32 section or None when no checkpoint is shipped). The bfloat16
    section also holds its agreement with float32 on the same piles, goal, key and steps (on ``_quality_model``):
    prediction_mean_mm and prediction_max_mm, |bfloat16 - float32| of the predicted positions at the float32 plan's
    final pushes (every push on every re-sampling); float32_best_cost, the float32 plan's best cost;
    best_cost_in_float32, the bfloat16 plan's best push scored by the float32 model (the honest peer of
    float32_best_cost); best_cost, as the bfloat16 model scores it; initial_cost, the piles unpushed (all costs in
    pixels, the mean over the re-samplings)."""
    import jax
    import jax.numpy as jnp

    from dynres_jax.control.planner import plan
    from dynres_jax.models.registry import EDGE_DTYPES, learned_dynamics

    model, cost = _timed_model_and_cost()
    config, pile, mask, key = _plan_inputs(positions, samples)

    def section(model, edge_dtype):
        return _plan_section(model, cost, edge_dtype, positions, samples, steps, repeats)

    f32, bf16 = (section(model, edge_dtype) for edge_dtype in EDGE_DTYPES)

    quality_model, quality_name = _quality_model(model)
    shipped = None
    if quality_model is not model:  # the shipped architecture may differ from the reference's (push frame)
        shipped = dict(section(quality_model, "float32"), model=quality_name, config=vars(quality_model.config))
    dynamics = {d: learned_dynamics(quality_model, d)(PARTICLE_RADIUS) for d in EDGE_DTYPES}
    plans = {d: plan(dynamics[d], cost, pile, mask, key, config, adam_steps=steps) for d in EDGE_DTYPES}

    def final(f, seq):
        """[R, N, 3]: every re-sampling after the pushes seq [T, 4], by the planner dynamics f."""
        return jax.vmap(lambda p, m: f(p, m, seq)[-1])(pile, mask)

    finals = jax.jit(jax.vmap(final, (None, 0)))  # over the M sequences
    score = jax.jit(lambda f, seq: jnp.mean(jax.vmap(cost)(final(f, seq), mask)))
    predicted = {d: np.asarray(finals(dynamics[d], plans["float32"].actions)) for d in EDGE_DTYPES}
    error_mm = 1e3 * np.linalg.norm(predicted["bfloat16"] - predicted["float32"], axis=-1)
    bf16.update(quality_model=quality_name, prediction_mean_mm=float(error_mm.mean()),
                prediction_max_mm=float(error_mm.max()), float32_best_cost=float(plans["float32"].best_cost),
                best_cost_in_float32=float(score(dynamics["float32"], plans["bfloat16"].best)),
                best_cost=float(plans["bfloat16"].best_cost),
                initial_cost=float(jnp.mean(jax.vmap(cost)(pile, mask))))
    return f32, bf16, shipped


def _objective_disagreement(positions: np.ndarray, torch_objective_px) -> float:
    """max |c_torch - c_JAX| (pixels) over the unpushed piles [R, N, 3]: the peer scores what the planner scores."""
    import jax
    import jax.numpy as jnp

    from dynres_jax.control.objective import objective

    camera, goal = _camera_and_goal()
    ours = jax.vmap(lambda p: objective(p, jnp.ones(p.shape[0], bool), goal, camera))(jnp.asarray(positions))
    return float(np.max(np.abs(np.asarray(ours) - np.asarray(torch_objective_px))))


def run(quick: bool) -> dict:
    """The benchmark; a JSON-ready dict with the sizes, a ``torch`` and a ``jax`` section and the ratios."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # torch and JAX share the GPU in one process
    sizes = QUICK if quick else FULL
    positions = _piles(sizes["particles"], sizes["resamples"])
    result = dict(quick=quick, particles=sizes["particles"], samples=sizes["samples"], resamples=sizes["resamples"],
                  batch=sizes["samples"] * sizes["resamples"], horizon=1, steps=sizes["steps"],
                  speedup_goal=SPEEDUP_GOAL, plan_goal_s=PLAN_GOAL_S)
    try:
        import torch  # noqa: F401
    except ImportError:
        result["torch"] = dict(skipped="torch is not importable: the PyTorch reference was not run")
    else:
        t = result["torch"] = _torch_reference(positions, sizes["samples"], sizes["torch_repeats"])
        t["objective_max_abs_px"] = _objective_disagreement(positions, t["objective_px"])
        print(f"  torch reference ({t['device']}): {t['ms_per_step']:.2f} ms/step with c (coverage by "
              f"{t['coverage_distances']}; by coverage: "
              + ", ".join(f"{k} {v:.2f}" for k, v in t["ms_per_step_by_coverage"].items())
              + f"), {t['ms_per_step_network_only']:.2f} network only; its c is within "
              f"{t['objective_max_abs_px']:.2e} px of JAX's", flush=True)
    j, b, shipped = _jax_planner(positions, sizes["samples"], sizes["steps"], sizes["repeats"])
    result["jax"], result["jax_bf16"] = j, b
    result["jax_stages"] = _stage_times(positions, sizes["samples"], sizes["repeats"])
    print("  JAX stages (float32): " + ", ".join(f"{k[:-3]} {v:.2f} ms" for k, v in result["jax_stages"].items()),
          flush=True)
    sections = [("JAX", j), ("JAX, bfloat16 edges", b)]
    if shipped is not None:
        result["jax_shipped"] = shipped
        sections.append((f"JAX, {shipped['model']}", shipped))
    for name, x in sections:
        print(f"  {name} ({x['device']}): {x['ms_per_step']:.2f} ms/step, {x['steps']}-step plan {x['plan_s']:.3f} s, "
              f"compile {x['compile_s']:.1f} s", flush=True)
    print(f"  bfloat16 vs float32 ({b['quality_model']}): predictions {b['prediction_mean_mm']:.3f} mm mean, "
          f"{b['prediction_max_mm']:.3f} mm max; best cost {b['best_cost_in_float32']:.2f} px (scored in float32) vs "
          f"{b['float32_best_cost']:.2f} px, unpushed {b['initial_cost']:.2f} px", flush=True)
    result["plan_meets_goal"] = j["plan_s"] < PLAN_GOAL_S
    result["plan_bf16_meets_goal"] = b["plan_s"] < PLAN_GOAL_S
    if "ms_per_step" in result["torch"]:
        if shipped is not None:
            result["speedup_shipped"] = result["torch"]["ms_per_step"] / shipped["ms_per_step"]
        result["speedup"] = result["torch"]["ms_per_step"] / j["ms_per_step"]
        result["speedup_vs_network_only_peer"] = result["torch"]["ms_per_step_network_only"] / j["ms_per_step"]
        result["speedup_meets_goal"] = result["speedup"] >= SPEEDUP_GOAL
        result["speedup_bf16"] = result["torch"]["ms_per_step"] / b["ms_per_step"]
        result["speedup_bf16_meets_goal"] = result["speedup_bf16"] >= SPEEDUP_GOAL
    return result

