"""Bad input is named before any work (issue: one model for every kind, bad input refused): piles too large for
the bin, damaged or missing checkpoints, unwritable output folders, impossible counts; and every kind's default pile
has the area of 100 coffee beans and fits its goals."""

import os

import jax
import numpy as np
import pytest
from flax import nnx

from dynres_jax.commands import evaluate, gather
from dynres_jax.config import DEFAULT_PIECES, KINDS, SceneConfig, SimConfig
from dynres_jax.control import tasks
from dynres_jax.control.planner import PlannerConfig
from dynres_jax.io import ckpt
from dynres_jax.learn.train import TrainConfig, card
from dynres_jax.models.dynamics import DynamicsConfig
from dynres_jax.models.registry import SHIPPED_DYNAMICS, build_model, load_dynamics, make_model
from dynres_jax.sim.env import PileEnv


def _env(kind, pieces):
    return PileEnv(SimConfig(scene=SceneConfig(kinds=(kind,), pieces=(pieces,))), backend="mujoco", render=False)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_every_kinds_default_pile_has_comparable_area_and_its_goals_fit(kind):
    env = _env(kind, DEFAULT_PIECES[kind])
    area = np.sum(np.pi * env.scene.footprint**2)
    coffee = np.sum(np.pi * _env("coffee", 100).scene.footprint**2)
    assert abs(area / coffee - 1) < 0.15, (kind, area, coffee)
    for seed in range(20):  # the largest discs too: FILL's upper end
        mask, info = tasks.gather_goal(np.random.default_rng(seed), env)
        assert mask.any() and abs(info["centre"][0]) + info["radius"] <= env.config.scene.bin_half_width
    assert tasks.redistribute_goal(np.random.default_rng(0), env, "U")[0].any()


def test_a_pile_too_large_for_the_bin_names_the_largest_that_fits():
    env = _env("almond", 100)  # the crash of issue 26: "high - low < 0" from deep inside NumPy
    largest = tasks.largest_pile(env.config.scene)
    assert 25 <= largest < 100
    with pytest.raises(ValueError, match=f"100 almond pieces need a goal disc wider .* at most {largest} fit"):
        tasks.gather_goal(np.random.default_rng(0), env)
    tasks.gather_goal(np.random.default_rng(0), _env("almond", largest))  # the named count works


def test_a_checkpoint_with_non_finite_weights_is_refused(tmp_path):
    cfg = TrainConfig(model=DynamicsConfig(hidden=4))
    model = make_model(cfg.model)
    model.predictor.layers[0].kernel[...] = model.predictor.layers[0].kernel[...].at[0, :3].set(np.nan)
    ckpt.save_module(str(tmp_path / "ckpt"), 1, model, card(cfg))
    with pytest.raises(ckpt.CheckpointError, match="3 parameter values are not finite"):
        ckpt.load_module(str(tmp_path / "ckpt"), build_model)


@pytest.fixture(scope="module")
def tiny_model():
    cfg = TrainConfig(model=DynamicsConfig(hidden=4))
    return cfg, make_model(cfg.model)


@pytest.mark.parametrize("edit, message", [
    (lambda c: c.pop("train"), "no train section"),
    (lambda c: c["train"].update(n_max="100"), "train.n_max must be a whole number in \\[1, 100\\]; got '100'"),
    (lambda c: c["train"].update(n_max=None), "train.n_max must be a whole number .* got None"),
    (lambda c: c["train"].update(n_max=0), "got 0"),
    (lambda c: c["dynamics"].update(k=0), "DynamicsConfig.k must be at least 1"),
    (lambda c: c["dynamics"].update(k=10**6), "DynamicsConfig.k must be at least 1 and at most 64, got 1000000"),
    (lambda c: c["dynamics"].update(hidden=10**5), "DynamicsConfig.hidden must be .* at most 4096"),
    (lambda c: c["dynamics"].update(edge_radius=-1.0), "DynamicsConfig.edge_radius must be positive"),
    (lambda c: c["dynamics"].update(length_scale=1e300), "DynamicsConfig.length_scale must be .* at most 1 m"),
    (lambda c: c["dynamics"].update(propagation_steps=0), "DynamicsConfig.propagation_steps must be at least 1"),
])
def test_a_sealed_card_is_read_not_trusted(tiny_model, tmp_path, edit, message):
    """A card edited and sealed again (its manifest matches) is refused in one line naming the field, before any
    planning: it was a KeyError, a TypeError, or a model planning with no edges or no message passing."""
    cfg, model = tiny_model
    meta = card(cfg)
    edit(meta)
    ckpt.save_module(str(tmp_path / "ckpt"), 1, model, meta)
    with pytest.raises(ckpt.CheckpointError, match=message) as refused:
        load_dynamics("learned", str(tmp_path / "ckpt"), 0.04)
    assert str(tmp_path / "ckpt") in str(refused.value) and "\n" not in str(refused.value)


