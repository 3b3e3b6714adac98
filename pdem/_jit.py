"""The one place where pdem configures numba.

* ``fastmath`` is off everywhere: bitwise determinism across rank counts needs IEEE arithmetic
  in the order the source states.
* Kernels are cached on disk (``cache=True``) so that a warm start does not recompile. The cache
  lives in a directory keyed by a hash of pdem's kernel sources (see :func:`_kernel_sources`):
  numba checks only the timestamp of the file that defines a cached function, so a law plugin
  whose cached wrapper inlines pdem's generic loops would otherwise keep running a stale loop after
  pdem changed. Set
  ``PDEM_NUMBA_CACHE_DIR`` (or numba's own ``NUMBA_CACHE_DIR``) to choose the base directory.

Import :data:`njit` from here, never decorate with numba directly.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numba

__all__ = ["njit", "njit_nocache", "cache_dir"]

_PKG = Path(__file__).resolve().parent


def _kernel_sources() -> list[Path]:
    """Files whose numba code can be inlined into cached functions defined in *other* files: every
    module of pdem that mentions ``njit`` (the kernel modules ``_*.py``, and others whose numba
    functions the plugin API exports, e.g. ``parallel/exact.py``'s exact sums, which
    ``complementarity/_kernels.py`` inlines), and the built-in laws. Editing any other file cannot
    make a cached kernel stale (``tests/test_jit_cache.py`` checks every numba function pdem defines
    against this list)."""
    files = [p for p in _PKG.rglob("*.py") if "njit" in p.read_text(encoding="utf-8")]
    files += list((_PKG / "laws").glob("*.py"))
    return sorted(set(files))


def _kernel_source_hash() -> str:
    h = hashlib.sha256()
    h.update(" ".join(LLVM_OPTIONS).encode())
    for path in _kernel_sources():
        h.update(path.relative_to(_PKG).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _choose_cache_dir() -> str:
    base = os.environ.get("PDEM_NUMBA_CACHE_DIR") or os.environ.get("NUMBA_CACHE_DIR")
    if not base:
        xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        base = os.path.join(xdg, "pdem", "numba")
    return os.path.join(base, f"{numba.__version__}-{_kernel_source_hash()}")


# LLVM vectorizes a loop over several arrays only after checking at run time that they do not
# overlap, and by default gives up above 8 comparisons ("too many memory checks needed"): a loop over
# contacts held in columns (DEM-P's Hertz–Mindlin pair kernel reads 19 columns and writes 7) needs
# more. Raising the limit only lets more loops vectorize. Without fastmath a vectorized loop rounds
# as the scalar one does, so results keep their bits. The options are part of the cache key.
LLVM_OPTIONS = ("--runtime-memory-check-threshold=512", "--vectorize-memory-check-threshold=1024")


def _configure_llvm() -> None:
    import llvmlite.binding as llvm

    for option in LLVM_OPTIONS:
        llvm.set_option("pdem", option)


_configure_llvm()
cache_dir = _choose_cache_dir()
numba.config.CACHE_DIR = cache_dir

_FLAGS = dict(cache=True, fastmath=False, nogil=True, error_model="numpy", boundscheck=False)


def njit(*args, **kwargs):
    """``numba.njit`` with pdem's flags (cached, no fastmath, numpy error model)."""
    opts = {**_FLAGS, **kwargs}
    if args and callable(args[0]) and len(args) == 1:
        return numba.njit(**opts)(args[0])
    return numba.njit(*args, **opts)


def njit_nocache(*args, **kwargs):
    """Like :func:`njit` but never cached: for generic loops that take a function argument.

    They are compiled into (and cached with) the small module-level wrappers that call them with a
    concrete law, see :mod:`pdem.contact.law`.
    """
    opts = {**_FLAGS, **kwargs, "cache": False}
    if args and callable(args[0]) and len(args) == 1:
        return numba.njit(**opts)(args[0])
    return numba.njit(*args, **opts)
