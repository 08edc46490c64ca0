"""The package's shape holds: io/ is the low layer (nothing there imports control/, models/, learn/ or commands/),
control/ never asks what kind of worlds it pushes, and no module of the library grows past 400 lines."""

import ast
import pathlib
import re

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "dynres_jax"


def _imports(path: pathlib.Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return names


def test_io_imports_nothing_above_it():
    above = ("dynres_jax.control", "dynres_jax.models", "dynres_jax.learn", "dynres_jax.commands", "dynres_jax.export")
    for path in (PACKAGE / "io").glob("*.py"):
        bad = [m for m in _imports(path) if m.startswith(above)]
        assert not bad, f"{path.name} imports {bad}"


def test_control_never_asks_which_worlds_it_pushes():
    """No isinstance on a world type and no engine name read in control/: worlds are what ``sim.pool.Worlds`` says."""
    worlds = {"PileEnv", "WorldPool", "MJXPool", "EnvWorlds"}
    for path in (PACKAGE / "control").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "isinstance":
                named = {n.id for n in ast.walk(node.args[1]) if isinstance(n, ast.Name)}
                assert not named & worlds, f"{path.name}:{node.lineno} asks isinstance of {named & worlds}"
            if isinstance(node, ast.Attribute):
                assert node.attr != "backend", f"{path.name}:{node.lineno} reads an engine name"


def test_no_module_over_400_lines():
    long = {p.relative_to(PACKAGE).as_posix(): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 400}
    assert not long, long


def test_the_package_face_is_light_and_complete():
    """``import dynres_jax.config`` and ``dynres_jax.sim`` load neither OpenCV nor the control layer (the face imports
    on first use), and every name the face offers resolves to the object of its home module."""
    import subprocess
    import sys

    code = ("import sys, dynres_jax.config, dynres_jax.sim; "
            "print(sorted(m for m in ('cv2', 'dynres_jax.control', 'dynres_jax.learn') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr[-2000:]
    import importlib

    import dynres_jax
    from dynres_jax import _HOMES

    for name in dynres_jax.__all__:
        assert getattr(dynres_jax, name) is getattr(importlib.import_module(f"dynres_jax.{_HOMES[name]}"), name)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        dynres_jax.nothing  # noqa: B018


def test_engines_are_known_by_their_row_not_their_name():
    """Outside the table (``sim/engines.py``) and the physics (``sim/physics/``) no code compares a run's engine or
    physics name (``args.backend == "mujoco"``, ``env.backend in ("mjx", "warp")``): what a caller needs to know (host
    workers, one device, traced, capacities) is a field of the engine's row or of its physics, so a new engine is a
    row and a new physics a module, not a hunt for string comparisons."""
    pattern = re.compile(r"(args|config|cfg|env|self)\.backend\s*(==|!=|in\b)|"
                         r"backend\s*(==|!=)\s*\"(mujoco|mjx|mjx-fast|warp)\"")
    found = [f"{p.relative_to(PACKAGE)}:{i}" for p in PACKAGE.rglob("*.py")
             if p.name != "engines.py" and "physics" not in p.relative_to(PACKAGE).parts
             for i, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert not found, found