def test_a_checkpoint_asked_for_by_name_is_never_replaced_by_the_heuristic(tmp_path, capsys):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        load_dynamics("auto", str(tmp_path / "typo"), 0.04)
    with pytest.raises(SystemExit):
        gather.main(["--ckpt", str(tmp_path / "typo"), "--out", str(tmp_path / "out")])
    assert "--ckpt: no checkpoint" in capsys.readouterr().err
    assert load_dynamics("auto", SHIPPED_DYNAMICS, 0.04).name.startswith("learned")


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc, where nobody creates folders")
def test_an_out_nobody_can_create_is_refused_before_the_episode(tmp_path, capsys):
    """Even as root (how CI runs): no folder can be made under /proc."""
    for main in (gather.main, evaluate.main):
        with pytest.raises(SystemExit) as exit_:
            main(["--out", "/proc/dynres-no-such/run"])
        assert exit_.value.code == 2 and "--out: cannot make" in capsys.readouterr().err


def test_the_default_model_still_loads(tmp_path):
    model, meta, _ = ckpt.load_module(SHIPPED_DYNAMICS, build_model)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(nnx.state(model)))


def test_characters_the_font_cannot_draw_are_refused():
    from dynres_jax.config import CameraConfig
    from dynres_jax.control.goals import text_goal
    from dynres_jax.sim.camera import Camera

    camera = Camera.top_down(CameraConfig())
    assert text_goal(camera, "J~", np.zeros(2), 0.08).any()
    with pytest.raises(ValueError, match=r"cannot draw \['é', 'ω'\]"):
        text_goal(camera, "éTω", np.zeros(2), 0.08)


@pytest.mark.parametrize("field, value, message", [
    ("K", [[1, 0, 0], [0, float("nan"), 0], [0, 0, 1]], "K must be finite numbers of shape"),
    ("centre", [0, 0], "centre must be finite numbers of shape"),
    ("rotation", "identity", "rotation must be"),
    ("width", 64.5, "whole pixels"),
    ("width", 100_000, r"outside \[8, 4096\]"),
])
def test_a_bad_camera_json_names_its_field(field, value, message):
    import json

    from dynres_jax.config import CameraConfig
    from dynres_jax.sim.camera import Camera

    good = json.loads(Camera.top_down(CameraConfig()).to_json())
    assert Camera.from_json(json.dumps(good)) == Camera.top_down(CameraConfig())
    with pytest.raises(ValueError, match=message):
        Camera.from_json(json.dumps({**good, field: value}).replace("NaN", "NaN"))


def test_absurd_image_sizes_are_refused_with_the_limit():
    from dynres_jax.config import CameraConfig
    from dynres_jax.control.goals import disc_goal, make_goal
    from dynres_jax.sim.camera import Camera

    with pytest.raises(ValueError, match=r"100000 x 128 pixels is outside \[8, 4096\]"):
        Camera.top_down(CameraConfig(width=100_000))
    cam = Camera.top_down(CameraConfig(width=32, height=32))
    with pytest.raises(ValueError, match=r"n_samples must be an int in \[1, 100000\], got 10000000"):
        make_goal(disc_goal(cam, (0.0, 0.0), 0.05), cam, 10**7)  # ran for minutes without a word


