import gc
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import pytest  # noqa: E402

import softbody  # noqa: E402,F401  (turns on float64 before any test builds arrays)
from softbody import linsolve, reference, simulate  # noqa: E402

#: XLA's CPU backend maps each compiled program's code into memory (~6 mappings for a
#: small one). A full run compiles thousands of programs; past the kernel's limit
#: (vm.max_map_count, 65530 by default) new code cannot be mapped and compiling fails. Keep
#: well below it by releasing compiled programs once a test leaves this many mappings.
MAPPINGS_LIMIT = 20000


def _release():
    jax.clear_caches()
    linsolve.clear_factor_cache()
    gc.collect()


def _mappings() -> int:
    try:
        with open(f"/proc/{os.getpid()}/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:  # no procfs: nothing to watch
        return 0


@pytest.fixture(autouse=True, scope="module")
def _release_module_programs():
    """After each test module, drop its compiled programs and host factorisations (no
    later module calls them again)."""
    yield
    _release()


@pytest.fixture(autouse=True)
def _bound_mappings():
    """After a test that leaves more than :data:`MAPPINGS_LIMIT` memory mappings, release
    the compiled programs (module-scoped fixtures recompile on their next call)."""
    yield
    if _mappings() > MAPPINGS_LIMIT:
        _release()


@pytest.fixture
def no_compiling(monkeypatch):
    """Make any attempt to run (compile) a rollout, a static solve or a Newton step fail, so
    a test can show that bad input is refused before anything compiles."""
    def forbidden(*args, **kwargs):
        raise AssertionError("reached the compiled solver: the input was not checked first")

    for name in ("_rollout", "_solve_static"):
        monkeypatch.setattr(simulate, name, forbidden)
    monkeypatch.setattr(reference, "prepare", forbidden)
