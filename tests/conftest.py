"""Suite-wide hygiene: each test module starts with JAX's compiled executables released, so a 2-core CI machine does
not carry hundreds of them (and their code memory) from one module into the next."""

import jax
import pytest


@pytest.fixture(autouse=True, scope="module")
def _fresh_compile_caches():
    jax.clear_caches()
    yield
