"""Suite-wide hygiene: each test module starts with JAX's compiled executables released, so a 2-core CI machine does
not carry hundreds of them (and their code memory) from one module into the next; and one persistent compilation
cache for the whole run (a fresh folder, removed at the end), so what one module, worker process or command
subprocess compiled the next loads instead of compiling again. On a 2-core CPU compiling is most of a test's time:
the task commands' tests ran in 74 s with a cold cache and 24 s with a warm one. A loaded executable is the one the
compiler wrote, so results do not change."""

import atexit
import os
import shutil
import tempfile

if "DYNRES_TEST_CACHE" not in os.environ:  # the first process of the run (pytest, or xdist's controller) makes it;
    _CACHE = tempfile.mkdtemp(prefix="dynres-jax-test-cache-")  # xdist's workers and commands' subprocesses inherit
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)  # the variable and share the one folder
    os.environ.update(DYNRES_TEST_CACHE=_CACHE, JAX_COMPILATION_CACHE_DIR=_CACHE,
                      JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1")

import jax  # noqa: E402  (after the cache settings, which JAX reads when it starts)
import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _fresh_compile_caches():
    jax.clear_caches()
    yield


@pytest.fixture(scope="session")
def script():
    """scripts/NAME.py loaded as a module: script(NAME), with scripts/ on the path as when it runs."""
    import importlib.util
    import sys

    folder = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scripts")

    def load(name: str):
        if folder not in sys.path:
            sys.path.insert(0, folder)
        spec = importlib.util.spec_from_file_location(name, os.path.join(folder, f"{name}.py"))
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
