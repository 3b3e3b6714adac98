"""The numba cache's key covers every file that defines pdem's numba functions.

numba checks only the timestamp of the file that defines a cached function, not of the files whose
functions it inlines; pdem keys its cache directory on a hash of those files instead
(``pdem._jit._kernel_sources``). A numba function defined in a file outside that list could be
inlined into a cached kernel and run stale after an upgrade or an edit (``parallel/exact.py``'s
exact sums once were)."""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

import numba.core.registry

import pdem
from pdem import _jit


def _numba_functions():
    """(module, name, defining file) of every numba dispatcher found in pdem's modules."""
    out = []
    for info in pkgutil.walk_packages(pdem.__path__, "pdem."):
        if info.name.endswith("__main__"):
            continue
        mod = importlib.import_module(info.name)
        for name, obj in vars(mod).items():
            if isinstance(obj, numba.core.registry.CPUDispatcher):
                out.append((info.name, name, Path(obj.py_func.__code__.co_filename).resolve()))
    return out


def test_every_numba_function_is_in_the_cache_key():
    covered = set(_jit._kernel_sources())
    found = _numba_functions()
    files = {f for _, _, f in found}
    assert Path(pdem.parallel.exact.__file__).resolve() in files  # the case that was missed
    assert len(files) >= 10
    missing = sorted({(m, n, str(f)) for m, n, f in found if f not in covered})
    assert not missing, missing


def test_the_cache_key_changes_with_a_kernel_source(tmp_path, monkeypatch):
    """A different byte in any covered file gives another cache directory."""
    base = _jit._kernel_source_hash()
    src = Path(pdem.parallel.exact.__file__).resolve()
    real = Path.read_bytes

    def read_bytes(self):
        data = real(self)
        return data + b"\n# edited" if self.resolve() == src else data

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    assert _jit._kernel_source_hash() != base
