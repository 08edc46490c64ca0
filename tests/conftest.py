"""Suite-wide hygiene: each test module starts with JAX's compiled executables released, so a 2-core CI machine does
not carry hundreds of them (and their code memory) from one module into the next; and one persistent compilation
cache for the whole run (a fresh folder, removed at the end), so what one module, worker process or command
subprocess compiled the next loads instead of compiling again. On a 2-core CPU compiling is most of a test's time:
the task commands' tests ran in 74 s with a cold cache and 24 s with a warm one. A loaded executable is the one the
compiler wrote, so results do not change. A DYNRES_TEST_CACHE set by the caller is used and kept (CI shares one
between its two tiers). And a line as each test file finishes (its tests, their seconds, the files done), so a long run
shows where it is."""

import atexit
import collections
import os
import shutil
import tempfile
import time

if "DYNRES_TEST_CACHE" not in os.environ:  # the first process of the run (pytest, or xdist's controller) makes it;
    _CACHE = tempfile.mkdtemp(prefix="dynres-jax-test-cache-")  # xdist's workers and commands' subprocesses inherit
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)  # the variable and share the one folder
    os.environ["DYNRES_TEST_CACHE"] = _CACHE
os.environ.update(JAX_COMPILATION_CACHE_DIR=os.environ["DYNRES_TEST_CACHE"],
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


class _FileProgress:
    """On the process that reports (pytest alone, or xdist's controller): a line as each test file's last test ends."""

    def __init__(self, config):
        self.config, self.left, self.seconds, self.files = config, collections.Counter(), collections.Counter(), 0
        self.start = time.monotonic()

    def _count(self, nodeids):
        if not self.left:
            self.left.update(nodeid.split("::")[0] for nodeid in nodeids)
            self.files = len(self.left)

    def pytest_collection_finish(self, session):
        self._count(item.nodeid for item in session.items)

    @pytest.hookimpl(optionalhook=True)
    def pytest_xdist_node_collection_finished(self, node, ids):
        self._count(ids)

    def pytest_runtest_logreport(self, report):
        path = report.nodeid.split("::")[0]
        self.seconds[path] += report.duration
        if report.when != "teardown" or path not in self.left:
            return
        self.left[path] -= 1
        if self.left[path] == 0:
            del self.left[path]
            minutes = (time.monotonic() - self.start) / 60
            reporter = self.config.pluginmanager.get_plugin("terminalreporter")
            if reporter._tw.width_of_current_line:  # after the progress dots
                reporter.write("\n")
            reporter.write_line(
                f"[{minutes:5.1f} min] {path} done in {self.seconds[path]:.0f} s "
                f"({self.files - len(self.left)} of {self.files} files)")


def pytest_configure(config):
    if not hasattr(config, "workerinput"):  # not on xdist's workers: their reports reach the controller
        config.pluginmanager.register(_FileProgress(config), "dynres_file_progress")
