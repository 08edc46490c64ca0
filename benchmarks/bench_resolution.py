"""Resolution benchmark: the cost of one Adam step at each ω in its bucket (``budget.bucket_for``), against the same
ω padded to 100 slots (how every ω was planned before buckets), measured in the same run.

    python -m experiments.benchmark resolution --json F

Batch: on a GPU the reference's 1,500 candidates (M = 50 pushes x R = 30 re-samplings); on a CPU the task commands'
50 (M = 50, R = 1); ``--batch benchmark|task`` chooses. Model: the shipped checkpoint (float32), cost: c on the
planner benchmark's disc goal, its samples cut to the bucket as ``decision.goal_cost`` cuts them. A step's time is the
difference of the median wall times of plans of N and N / 10 steps over 0.9 N, which removes a call's fixed cost.
Result keys: ``ms_per_step`` (ω -> ms, in its bucket), ``ms_per_step_padded`` (ω -> ms, padded to 100),
``ratio_25_100`` and ``ratio_10_100`` (ms at ω = 25 and 10 over ms at ω = 100).
"""

from __future__ import annotations

import time

import numpy as np

OMEGAS = (10, 25, 50, 75, 100)
BATCHES = dict(benchmark=(50, 30), task=(50, 1))  # (M, R)
RATIO_GOAL = 0.35  # the target: a step at ω = 25 at most this share of one at ω = 100
FULL = dict(steps=200, repeats=5)
CPU = dict(steps=40, repeats=3)
QUICK = dict(steps=4, repeats=2)


def _ms_per_step(dynamics, cost, positions, mask, config, steps: int, repeats: int) -> float:
    """ms per Adam step of ``planner.plan`` on positions [R, N, 3] with mask [R, N]: (median at ``steps`` - median at
    steps // 10) / the step difference; the compiling call is not timed (the step count is traced: one compile)."""
    import jax

    from benchmarks.bench_planner import _median_s
    from dynres_jax.control.planner import plan

    key = jax.random.PRNGKey(0)

    def call(n):
        return lambda: jax.block_until_ready(plan(dynamics, cost, positions, mask, key, config, adam_steps=n))

    short = max(1, steps // 10)
    call(short)()  # compile
    walls = [_median_s(call(n), repeats, lambda: None) for n in (short, steps)]
    return 1e3 * (walls[1] - walls[0]) / (steps - short)


def run(quick: bool, batch: str | None = None) -> dict:
    """The benchmark on the device JAX sees -> a JSON-ready dict (module docstring)."""
    import jax

    from benchmarks.bench_planner import PARTICLE_RADIUS, _camera_and_goal, _piles
    from dynres_jax.control.budget import bucket_for
    from dynres_jax.control.decision import goal_cost
    from dynres_jax.control.planner import PlannerConfig
    from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics

    device = jax.devices()[0]
    batch = batch or ("task" if device.platform == "cpu" else "benchmark")
    samples, resamples = BATCHES[batch]
    sizes = QUICK if quick else CPU if device.platform == "cpu" else FULL
    if quick:
        samples, resamples = 4, min(resamples, 2)
    camera, goal = _camera_and_goal()
    dynamics, _, name = load_dynamics("auto", SHIPPED_DYNAMICS, 0.04)
    dynamics = dynamics(PARTICLE_RADIUS)
    config = PlannerConfig(samples=samples, resamples=resamples, adam_steps=sizes["steps"])
    t0 = time.perf_counter()
    def ms_at(omega, slots):  # ms per step of ω valid particles in ``slots`` slots
        positions = _piles(slots, resamples, seed=omega)
        mask = np.broadcast_to(np.arange(slots) < omega, (resamples, slots))
        return _ms_per_step(dynamics, goal_cost(goal, camera, slots), positions, mask, config, sizes["steps"],
                            sizes["repeats"])

    ms, padded = {}, {}
    for omega in OMEGAS:
        ms[omega] = ms_at(omega, bucket_for(omega))
        padded[omega] = ms[omega] if bucket_for(omega) == 100 else ms_at(omega, 100)  # bucket 100: the same plan
        print(f"  ω = {omega:3d}: {ms[omega]:8.3f} ms/step in bucket {bucket_for(omega):3d}, "
              f"{padded[omega]:8.3f} padded to 100", flush=True)
    result = dict(device=f"{device.platform}: {device.device_kind}", jax_version=jax.__version__, quick=quick,
                  batch=batch, samples=samples, resamples=resamples, candidates=samples * resamples,
                  steps=sizes["steps"], repeats=sizes["repeats"], model=name,
                  buckets={w: bucket_for(w) for w in OMEGAS}, ms_per_step=ms, ms_per_step_padded=padded,
                  ratio_25_100=ms[25] / ms[100], ratio_10_100=ms[10] / ms[100], ratio_goal=RATIO_GOAL,
                  seconds=time.perf_counter() - t0)
    result["meets_goal"] = result["ratio_25_100"] <= RATIO_GOAL
    print(f"  {result['device']}, {result['candidates']} candidates: ratio ω=25 / ω=100 = "
          f"{result['ratio_25_100']:.3f} (goal <= {RATIO_GOAL}), ω=10 / ω=100 = {result['ratio_10_100']:.3f}",
          flush=True)
    return result


def table(result: dict) -> str:
    """Markdown table of a resolution benchmark result."""
    lines = [f"Device: {result['device']} (JAX {result['jax_version']}); {result['candidates']:,} candidates "
             f"({result['samples']} pushes x {result['resamples']} re-samplings); {result['model']}.", "",
             "| ω | bucket | ms per Adam step | padded to 100 | bucket / padded | / ω = 100 |",
             "|---:|---:|---:|---:|---:|---:|"]
    top = result["ms_per_step"][100]
    for w, m in result["ms_per_step"].items():
        p = result["ms_per_step_padded"][w]
        lines.append(f"| {w} | {result['buckets'][w]} | {m:.3f} | {p:.3f} | {m / p:.2f} | {m / top:.2f} |")
    return "\n".join(lines)
