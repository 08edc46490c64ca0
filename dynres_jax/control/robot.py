"""A robot's closed loop: frames from a camera, one planned push at a time to an arm, until the pile is in the goal.

Two small protocols are all a setup implements: a ``FrameSource`` (its ``camera`` and ``read() -> Observation``: depth
[H, W] m, colour [H, W, 3] uint8; the kind and segmentation images unknown, -1) and a ``Pusher`` (``push(action)``:
move the plate from (x_start, y_start) to (x_end, y_end), m in the table frame, and return when it is lifted again).
Shipped: ``ReplaySource`` (frames saved in a folder), ``SimulatedRobot`` (the simulator as camera and arm, its frames
through a depth camera's profile) and ``DryRun`` (a pusher that moves nothing). A RealSense and an arm, for example:

    class RealSense:                                   # pip install pyrealsense2
        def __init__(self, camera):                    # camera: io.frames.load_camera("cam.json"), calibrated
            self.camera, self.pipe = camera, rs.pipeline(); self.pipe.start()
        def read(self):
            f = rs.align(rs.stream.color).process(self.pipe.wait_for_frames())
            depth = (np.asarray(f.get_depth_frame().get_data()) / 1000.0).astype(np.float32)  # mm -> m; 0 or NaN:
            # no reading, as every path reads a frame (sim.sensor.is_reading)
            unknown = np.full(depth.shape, -1, np.int32)
            return Observation(depth, unknown, unknown, np.asarray(f.get_color_frame().get_data()))

    class Arm:
        def push(self, action):                        # plate down at the start, along, up at the end
            x0, y0, x1, y1 = action; arm.move_to(x0, y0, z_up); arm.move_to(x0, y0, z_push); ...

``run_robot`` perceives each frame (as a real camera's with ``MPCConfig.real_depth``), plans one push with
the dynamics model as a chooser orders (fixed ω, the regressor g, the probe: ``mpc.propose``, warm-started from the
last plan), checks it against the workspace
before sending it (``Workspace.check``), and stops when the share of foreground pixels inside the goal reaches
``success`` or after ``MPCConfig.mpc_steps`` pushes. What the robot sees is all it knows: d and the share inside are
measured on its frames.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.control.budget import TimingTable
from dynres_jax.control.choosers import Chooser, FixedOmega
from dynres_jax.control.decision import Situation, batch
from dynres_jax.control.goals import Goal, make_goal
from dynres_jax.control.keep import best_rate
from dynres_jax.control.mpc import MPCConfig, Progress, announce, propose, shift
from dynres_jax.control.objective import distribution_distance, seen_inside
from dynres_jax.errors import InputError
from dynres_jax.io.files import check_input
from dynres_jax.io.frames import load_frame
from dynres_jax.perception import calibrate, foreground
from dynres_jax.sim import pushes
from dynres_jax.sim.camera import Camera, Observation

STOP_SHARE = 0.97  # stop at this share of the frame's foreground inside the goal: a depth camera's share reads
# 2.8 ± 1.3 points above the pieces' own (64 simulated RealSense episodes, docs/robot), so stopping at the 0.9 that
# success asks of the pieces left 83 % of episodes just short of it


class FrameSource(Protocol):
    """A camera: ``camera`` (intrinsics and pose in the table frame) and ``read()``, the next frame (None when it has
    no more: a replay's end, where the loop stops)."""

    camera: Camera

    def read(self) -> Observation | None: ...


class Pusher(Protocol):
    """An arm: ``push(action [4] m)`` executes one push and returns when the plate is lifted."""

    def push(self, action: np.ndarray) -> None: ...


class UnsafePush(RuntimeError):
    """A push outside the workspace; never sent."""


@dataclass(frozen=True)
class Workspace:
    """Where pushes may go (``sim.pushes``' action space): ends within ±bound m, starts there or at ±reach (outside a
    wall; None: a table without walls), lengths in [min_length, max_length] m."""

    bound: float
    min_length: float
    max_length: float
    reach: float | None = None

    @classmethod
    def of(cls, env) -> Workspace:
        """The workspace of a ``PileEnv``'s bin."""
        p = env.config.push
        return cls(env.action_bound, p.min_length, p.max_length, env.reach)

    def check(self, action) -> np.ndarray:
        """action [4] m, as float32, or UnsafePush naming the problem: not finite, or not a push of this action
        space (projecting it moves it by more than 0.1 mm)."""
        a = np.asarray(action, np.float32)
        if a.shape != (4,) or not np.all(np.isfinite(a)):
            raise UnsafePush(f"push {a.tolist()} is not four finite numbers; not sent")
        fixed = np.asarray(pushes.project(jnp.asarray(a), self.bound, self.min_length, self.max_length, self.reach))
        if np.max(np.abs(fixed - a)) > 1e-4:
            raise UnsafePush(f"push {np.round(a, 4).tolist()} leaves the workspace (ends within ±{self.bound:.3f} m, "
                             f"starts there or at ±{self.reach} m, lengths {self.min_length}-{self.max_length} m); "
                             "not sent")
        return a


class ReplaySource:
    """Frames saved in ``folder``, one sub-folder per frame in name order, each as ``io.frames.save_frame`` writes
    them (depth.png in mm, rgb.png, camera.json); the camera is the first frame's. Every frame is read here, so a
    damaged one is an InputError before any planning, not after the frames before it."""

    def __init__(self, folder: str):
        check_input(folder, "replay folder", expect=("folder",))
        names = sorted(n for n in os.listdir(folder) if os.path.isfile(os.path.join(folder, n, "depth.png")))
        if not names:
            raise InputError(f"replay folder {folder!r} holds no frame (sub-folders with depth.png, rgb.png and "
                             "camera.json, as io.frames.save_frame writes them)")
        read = [load_frame(*(os.path.join(folder, name, n) for n in ("depth.png", "rgb.png", "camera.json")))
                for name in names]
        self.frames, self.camera, self.next = [obs for obs, _ in read], read[0][1], 0

    def read(self) -> Observation | None:
        """The next frame, or None after the last (the replay ends there, as its recording did)."""
        if self.next >= len(self.frames):
            return None
        self.next += 1
        return self.frames[self.next - 1]


class DryRun:
    """A pusher that moves nothing: it keeps the pushes it was sent (``pushes``)."""

    def __init__(self):
        self.pushes: list[list[float]] = []

    def push(self, action) -> None:
        self.pushes.append(np.asarray(action, np.float64).tolist())


class SimulatedRobot:
    """The simulator as camera and arm: one C MuJoCo ``PileEnv`` world from ``key``, its frames through ``sensor``
    (``sim.sensor.DepthSensor``; None: exact depth) with the camera the sensor believes in, its plate executing the
    pushes. ``state`` is the true world (for scoring what the robot cannot see)."""

    def __init__(self, env, key, sensor=None):
        self.env, self.sensor, self.key = env, sensor, key
        self.state = env.reset(key)
        self.camera = env.camera if sensor is None else sensor.believed_camera(env.camera)
        self.frames = 0

    def read(self) -> Observation:
        obs = self.peek()
        self.frames += 1
        return obs

    def peek(self) -> Observation:
        """The frame the next ``read`` returns, without reading it (its sensor's noise drawn from the frame count)."""
        obs = self.state.obs
        return obs if self.sensor is None else self.sensor.observe(obs, jax.random.fold_in(self.key, self.frames + 1))

    def push(self, action) -> None:
        self.state = self.env.push(self.state, np.asarray(action, np.float32))


def seen_scores(obs: Observation, goal: Goal, camera: Camera, real_depth: bool) -> tuple[float, float]:
    """What a camera can tell of the goal, from the frame's foreground (computed once): d (px) and the share of
    foreground pixels that lie on goal pixels."""
    _, valid = foreground(obs, camera, real_depth=real_depth)
    valid = jnp.reshape(valid, (camera.height, camera.width))
    return float(distribution_distance(valid, goal, camera)), float(seen_inside(valid, goal, camera))


def run_robot(source: FrameSource, pusher: Pusher, goal_mask, dynamics, cfg: MPCConfig,
              chooser: int | Callable[[Goal], Chooser], key, *, workspace: Workspace,
              bin_size: tuple[float, float] | None = None, success: float = STOP_SHARE,
              timing: TimingTable | None = None, on_step: Callable | None = None, log=print,
              resume: Progress | None = None, on_progress: Callable[[Progress], None] | None = None) -> list[dict]:
    """The loop: read a frame, stop if ``success`` of its foreground is inside the goal (or after cfg.mpc_steps
    pushes), else plan as the chooser orders, check the push against ``workspace`` and send it. chooser: ω (an int,
    ``FixedOmega``) or a function of the goal (a Goal batched [1]) returning any chooser that keeps by the model
    (``AdaptiveOmega``, ``ProbeOmega``) or by a judge (``judge.JudgeScored``); one whose orders need the simulator
    (the oracle, best of K) is refused at the first frame, before any push. bin_size: (bin_half_width, wall_height)
    m to refine the camera's pose from the first frame (``perception.calibrate``), None to trust it. timing: the
    table cfg.time_budget is spent by. on_step(t, obs, particles [n, 3] or None, record): per frame (GIF, saving).
    Returns one record per frame: step, distance (d on the frame, px), inside (share of foreground on the goal), and
    for a frame that was acted on: omega, action [4] m, predicted_objective, planning_s. resume: a ``Progress`` to
    go on from (its records and warm plan; the source then reads the frame after its last push); on_progress: called
    with the ``Progress`` after every push (its states None: the world is the source's)."""
    camera = source.camera
    obs = source.read()
    if obs is None:
        raise InputError("the frame source gave no frame to start from")
    if bin_size is not None:
        camera = calibrate(obs, camera, bin_half_width=bin_size[0], wall_height=bin_size[1])
        moved = 1000 * np.linalg.norm(np.asarray(camera.centre) - np.asarray(source.camera.centre))
        log(f"camera pose refined from the first frame: moved {moved:.1f} mm")
    goal = make_goal(np.asarray(goal_mask, bool), camera)
    chooser = FixedOmega(batch(goal), int(chooser)) if isinstance(chooser, int | np.integer) else chooser(batch(goal))
    init, warm, records = jnp.zeros((1, cfg.planner.horizon, 4), jnp.float32), False, []
    if resume is not None:
        records, init, warm = list(resume.records), jnp.asarray(resume.init, jnp.float32), resume.warm
    for t in range(len(records), cfg.mpc_steps + 1):
        distance, inside = seen_scores(obs, goal, camera, cfg.real_depth)
        record = dict(step=t, distance=distance, inside=inside)
        if record["inside"] >= success or t == cfg.mpc_steps:
            records.append(record)
            if on_step:
                on_step(t, obs, None, record)
            log(f"frame {t}: d={record['distance']:.2f}  inside={record['inside']:.0%}: "
                f"{'at the goal' if record['inside'] >= success else 'out of steps'}, stopping")
            return records
        orders = chooser(t, batch(obs))
        choose = getattr(orders.keep, "choose", None)  # a keep rule that chooses without worlds (the judge's)
        if choose is None and orders.keep != "rate" and (len(orders.candidates) > 1
                                                         or orders.candidates[0].proposals != "plan"):
            raise InputError(f"{type(chooser).__name__} keeps a push by pushing copies of the world; a robot has one "
                             "world: give a chooser that keeps by the model (fixed ω, AdaptiveOmega, ProbeOmega) or "
                             "a judge (JudgeScored)")
        for candidate in orders.candidates:
            announce(cfg, candidate.omega, log)
        t0 = time.perf_counter()
        now = Situation(None, batch(obs), camera, orders.goals, orders.kinds, batch(jax.random.fold_in(key, t)),
                        init, warm)
        plans = [propose(now, c, cfg=cfg, timing=timing, dynamics=dynamics) for c in orders.candidates]
        plan = best_rate(plans, timing) if choose is None else choose(plans[0], now)  # a judge orders one plan
        best = jnp.asarray(plan["proposals"][:, 0])
        action = workspace.check(np.asarray(best[0, 0]))
        record.update(omega=int(plan["omega"][0]), action=action.tolist(),
                      predicted_objective=float(plan["predicted_objective"][0]), planning_s=time.perf_counter() - t0)
        if on_step:
            particles = plan["particles"]
            on_step(t, obs, np.asarray(particles.positions[0])[np.asarray(particles.mask[0])], record)
        log(f"frame {t}: d={record['distance']:.2f}  inside={record['inside']:.0%}  ω={record['omega']}  push "
            f"{np.round(action.astype(np.float64), 3).tolist()}  plan {record['planning_s']:.2f}s")
        pusher.push(action)
        records.append(record)
        init, warm = shift(best), True
        if on_progress:
            on_progress(Progress(records, None, init, warm, np.zeros(1, bool)))
        obs = source.read()
        if obs is None:
            log(f"the source has no frame after push {t + 1}: stopping")
            return records
    return records
