"""Compiled programs kept between runs: JAX's persistent compilation cache, on by default.

Importing :mod:`softbody` calls :func:`setup`, which points JAX's persistent compilation
cache at ``$SOFTBODY_CACHE_DIR/xla`` (default ``~/.cache/softbody/xla``, beside the native
library built by :mod:`softbody.native`). A later process that traces the same program
(same shapes, same constants, same jax/jaxlib and XLA flags) then loads its machine code
from there instead of compiling it again.

* ``SOFTBODY_COMPILATION_CACHE=0`` turns it off (``1``, or unset, leaves it on).
* Your own JAX settings win: if ``JAX_COMPILATION_CACHE_DIR`` (or
  ``jax.config.update("jax_compilation_cache_dir", ...)`` before importing softbody) names a
  folder, or ``JAX_ENABLE_COMPILATION_CACHE=0``, softbody changes nothing; likewise for
  ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``.
* Programs that compile in under :data:`MIN_COMPILE_TIME_S` are not written (JAX's own
  default is 1 s).
* JAX never writes a program that holds a Python host callback. With the native library
  (:mod:`softbody.native`, built with the system C++ compiler) the default path holds
  none: :class:`~softbody.linsolve.DenseCholesky` (the default below 400 vertices),
  :class:`~softbody.linsolve.PCG` and :class:`~softbody.linsolve.SparseLDL` (the default
  from 400 vertices, factorised and solved by XLA FFI calls) run inside the program, and
  under an outer ``jit``/``grad`` ``rollout(..., throw=True)`` checks its steps with an
  FFI call too. The README's first script (555 vertices, a 50-step rollout and its
  gradient) then spent 64 s compiling in its first process and 6.4 s in the second
  (tracing, lowering, and compiling or loading 125 programs, 104 of them from the cache;
  95 s against 28 s wall, on one core of a loaded 2-core machine). Host callbacks remain in
  :class:`~softbody.linsolve.SparseCholesky` and :class:`~softbody.linsolve.SparseLU`
  (without a C++ compiler, or above 10k vertices) and, without the native library or off
  the CPU, in the ``throw=True`` check: there compiled functions that should be cached
  call ``rollout(..., throw=False)`` and :func:`softbody.simulate.check_trajectory` on
  their output (as ``softbody demo`` does).
* The folder is kept under ``SOFTBODY_COMPILATION_CACHE_MB`` megabytes (default
  :data:`DEFAULT_MAX_MB`): at import, the least recently used programs beyond it are
  deleted. One run can go past the cap; the next import trims it.
* When the folder cannot be created or written, softbody prints one line to stderr and
  runs without the cache.

Command line::

    softbody cache info             the folder, its size and entry count
    softbody cache clear [--all]    delete the compiled programs (--all: the native library too)

The cache is trusted code: whoever can write to the folder can make your process run
their machine code. Do not point it at a folder others can write to.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import os
import shutil
import sys
import tempfile
from pathlib import Path

#: Environment variable that turns the cache off (``0``) or on (``1``, the default).
SWITCH = "SOFTBODY_COMPILATION_CACHE"
#: Environment variable with the size cap in megabytes.
MAX_MB_VARIABLE = "SOFTBODY_COMPILATION_CACHE_MB"
#: Default size cap, MB.
DEFAULT_MAX_MB = 1024
#: Programs compiling faster than this (s) are not written to the cache. JAX's default, 1 s,
#: skips all but the two big programs of ``softbody demo --quick``; its ~140 small ones
#: (eager operations, the optimiser's update) took 12-26 s together to compile on the
#: shared 2-core machine and 1.5 s to load from the cache (142 programs, ~9 ms each, 0.6 MB).
#: Below 0.02 s (21 of them, 0.23 s together) a file does not pay.
MIN_COMPILE_TIME_S = 0.02
#: JAX's file suffix for one compiled program.
ENTRY_SUFFIX = "-cache"

_OFF, _ON = {"0", "false", "no", "off"}, {"", "1", "true", "yes", "on"}
_state: dict = {"folder": None, "reason": "softbody.cache.setup() has not run"}


def folder() -> Path:
    """softbody's compilation cache folder: ``<native cache dir>/xla``.

    Returns:
        ``$SOFTBODY_CACHE_DIR/xla`` (default ``~/.cache/softbody/xla``), whether or not
        the cache is in use.
    """
    from softbody.native import cache_dir

    return cache_dir() / "xla"


def max_bytes() -> int:
    """The size cap from ``$SOFTBODY_COMPILATION_CACHE_MB`` (default :data:`DEFAULT_MAX_MB`), in bytes.

    Raises:
        ValueError: if the variable is not a positive number.
    """
    text = os.environ.get(MAX_MB_VARIABLE, "").strip()
    if not text:
        return DEFAULT_MAX_MB << 20
    try:
        mb = float(text)
    except ValueError:
        mb = -1.0
    if not mb > 0:
        raise ValueError(f"{MAX_MB_VARIABLE}={text!r} is not a positive number of megabytes; "
                         f"set e.g. {MAX_MB_VARIABLE}={DEFAULT_MAX_MB}, or unset it")
    return int(mb * (1 << 20))


def setup() -> Path | None:
    """Turn on JAX's persistent compilation cache in :func:`folder` unless told not to.

    Called once by ``import softbody``. Leaves JAX alone when the user configured its
    cache (see the module docstring) or set ``SOFTBODY_COMPILATION_CACHE=0``; prints one
    line to stderr and leaves the cache off when the folder is not writable or a
    setting is malformed.

    Returns:
        The folder now in use, or ``None`` (then :func:`reason` says why).
    """
    import jax

    _state["folder"] = None
    switch = os.environ.get(SWITCH, "").strip().lower()
    if switch in _OFF:
        return _off(f"off ({SWITCH}={os.environ[SWITCH]})")
    if jax.config.jax_compilation_cache_dir is not None:
        return _off(f"your own JAX cache is in use: {jax.config.jax_compilation_cache_dir}")
    if not jax.config.jax_enable_compilation_cache:
        return _off("off (JAX's jax_enable_compilation_cache is False)")
    if switch not in _ON:
        return _off(f"off: {SWITCH}={os.environ[SWITCH]!r} is neither 0 nor 1; set one of them", warn=True)
    path = folder()
    try:
        cap = max_bytes()
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
        prune(path, cap)
    except OSError as error:
        return _off(f"off: cannot write to {path} ({error.strerror or error})", warn=True,
                    hint=f"set SOFTBODY_CACHE_DIR to a writable folder, or {SWITCH}=0 to silence this")
    except ValueError as error:
        return _off(f"off: {error}", warn=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    _state["folder"], _state["reason"] = path, f"on: {path}"
    return path


def _off(why: str, warn: bool = False, hint: str = "") -> None:
    _state["reason"] = why
    if warn:
        print(f"softbody: compilation cache {why}" + (f"; {hint}" if hint else ""), file=sys.stderr)
    return None


def active() -> Path | None:
    """The folder softbody's cache uses in this process, or ``None`` when it is not in use."""
    return _state["folder"]


