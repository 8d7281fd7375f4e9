import gc
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import pytest  # noqa: E402

import softbody  # noqa: E402,F401  (turns on float64 before any test builds arrays)
from softbody import linsolve  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_module_programs():
    """After each test module, drop its compiled programs and host factorisations.

    A full run otherwise keeps every module's XLA executables and Cholesky factors alive
    to the end (the process grew to ~8 GB resident by the gradient tests), though no
    later module calls them again.
    """
    yield
    jax.clear_caches()
    linsolve.clear_factor_cache()
    gc.collect()