def _library_cases():
    """(call, message) pairs: the library's functions called with odd arguments (the 2026-11-29 audit: NumPy or JAX
    internals, or silently accepted)."""
    from dynres_jax import perception
    from dynres_jax.config import CameraConfig
    from dynres_jax.control.goals import disc_goal, make_goal, text_goal
    from dynres_jax.control.objective import objective
    from dynres_jax.control.task_env import TaskEnv
    from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics
    from dynres_jax.sim.camera import Camera, Observation

    cam = Camera.top_down(CameraConfig(width=32, height=32))
    goal = make_goal(disc_goal(cam, (0.0, 0.0), 0.08), cam)
    obs = Observation(np.ones((32, 32), np.float32), None, None, None)
    sample = lambda **kw: perception.sample_particles(obs, cam, kw.pop("omega", 4), jax.random.PRNGKey(0),  # noqa: E731
                                                      kw.pop("capacity", 16), **kw)
    return [
        (lambda: disc_goal(cam, [0, 0, 0], 0.05), r"disc centre must be a finite \(x, y\)"),
        (lambda: disc_goal(cam, [0, 0], "0.05"), "disc radius must be positive: one finite number, got '0.05'"),
        (lambda: disc_goal(cam, [0, 0], np.array([0.05, 0.06])), "disc radius must be positive"),
        (lambda: disc_goal(cam, [0, 0], 0.05, bin_half_width=float("nan")), "bin_half_width must be positive"),
        (lambda: text_goal(cam, "A", (0, 0, 1), 0.1), "text centre must be"),
        (lambda: objective(np.zeros((0, 3)), np.zeros(0, bool), goal, cam), r"positions must be \[N >= 1, 3\]"),
        (lambda: objective(np.zeros((5, 2)), np.ones(5, bool), goal, cam), r"positions must be \[N >= 1, 3\]"),
        (lambda: sample(omega=np.array([4, 8])), "omega must be one count of particles"),
        (lambda: sample(kind="pebble"), "kind must be a piece kind's index"),
        (lambda: sample(margin=float("nan")), "margin must be a finite number >= 0"),
        (lambda: sample(margin=-0.5), "margin must be a finite number >= 0"),
        (lambda: sample(r_center=-1.0), "r_center must be a finite number >= 0"),
        (lambda: sample(capacity=10**7), r"capacity must be an int in \[1, 4096\]"),
        (lambda: load_dynamics("sweep", SHIPPED_DYNAMICS, -0.04), "plate_half_width must be a positive number"),
        (lambda: load_dynamics("learned", SHIPPED_DYNAMICS, 0.04).dynamics(float("nan")),  # a NaN push before
         "radius must be the particles' spacing, a positive number of metres"),
        (lambda: load_dynamics("sweep", SHIPPED_DYNAMICS, float("nan")), "plate_half_width must be a positive"),
        (lambda: TaskEnv(episode_length=2.5), "episode_length must be a whole number"),
    ]


def test_the_library_names_an_odd_argument_before_any_work():
    """Each call, with one argument of the wrong shape, type or value, is a ValueError naming that argument (they
    were NumPy or JAX internals, a ZeroDivisionError, or silently accepted); the same calls with good arguments
    work (the disc and the sweep model are built, so the checks are not refusing everything)."""
    for call, message in _library_cases():
        with pytest.raises(ValueError, match=message):
            call()
    from dynres_jax.config import CameraConfig
    from dynres_jax.control.goals import disc_goal
    from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics
    from dynres_jax.sim.camera import Camera

    assert disc_goal(Camera.top_down(CameraConfig(width=32, height=32)), [0.0, 0.0], np.float32(0.05)).any()
    assert load_dynamics("sweep", SHIPPED_DYNAMICS, 0.04).name == "sweep heuristic"


def test_a_number_flag_says_finite_without_infinite_bounds():
    import argparse

    from dynres_jax.commands import checks

    with pytest.raises(argparse.ArgumentTypeError, match=r"^expected a finite number, got nan$"):
        checks.number()("nan")
    with pytest.raises(argparse.ArgumentTypeError, match=r"expected a finite number in \[0, 1\], got 2"):
        checks.number(0, 1)("2")


