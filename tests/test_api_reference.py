"""The API reference builds from the docstrings with the README's own pdoc line (its brace list expanded as bash
would): every public module of the library it names gets a page, and the names a reader of the paper looks up are
documented on theirs."""

import importlib
import pkgutil
import re

import pytest
from test_readme_commands import README

pytestmark = pytest.mark.slow  # pdoc imports every module: CI's second tier


def readme_modules() -> list[str]:
    """The modules of the README's ``pdoc ... -o out/api`` line, ``a.{b,c}`` expanded to ``a.b a.c``."""
    line = re.search(r"`pdoc (.*?) -o out/api`", README).group(1)
    names = []
    for word in line.split():
        m = re.fullmatch(r"(.*)\{(.*)\}", word)
        names += [m.group(1) + part for part in m.group(2).split(",")] if m else [word]
    return names


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    import pdoc

    folder = tmp_path_factory.mktemp("api")
    pdoc.pdoc(*readme_modules(), output_directory=folder)
    return folder


def test_every_public_library_module_has_a_page(reference):
    """Every module under the named packages, without the command line (commands/, documented by --help)."""
    names = readme_modules()
    modules = set()
    for name in names:
        module = importlib.import_module(name)
        modules.add(name)
        if hasattr(module, "__path__") and name != "dynres_jax":
            modules |= {m.name for m in pkgutil.walk_packages(module.__path__, name + ".")}
    modules = sorted(m for m in modules if not any(part.startswith("_") for part in m.split(".")))
    assert len(modules) >= 45 and "dynres_jax.control.planner" in modules
    missing = [m for m in modules if not (reference / (m.replace(".", "/") + ".html")).exists()]
    assert missing == []


@pytest.mark.parametrize("module, names", [
    ("dynres_jax.control.planner", ["plan", "PlannerConfig"]),
    ("dynres_jax.control.objective", ["objective", "distribution_distance", "inside_share"]),
    ("dynres_jax.control.goals", ["make_goal", "with_objective"]),
    ("dynres_jax.perception", ["sample_particles"]),
    ("dynres_jax.control.tasks", ["TASKS", "first_steps", "stopped"]),
])
def test_the_papers_names_are_documented(reference, module, names):
    page = (reference / (module.replace(".", "/") + ".html")).read_text()
    for name in names:
        assert f'id="{name}"' in page, (module, name)
