"""Resolution buckets and the planner's time budget: what makes a coarse ω cheaper than a fine one.

Buckets. Perception, the model and the planner run at a static particle capacity: the smallest bucket that holds ω
(``bucket_for``; default ``BUCKETS``). Inside a bucket ω stays a traced prefix mask, so one compiled function serves
every ω of the bucket and ``jax.vmap`` over them still works; a run compiles at most one decision per bucket it
visits. Padding is inert: a plan at ω in a small bucket equals the same plan in a larger one (tests/test_budget.py).

Time budget. ``TimingTable`` holds, per bucket and for one device and planner batch, the seconds a decision spends
outside the Adam steps (``fixed_s``: perception, sampling the pushes, scoring the last ones) and the seconds of one
Adam step (``step_s``). ``measure`` fills it after compiling, from the wall time of decisions of two step counts;
``TimingTable.refine`` updates a bucket's step time from the decisions a run makes. ``adam_steps`` is the one
budget function: the Adam steps a decision at a bucket runs under a budget in seconds (or the plain count when
there is no budget). A table saved beside the labels or evaluation it drove (``save``, ``--timing FILE``) re-derives
their step counts on any machine.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import jax

from dynres_jax.config import OMEGA_MAX
from dynres_jax.io import files

BUCKETS = (16, 32, 50, 75, OMEGA_MAX)  # particle capacities; the last is OMEGA_MAX, so ω = OMEGA_MAX pads nothing.
# 50 and 75, not 64: at 64 slots, the model's channel count, XLA strides the exact sums' scatter and an Adam step cost
# 0.98 of bucket 100's on an H200; at 50 it costs 0.55 (docs/repeat, "It is the size 64, not the ω")
REFINE_WEIGHT = 0.5  # weight of a decision's own step time when a table is refined from it
REFINE_CLIP = 2.0  # a decision's own step time counts within [1/2, 2] x the table's (one slow outlier moves it little)


def check_buckets(buckets: Sequence[int]) -> tuple[int, ...]:
    """buckets as a strictly increasing tuple of positive ints, or a ValueError naming the problem."""
    out = tuple(buckets)
    if not out or any(not isinstance(b, int) or isinstance(b, bool) or b < 1 for b in out):
        raise ValueError(f"buckets must be positive ints, got {buckets!r}")
    if any(a >= b for a, b in zip(out, out[1:], strict=False)):
        raise ValueError(f"buckets must be strictly increasing, got {buckets!r}")
    return out


def bucket_for(omega: int, buckets: Sequence[int] = BUCKETS) -> int:
    """The smallest bucket holding ω particles. ValueError when ω < 1 or ω exceeds the largest bucket."""
    if int(omega) != omega or omega < 1:
        raise ValueError(f"omega must be a positive integer, got {omega!r}")
    for b in buckets:
        if omega <= b:
            return int(b)
    raise ValueError(f"omega={omega} exceeds the largest resolution bucket {buckets[-1]} (buckets {tuple(buckets)})")


@dataclass
class TimingTable:
    """Seconds per decision, per bucket, on one device at one planner batch.

    device: where it was measured (``jax.devices()[0]``); samples, horizon: the planner batch (M, T) it holds for;
    fixed_s, step_s: {bucket: s}, a decision takes fixed_s + steps × step_s; refined: decisions it was refined from;
    frozen: loaded from a file to reproduce a run, so ``refine`` leaves it as it is; by_omega: the keys are ω, not
    buckets, so each ω has its own price whatever bucket it runs in (the reference's pricing)."""

    device: str
    samples: int
    horizon: int
    fixed_s: dict[int, float]
    step_s: dict[int, float]
    refined: dict[int, int] = field(default_factory=dict)
    frozen: bool = False
    by_omega: bool = False

    def __post_init__(self):
        self.fixed_s = {int(b): float(s) for b, s in self.fixed_s.items()}
        self.step_s = {int(b): float(s) for b, s in self.step_s.items()}
        self.refined = {int(b): int(n) for b, n in self.refined.items()}
        if set(self.fixed_s) != set(self.step_s):
            raise ValueError(f"timing table: fixed_s has buckets {sorted(self.fixed_s)}, step_s {sorted(self.step_s)}")
        bad = {b: s for b, s in self.step_s.items() if not (math.isfinite(s) and s > 0)}
        bad |= {b: s for b, s in self.fixed_s.items() if not (math.isfinite(s) and s >= 0)}
        if bad:
            raise ValueError(f"timing table: times must be finite, step_s > 0 and fixed_s >= 0; got {bad}")

    @property
    def buckets(self) -> tuple[int, ...] | None:
        """The buckets the table prices, None where it prices by ω."""
        return None if self.by_omega else tuple(sorted(self.step_s))

    def key(self, omega: int, buckets: Sequence[int]) -> int:
        """What a decision at ``omega`` is priced by: ω where the table prices by ω, else its bucket in ``buckets``."""
        return int(omega) if self.by_omega else bucket_for(int(omega), buckets)

    def seconds(self, bucket: int, steps: int) -> float:
        """The predicted wall time (s) of a decision of ``steps`` Adam steps at ``bucket``."""
        self._check(bucket)
        return self.fixed_s[bucket] + steps * self.step_s[bucket]

    def steps(self, bucket: int, seconds: float, max_steps: int) -> int:
        """The Adam steps that fit a decision at ``bucket`` into ``seconds``: floor((seconds - fixed) / step), clipped
        to [0, max_steps]."""
        self._check(bucket)
        fit = (seconds - self.fixed_s[bucket]) / self.step_s[bucket]
        return int(max_steps) if fit >= max_steps else max(math.floor(fit), 0)

    def refine(self, bucket: int, steps: int, seconds: float) -> None:
        """Update ``bucket``'s step time from a decision of ``steps`` steps that took ``seconds`` (no-op when frozen,
        for zero steps, or when the decision took less than the fixed time)."""
        self._check(bucket)
        if self.frozen or steps < 1 or seconds <= self.fixed_s[bucket]:
            return
        own = (seconds - self.fixed_s[bucket]) / steps
        own = min(max(own, self.step_s[bucket] / REFINE_CLIP), self.step_s[bucket] * REFINE_CLIP)
        self.step_s[bucket] = (1 - REFINE_WEIGHT) * self.step_s[bucket] + REFINE_WEIGHT * own
        self.refined[bucket] = self.refined.get(bucket, 0) + 1

    def _check(self, bucket: int) -> None:
        if bucket not in self.step_s:
            raise ValueError(f"the timing table has no bucket {bucket} (it holds {sorted(self.step_s)}); measure it "
                             "with the run's buckets")

    def to_json(self) -> dict:
        out = asdict(self)
        out.pop("frozen")
        return out

    def save(self, path: str) -> None:
        """Write the table as JSON, atomically."""
        files.write_json(path, self.to_json())

    @classmethod
    def load(cls, path: str, *, frozen: bool = True) -> TimingTable:
        """A table saved by ``save``; frozen (not refined) by default, so a run reproduces the step counts."""
        with open(path) as f:
            data = json.load(f)
        missing = {"device", "samples", "horizon", "fixed_s", "step_s"} - set(data)
        if missing:
            raise ValueError(f"{path} is not a timing table: it lacks {sorted(missing)}")
        for name in ("samples", "horizon"):
            if isinstance(data[name], bool) or not isinstance(data[name], int):
                raise ValueError(f"{path}: {name} must be an integer, got {data[name]!r}")
        return cls(**data, frozen=frozen)


def reference_step_s(omega: int) -> float:
    """The reference's price of one Adam step at ω particles (s): the quadratic its planner fitted to its own step
    times (planners.py, ``particle_num_to_iter_time``: 11, 20, 40 and 72 ms at ω = 25, 50, 75 and 100, whole ms), at
    least 1 ms."""
    return max(int((2969.3971 - 69.923244 * omega + 1.8509846 * omega**2) / 200.0), 1) / 1000.0


def reference_table(buckets: Sequence[int], samples: int, horizon: int) -> TimingTable:
    """A timing table in the reference's pricing: no fixed part, the Adam step of a decision at ω priced at
    ``reference_step_s(ω)`` whatever bucket it runs in (the reference has no buckets), for every ω up to the largest
    bucket; frozen, so no run refines it."""
    omegas = range(1, max(check_buckets(buckets)) + 1)
    return TimingTable("reference (the authors' fitted step time)", samples, horizon, {w: 0.0 for w in omegas},
                       {w: reference_step_s(w) for w in omegas}, frozen=True, by_omega=True)


def adam_steps(key: int, max_steps: int, seconds: float | None = None, table: TimingTable | None = None) -> int:
    """The one budget function: the Adam steps a decision priced by ``key`` (``TimingTable.key``: its bucket, or its ω)
    runs. No budget (seconds None): max_steps. A budget of ``seconds`` per decision: as many steps as ``table`` says
    fit, at most max_steps."""
    if seconds is None:
        return int(max_steps)
    if table is None:
        raise ValueError("a time budget needs a timing table (budget.measure, or --timing FILE)")
    return table.steps(key, seconds, max_steps)


def measure(decide: Callable[[int, int], object], buckets: Sequence[int], *, samples: int, horizon: int,
            max_steps: int, repeats: int = 3, log: Callable[[str], None] = print) -> TimingTable:
    """Fill a timing table on this device. decide(bucket, steps) runs one whole decision (perception and plan) and
    returns its result; it is compiled first (untimed), then timed ``repeats`` times (medians) at 0 steps (fixed_s)
    and at a probe of 10 steps, then 4 times as many, until the steps take at least as long as the fixed part (or
    the probe reaches max_steps): step_s from the difference. samples, horizon: the planner batch; log: one line per
    bucket as it starts (a CPU takes tens of seconds a bucket)."""
    fixed, step = {}, {}

    def wall(bucket, steps):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(decide(bucket, steps))
            times.append(time.perf_counter() - t0)
        return statistics.median(times)

    buckets = check_buckets(buckets)
    for i, b in enumerate(buckets):
        log(f"timing table: bucket {b} ({i + 1} of {len(buckets)}): compiling its decision, then timing it")
        jax.block_until_ready(decide(b, 0))  # compile (the step count is traced: one compile serves every count)
        short = wall(b, 0)
        probe = min(10, max_steps)
        while True:
            long = wall(b, probe)
            if long - short >= max(short, 1e-3) or probe >= max_steps:
                break
            probe = min(4 * probe, max_steps)
        fixed[b], step[b] = short, max((long - short) / probe, 1e-9)
    device = jax.local_devices()[0]
    return TimingTable(f"{device.platform}: {device.device_kind}", samples, horizon, fixed, step)


__all__ = ["BUCKETS", "TimingTable", "adam_steps", "bucket_for", "check_buckets", "measure", "reference_step_s",
           "reference_table"]