@pytest.mark.parametrize("make, message", [
    (lambda: PlannerConfig(samples=2.5), "PlannerConfig.samples must be an int, got 2.5"),
    (lambda: PlannerConfig(lr=float("nan")), "PlannerConfig.lr must be a finite number"),
    (lambda: SceneConfig(bin_half_width="0.2"), "SceneConfig.bin_half_width must be a float"),
    (lambda: DynamicsConfig(push_frame=1), "DynamicsConfig.push_frame must be a bool"),
    (lambda: TrainConfig(steps=True), "TrainConfig.steps must be an int"),
    (lambda: SceneConfig(kinds="coffee", pieces=(10,)), "SceneConfig.kinds must be a tuple of strs, got 'coffee'"),
    (lambda: SceneConfig(pieces=(10.0,)), r"SceneConfig.pieces\[0\] must be an int, got 10.0"),
    (lambda: SceneConfig(pieces=(True,)), r"SceneConfig.pieces\[0\] must be an int, got True"),
])
def test_the_python_api_names_a_field_of_the_wrong_type(make, message):
    with pytest.raises((TypeError, ValueError), match=message):
        make()


@pytest.mark.parametrize("platforms, message", [("bogus", "Unable to initialize backend 'bogus'"),
                                                ("cuda" if jax.default_backend() == "cpu" else "tpu",
                                                 "cannot start")])
def test_a_platform_jax_cannot_start_is_one_line_naming_jax_platforms(tmp_path, platforms, message):
    """JAX_PLATFORMS naming an unknown platform, or one with no plugin here, was a raw RuntimeError or a bare
    AssertionError from JAX's backend setup; now one line naming the variable, exit status 2, no folder made."""
    import subprocess
    import sys

    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "experiments.gather", "--mpc-steps", "1", "--out", str(out)],
                          env={**os.environ, "JAX_PLATFORMS": platforms}, capture_output=True, text=True, timeout=300,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2, done.stderr[-2000:]
    assert len(lines) == 1 and f"error: JAX_PLATFORMS='{platforms}'" in lines[0] and message in lines[0], lines
    assert not out.exists()


@pytest.mark.parametrize("variable", ["JAX_DEFAULT_MATMUL_PRECISION", "JAX_ENABLE_X64"])
def test_a_jax_environment_variable_jax_cannot_read_is_one_line(tmp_path, variable):
    """JAX_DEFAULT_MATMUL_PRECISION=bogus (an enum) or JAX_ENABLE_X64=bogus (a truth value) was JAX's traceback on
    import; now one line naming the variable, exit 2."""
    import subprocess
    import sys

    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "experiments.gather", "--out", str(out)],
                          env={**os.environ, variable: "bogus"}, capture_output=True, text=True,
                          timeout=300, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1, done.stderr[-2000:]
    assert f"the environment variable {variable}" in lines[0] and not out.exists()


def test_a_closed_standard_output_ends_a_command_quietly():
    """`... | head -c 0`: a command whose stdout closes ends with status 1 and nothing on stderr (was a BrokenPipeError
    traceback), as Unix tools do."""
    import subprocess
    import sys

    code = ("from dynres_jax.commands import checks\n"
            "@checks.guarded('x')\n"
            "def main(argv):\n"
            "    for _ in range(100000):\n"
            "        print('step ' * 20, flush=True)\n"
            "main()\n")
    done = subprocess.run(f"{sys.executable} -c \"{code}\" | head -c 10", shell=True, capture_output=True, text=True,
                          timeout=120)
    assert done.stdout == "step step ", done.stdout
    assert done.stderr == "", done.stderr[-2000:]


def test_a_full_disk_is_one_line_whatever_wrapped_it(capsys):
    """ENOSPC raised under another exception (as orbax and NumPy wrap it) ends a command with one line naming the
    file and how to go on, status 1; any other error still propagates as itself."""
    import errno

    from dynres_jax.commands import checks

    def failing(error):
        @checks.guarded("train_dynamics")
        def main(argv):
            try:
                raise OSError(errno.ENOSPC, "No space left on device", "/data/run/ckpt/1500/x")
            except OSError as e:
                raise error from e
        return main

    with pytest.raises(SystemExit) as ended:
        failing(RuntimeError("orbax: save failed"))([])
    err = capsys.readouterr().err
    assert ended.value.code == 1 and "Traceback" not in err
    assert err.strip().splitlines() == ["python -m experiments.train_dynamics: error: No space left on device writing "
                                        "'/data/run/ckpt/1500/x'; free space and rerun the same command"]
    with pytest.raises(ValueError, match="another"):  # not a full disk: the error itself
        checks.guarded("train_dynamics")(lambda argv: (_ for _ in ()).throw(ValueError("another")))([])