def reason() -> str:
    """Whether the cache is on, and if not, why (one line)."""
    return _state["reason"]


#: JAX's monitoring events of the persistent cache -> the names :func:`watch` counts them under.
_EVENTS = {"/jax/compilation_cache/compile_requests_use_cache": "requests",
           "/jax/compilation_cache/cache_hits": "hits",
           "/jax/compilation_cache/cache_misses": "writes"}


@contextlib.contextmanager
def watch():
    """Count what JAX's persistent cache does while the ``with`` block runs.

    Yields:
        A :class:`collections.Counter` filled as the block runs: ``"requests"`` (programs
        looked up in the cache, i.e. compiled or loaded), ``"hits"`` (loaded from it) and
        ``"writes"`` (compiled and written to it).
    """
    import jax

    counts: collections.Counter = collections.Counter()

    def listen(event: str, **_metadata) -> None:
        if event in _EVENTS:
            counts[_EVENTS[event]] += 1

    jax.monitoring.register_event_listener(listen)
    try:
        yield counts
    finally:
        jax.monitoring.unregister_event_listener(listen)


def entries(path: Path | None = None) -> list[Path]:
    """The compiled programs in ``path`` (default :func:`folder`), one file each.

    Returns:
        The files named ``*-cache``; an empty list if the folder does not exist.
    """
    path = folder() if path is None else Path(path)
    return sorted(path.glob(f"*{ENTRY_SUFFIX}")) if path.is_dir() else []


