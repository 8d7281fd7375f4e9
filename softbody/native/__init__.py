"""Native kernels that XLA calls directly, compiled from source on first use.

``sparse_ldl.cc`` holds sparse ``LDL^T`` triangular solves registered as an XLA FFI
target (``softbody_ldl_solve``), used by :class:`softbody.linsolve.SparseLDL`. A host
callback (``jax.pure_callback``) costs about 1-2 ms per call inside a compiled loop that
also does heavy XLA work (measured on the shared DiffPD cantilever: 3.5 ms against 1.4 ms
per local-global iteration with a JAX-native stand-in); a native call does not enter Python.

The library is built with the system C++ compiler (``$CXX`` or ``c++``) against the XLA
FFI headers shipped with jaxlib, once per source and jaxlib version, into
``$SOFTBODY_CACHE_DIR`` (default ``~/.cache/softbody``). Without a compiler
:func:`library` returns ``None`` and :func:`unavailable_reason` says why; the solvers fall
back to :class:`softbody.linsolve.SparseCholesky`.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
from importlib import resources
from pathlib import Path

import numpy as np

#: Name of the XLA FFI target of the LDL^T solve.
SOLVE_TARGET = "softbody_ldl_solve"

_lock = threading.Lock()
_state: dict = {}


def cache_dir() -> Path:
    """Where compiled libraries are kept: ``$SOFTBODY_CACHE_DIR`` or ``~/.cache/softbody``."""
    base = os.environ.get("SOFTBODY_CACHE_DIR")
    if base:
        return Path(base)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "softbody"


def _compile(source: Path, target: Path) -> None:
    import jax
    import jaxlib

    compiler = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if compiler is None:
        raise RuntimeError("no C++ compiler found (install g++, or set CXX)")
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    cmd = [compiler, "-O3", "-std=c++17", "-fPIC", "-shared", "-isystem", jax.ffi.include_dir(),
           str(source), "-o", tmp]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed (jaxlib {jaxlib.__version__}):\n{done.stderr[-2000:]}")
        os.replace(tmp, target)  # atomic: concurrent builders race harmlessly
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _load() -> ctypes.CDLL:
    import jax
    import jaxlib

    src = resources.files("softbody.native").joinpath("sparse_ldl.cc")
    text = src.read_bytes()
    key = hashlib.sha256(text + jaxlib.__version__.encode() + os.environ.get("CXX", "").encode()).hexdigest()[:16]
    target = cache_dir() / f"sparse_ldl-{key}.so"
    if not target.exists():
        with resources.as_file(src) as path:
            _compile(Path(path), target)
    lib = ctypes.CDLL(str(target))
    i64 = np.ctypeslib.ndpointer(np.int64, flags="C_CONTIGUOUS")
    f64 = np.ctypeslib.ndpointer(np.float64, flags="C_CONTIGUOUS")
    lib.softbody_ldl_store.restype = ctypes.c_int64
    lib.softbody_ldl_store.argtypes = [ctypes.c_int64, ctypes.c_int64, i64, i64, f64, f64, i64, i64]
    lib.softbody_ldl_release.restype = None
    lib.softbody_ldl_release.argtypes = [ctypes.c_int64, ctypes.c_int64]
    lib.softbody_ldl_solve_host.restype = ctypes.c_int
    lib.softbody_ldl_solve_host.argtypes = [ctypes.c_int64, f64, f64, ctypes.c_int64]
    lib.softbody_ldl_count.restype = ctypes.c_int64
    lib.softbody_ldl_count.argtypes = []
    jax.ffi.register_ffi_target(SOLVE_TARGET, jax.ffi.pycapsule(lib.SoftbodyLdlSolve), platform="cpu")
    return lib


def library() -> ctypes.CDLL | None:
    """The compiled native library (built on first call), or ``None`` if it cannot be built.

    Returns:
        A ``ctypes.CDLL`` with ``softbody_ldl_store``, ``softbody_ldl_release``,
        ``softbody_ldl_solve_host`` and ``softbody_ldl_count``; its FFI solve is
        registered with XLA as :data:`SOLVE_TARGET`. ``None`` when there is no C++
        compiler or the build fails (see :func:`unavailable_reason`).
    """
    with _lock:
        if "lib" not in _state:
            try:
                _state["lib"], _state["reason"] = _load(), None
            except Exception as error:  # no compiler, failed build: fall back, keep the reason
                _state["lib"], _state["reason"] = None, f"{type(error).__name__}: {error}"
        return _state["lib"]


def unavailable_reason() -> str | None:
    """Why :func:`library` returned ``None`` (``None`` when it is available)."""
    library()
    return _state["reason"]


def available() -> bool:
    """Whether the native library is (or can be) built here."""
    return library() is not None