def size(path: Path | None = None) -> int:
    """Total bytes of every file under ``path`` (default :func:`folder`); 0 if it is missing."""
    path = folder() if path is None else Path(path)
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                total += os.stat(os.path.join(root, name)).st_size
            except OSError:  # deleted meanwhile by another process
                pass
    return total


def prune(path: Path, limit: int) -> int:
    """Delete the least recently used compiled programs in ``path`` until they fit in ``limit`` bytes.

    Arguments:
        path: a compilation cache folder.
        limit: the size cap, bytes.

    Returns:
        The number of programs deleted.
    """
    found = []
    for entry in entries(path):
        try:
            stat = entry.stat()
        except OSError:
            continue
        found.append((max(stat.st_atime, stat.st_mtime), stat.st_size, entry))
    total = sum(size for _, size, _ in found)
    deleted = 0
    for _, entry_size, entry in sorted(found):
        if total <= limit:
            break
        for stale in (entry, entry.with_name(entry.name[: -len(ENTRY_SUFFIX)] + "-atime")):
            stale.unlink(missing_ok=True)
        total -= entry_size
        deleted += 1
    return deleted


def clear(native: bool = False) -> tuple[int, int]:
    """Delete softbody's compiled programs (the folder :func:`folder`).

    Arguments:
        native: also delete the native libraries (``softbody-*.so``) built by
            :mod:`softbody.native`; they are rebuilt on first use.

    Returns:
        ``(files, bytes)`` deleted.
    """
    from softbody.native import cache_dir

    path = folder()
    files, freed = 0, size(path)
    if path.is_dir():
        files += sum(len(names) for _root, _dirs, names in os.walk(path))
        shutil.rmtree(path)
    if native:
        for library in cache_dir().glob("softbody-*.so"):
            freed += library.stat().st_size
            library.unlink()
            files += 1
    return files, freed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``softbody cache``."""
    parser.add_argument("action", choices=("info", "clear"),
                        help="info: the folder, its size and entry count; clear: delete the compiled programs")
    parser.add_argument("--all", action="store_true",
                        help="with clear: also delete the native library (rebuilt on first use)")


def run(args: argparse.Namespace) -> int:
    """Run ``softbody cache``; returns the exit status (0 ok, 1 failed)."""
    from softbody.native import cache_dir

    path = folder()
    if args.action == "clear":
        try:
            files, freed = clear(native=args.all)
        except OSError as error:
            print(f"softbody cache: could not delete {error.filename}: {error.strerror}", file=sys.stderr)
            return 1
        what = "compiled programs and native library" if args.all else "compiled programs"
        print(f"deleted {files} files ({freed / 2**20:.1f} MB) of {what} under {cache_dir()}")
        return 0
    try:
        cap = f"cap {max_bytes() / 2**20:.0f} MB, ${MAX_MB_VARIABLE}"
    except ValueError as error:
        print(f"softbody cache: {error}", file=sys.stderr)
        return 1
    libraries = sorted(cache_dir().glob("softbody-*.so"))
    print(f"compilation cache: {reason()}")
    print(f"folder:            {path}")
    print(f"size:              {size(path) / 2**20:.1f} MB in {len(entries(path))} compiled programs ({cap})")
    print(f"native library:    {len(libraries)} file(s), "
          f"{sum(p.stat().st_size for p in libraries) / 2**20:.1f} MB in {cache_dir()}")
    return 0
