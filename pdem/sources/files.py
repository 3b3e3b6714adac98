"""Read and write sphere packings.

Text format (any suffix except ``.h5``/``.hdf5``): one sphere per line, columns separated by
whitespace and/or commas, ``#`` starts a comment, blank lines are ignored. Columns are
``x y z diameter`` with optional ``vx vy vz`` (SI units). The first non-comment line may be a
header naming the columns; with a header the columns may come in any order and ``radius`` may
replace ``diameter``.

HDF5 format: root datasets ``x`` or ``position`` (n,3), ``diameter`` or ``radius`` (n,), optional
``velocity`` (n,3). Plural spellings (``positions``, ``radii``, ``diameters``, ``velocities``) are
accepted too.

Limits (docs/deck.md, "Limits"): the file must be a regular file (a directory, a device or a named
pipe is refused without reading it); a text line is at most :data:`MAX_LINE_LENGTH` characters of
UTF-8 text; radii lie in :data:`~pdem.deck.schema.RADIUS_RANGE`, coordinates and velocity
components within :data:`~pdem.deck.schema.MAX_MAGNITUDE`. Errors quote at most about 80 characters
of a line, so a file that is not a packing file (a system file, a binary) is named, not printed.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pdem.errors import InputError
from pdem.textutil import clip, file_problem, quote

__all__ = ["read_spheres", "iter_spheres", "write_spheres_text", "packing_file_problem", "MAX_LINE_LENGTH"]

_SPLIT = re.compile(r"[,\s]+")
_HDF5_SUFFIXES = (".h5", ".hdf5")
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_KNOWN_COLUMNS = ("x", "y", "z", "diameter", "radius", "vx", "vy", "vz")
#: longest line of a text packing file [characters]; a row of 7 numbers is at most ~200
MAX_LINE_LENGTH = 10_000
#: characters of a line quoted in an error
_SHOWN = 80


def _name(p: Path) -> str:
    """The file as named in a message (at most ~200 characters)."""
    return clip(str(p))


def _tok(token: str) -> str:
    return quote(token, _SHOWN)


def packing_file_problem(path: str | os.PathLike[str]) -> str | None:
    """None if ``path`` is a regular, readable file; else why it cannot be a packing file (the end
    of a sentence: ``"is a named pipe (FIFO), not a regular file"``). Looks at the path only."""
    return file_problem(path)


def read_spheres(path: str | os.PathLike[str]) -> dict[str, NDArray[np.float64] | None]:
    """Read a sphere packing from a text or HDF5 file (see the module docstring for the formats).

    Returns ``{"positions": (n,3), "radii": (n,), "velocities": (n,3) or None}`` (float64, file
    order). Raises :class:`~pdem.errors.InputError` naming the file (and line) for a missing file,
    a malformed line, a non-positive diameter, non-finite values or missing datasets.
    """
    p = Path(path)
    problem = packing_file_problem(p)
    if problem is not None:
        raise InputError(f"sphere file {quote(str(p))} {problem}; give a packing file (text or HDF5)")
    if p.suffix.lower() in _HDF5_SUFFIXES:
        out = _read_hdf5(p)
        linenos = None
    else:
        out, linenos = _read_text(p)
    _validate(p, out, linenos)
    return out


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _not_packing(p: Path, lineno: int, line: str) -> InputError:
    return InputError(
        f"{_name(p)} is not a packing file: line {lineno} ({quote(line, _SHOWN)}) is neither a row of "
        "numbers 'x y z diameter [vx vy vz]' nor a header naming those columns; check the path"
    )


def _header_columns(p: Path, lineno: int, tokens: list[str], line: str) -> dict[str, int]:
    names = [t.lower() for t in tokens]
    if not any(t in _KNOWN_COLUMNS for t in names) or len(names) > 2 * len(_KNOWN_COLUMNS):
        raise _not_packing(p, lineno, line)
    for t in names:
        if t not in _KNOWN_COLUMNS:
            raise InputError(
                f"{_name(p)}: line {lineno}: unknown column {_tok(t)} in header; expected the columns "
                "'x y z diameter' (or radius), optionally followed by 'vx vy vz'"
            )
    header = quote(" ".join(tokens), _SHOWN)
    if len(set(names)) != len(names):
        raise InputError(f"{_name(p)}: line {lineno}: header {header} repeats a column name")
    cols = {t: i for i, t in enumerate(names)}
    missing = [c for c in ("x", "y", "z") if c not in cols]
    if missing or ("diameter" in cols) == ("radius" in cols):
        raise InputError(
            f"{_name(p)}: line {lineno}: header {header} must name x, y, z and exactly one of "
            "diameter or radius"
        )
    nv = sum(c in cols for c in ("vx", "vy", "vz"))
    if nv not in (0, 3):
        raise InputError(f"{_name(p)}: line {lineno}: header names {nv} of vx vy vz; give all three or none")
    return cols


def _lines(p: Path):
    """``(line number, text)`` of a text packing file, refusing binary data (NUL bytes, not UTF-8,
    an HDF5 file under another suffix) and lines longer than :data:`MAX_LINE_LENGTH` without
    reading them whole."""
    with p.open("rb") as fh:
        lineno = 0
        while True:
            raw = fh.readline(MAX_LINE_LENGTH + 2)
            if not raw:
                return
            lineno += 1
            if lineno == 1 and raw.startswith(_HDF5_SIGNATURE):
                raise InputError(
                    f"{_name(p)} is an HDF5 file; name it with the suffix .h5 or .hdf5 to read it as one"
                )
            if len(raw.rstrip(b"\r\n")) > MAX_LINE_LENGTH:
                raise InputError(
                    f"{_name(p)}: line {lineno} is longer than {MAX_LINE_LENGTH:,} characters, which no "
                    "row 'x y z diameter [vx vy vz]' is: is this a packing file?"
                )
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError:
                text = "\x00"
            if "\x00" in text:
                raise InputError(
                    f"{_name(p)} is not a text packing file: line {lineno} holds binary data; give a text "
                    "file of rows 'x y z diameter [vx vy vz]', or an HDF5 file named .h5 or .hdf5"
                )
            yield lineno, text


def _text_chunks(p: Path, size: int):
    """The numeric rows of a text packing file, ``size`` at a time: ``(data (k, ncol), line numbers,
    columns by name or None, ncol)``; the header and every row's shape are checked on the way."""
    cols: dict[str, int] | None = None
    ncol: int | None = None
    rows: list[list[float]] = []
    linenos: list[int] = []
    seen = 0
    for lineno, raw in _lines(p):
        line = raw.split("#", 1)[0].strip().strip(",")
        if not line:
            continue
        tokens = [t for t in _SPLIT.split(line) if t]
        if cols is None and not seen and not all(_is_number(t) for t in tokens):
            cols = _header_columns(p, lineno, tokens, line)
            ncol = len(tokens)
            continue
        if ncol is None:
            if len(tokens) not in (4, 7):
                if not seen and not all(_is_number(t) for t in tokens):
                    raise _not_packing(p, lineno, line)
                raise InputError(
                    f"{_name(p)}: line {lineno}: expected 4 columns 'x y z diameter' or 7 columns "
                    f"'x y z diameter vx vy vz', found {len(tokens)}"
                )
            ncol = len(tokens)
        elif len(tokens) != ncol:
            raise InputError(
                f"{_name(p)}: line {lineno}: expected {ncol} columns like the "
                f"{'header' if cols is not None else 'first data line'}, found {len(tokens)}"
            )
        try:
            rows.append([float(t) for t in tokens])
            linenos.append(lineno)
            seen += 1
        except ValueError:
            bad = next(t for t in tokens if not _is_number(t))
            raise InputError(
                f"{_name(p)}: line {lineno}: cannot read {_tok(bad)} as a number; expected numeric "
                "columns x y z diameter [vx vy vz]"
            ) from None
        if len(rows) == size:
            yield np.asarray(rows, dtype=np.float64), linenos, cols, ncol
            rows, linenos = [], []
    if not seen:
        raise InputError(f"{_name(p)}: no sphere rows found; expected lines 'x y z diameter [vx vy vz]'")
    if rows:
        yield np.asarray(rows, dtype=np.float64), linenos, cols, ncol


def _text_columns(
    p: Path, data: NDArray[np.float64], linenos: list[int], cols: dict[str, int] | None, ncol: int
) -> dict[str, NDArray[np.float64] | None]:
    """Positions, radii and velocities of text rows, checked (finite, radius > 0)."""
    bad_rows = ~np.all(np.isfinite(data), axis=1)
    if np.any(bad_rows):
        i = int(np.argmax(bad_rows))
        raise InputError(
            f"{_name(p)}: line {linenos[i]}: non-finite value in {data[i].tolist()}; fix the file"
        )
    if cols is None:
        cols = {"x": 0, "y": 1, "z": 2, "diameter": 3}
        if ncol == 7:
            cols.update(vx=4, vy=5, vz=6)
    positions = np.ascontiguousarray(data[:, [cols["x"], cols["y"], cols["z"]]])
    if "diameter" in cols:
        radii = 0.5 * data[:, cols["diameter"]]
    else:
        radii = data[:, cols["radius"]].copy()
    if np.any(radii <= 0.0):
        i = int(np.argmax(radii <= 0.0))
        what = "diameter" if "diameter" in cols else "radius"
        raise InputError(
            f"{_name(p)}: line {linenos[i]}: {what} {float(data[i, cols[what]])!r} is not > 0; expected a "
            f"positive sphere {what} in metres"
        )
    velocities = None
    if "vx" in cols:
        velocities = np.ascontiguousarray(data[:, [cols["vx"], cols["vy"], cols["vz"]]])
    return {"positions": positions, "radii": np.ascontiguousarray(radii), "velocities": velocities}


def _read_text(p: Path) -> tuple[dict[str, NDArray[np.float64] | None], list[int]]:
    chunks = list(_text_chunks(p, 1 << 62))
    data, linenos, cols, ncol = chunks[0]
    return _text_columns(p, data, linenos, cols, ncol), linenos


def iter_spheres(path: str | os.PathLike[str], size: int = 65536):
    """Read a packing file (as :func:`read_spheres`) ``size`` spheres at a time, in file order:
    yields ``{"positions", "radii", "velocities", "start"}`` (``start``: the first sphere's row, from
    0), each chunk checked as :func:`read_spheres` checks the whole file (the first error found may
    be a later one in the file than the whole file's). Memory is one chunk's."""
    p = Path(path)
    problem = packing_file_problem(p)
    if problem is not None:
        raise InputError(f"sphere file {quote(str(p))} {problem}; give a packing file (text or HDF5)")
    start = 0
    if p.suffix.lower() in _HDF5_SUFFIXES:
        for out in _hdf5_chunks(p, size):
            _validate(p, out, None, start)
            yield {**out, "start": start}
            start += out["radii"].shape[0]
        return
    for data, linenos, cols, ncol in _text_chunks(p, size):
        out = _text_columns(p, data, linenos, cols, ncol)
        _validate(p, out, linenos)
        yield {**out, "start": start}
        start += out["radii"].shape[0]


def _open_hdf5(p: Path):
    """The HDF5 file ``p``, open for reading, or an InputError naming it."""
    import h5py

    try:
        return h5py.File(p, "r")
    except OSError as exc:
        why = clip(str(exc))
        raise InputError(f"{_name(p)}: cannot open as HDF5 ({why}); is it really an HDF5 file?") from None


def _hdf5_chunks(p: Path, size: int):
    """An HDF5 packing's spheres ``size`` at a time (the datasets checked as :func:`_read_hdf5` does)."""
    with _open_hdf5(p) as f:
        names = {}
        for key, options in (("pos", ("x", "position", "positions")), ("diam", ("diameter", "diameters")),
                             ("rad", ("radius", "radii")), ("vel", ("velocity", "velocities"))):  # fmt: skip
            found = [n for n in options if n in f]
            if len(found) > 1:
                keep = list(options)
                raise InputError(f"{_name(p)}: datasets {found} all present; keep only one of {keep}")
            names[key] = found[0] if found else None
        if names["pos"] is None or (names["diam"] is None and names["rad"] is None) or (
            names["diam"] is not None and names["rad"] is not None
        ):
            _read_hdf5(p)  # the whole-file reader names what is wrong
        pos = f[names["pos"]]
        n = pos.shape[0] if len(pos.shape) == 2 and pos.shape[1] == 3 else -1
        rad = f[names["diam"] or names["rad"]]
        vel = f[names["vel"]] if names["vel"] else None
        if n < 0 or rad.shape != (n,) or (vel is not None and vel.shape != (n, 3)):
            _read_hdf5(p)
        for a in range(0, n, size):
            b = min(n, a + size)
            try:
                x = np.asarray(pos[a:b], dtype=np.float64)
                r = np.asarray(rad[a:b], dtype=np.float64) * (0.5 if names["diam"] else 1.0)
                v = None if vel is None else np.asarray(vel[a:b], dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise InputError(f"{_name(p)}: a dataset is not numeric ({clip(str(exc))})") from None
            yield {"positions": np.ascontiguousarray(x), "radii": np.ascontiguousarray(r),
                   "velocities": None if v is None else np.ascontiguousarray(v)}  # fmt: skip


def _dataset(f, p: Path, names: tuple[str, ...]) -> NDArray[np.float64] | None:
    found = [n for n in names if n in f]
    if len(found) > 1:
        raise InputError(f"{_name(p)}: datasets {found} all present; keep only one of {list(names)}")
    if not found:
        return None
    try:
        return np.asarray(f[found[0]][()], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{_name(p)}: dataset {_tok(found[0])} is not numeric ({clip(str(exc))})") from None


def _read_hdf5(p: Path) -> dict[str, NDArray[np.float64] | None]:
    with _open_hdf5(p) as f:
        pos = _dataset(f, p, ("x", "position", "positions"))
        diam = _dataset(f, p, ("diameter", "diameters"))
        rad = _dataset(f, p, ("radius", "radii"))
        vel = _dataset(f, p, ("velocity", "velocities"))
    if pos is None:
        raise InputError(f"{_name(p)}: no dataset 'x' or 'position' of shape (n, 3) holding sphere centres")
    if diam is None and rad is None:
        raise InputError(f"{_name(p)}: no dataset 'diameter' or 'radius' of shape (n,)")
    if diam is not None and rad is not None:
        raise InputError(f"{_name(p)}: both 'diameter' and 'radius' datasets present; keep only one")
    radii = 0.5 * diam if diam is not None else rad
    assert radii is not None
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise InputError(f"{_name(p)}: position dataset has shape {pos.shape}, expected (n, 3)")
    n = pos.shape[0]
    if radii.shape != (n,):
        raise InputError(
            f"{_name(p)}: {'diameter' if diam is not None else 'radius'} dataset has shape {radii.shape}, "
            f"expected ({n},) to match the positions"
        )
    if vel is not None and vel.shape != (n, 3):
        raise InputError(f"{_name(p)}: velocity dataset has shape {vel.shape}, expected ({n}, 3)")
    return {
        "positions": np.ascontiguousarray(pos),
        "radii": np.ascontiguousarray(radii),
        "velocities": None if vel is None else np.ascontiguousarray(vel),
    }


def _validate(
    p: Path, out: dict[str, NDArray[np.float64] | None], linenos: list[int] | None = None, start: int = 0
) -> None:
    """Finite values, positive radii within RADIUS_RANGE, coordinates and velocities within
    MAX_MAGNITUDE; an error names the sphere's line (text) or index (HDF5; ``start``: the index of
    the first sphere given)."""
    from ..deck.schema import MAX_MAGNITUDE, RADIUS_RANGE

    def where(i: int) -> str:
        return f"line {linenos[i]}" if linenos is not None else f"sphere {start + i} (0-based)"

    for key in ("positions", "radii", "velocities"):
        arr = out[key]
        if arr is not None and not np.all(np.isfinite(arr)):
            i = int(np.argmax(~np.all(np.isfinite(arr.reshape(arr.shape[0], -1)), axis=1)))
            raise InputError(f"{_name(p)}: {where(i)}: a non-finite value in the {key}; fix the file")
    radii = out["radii"]
    assert radii is not None
    if np.any(radii <= 0.0):
        i = int(np.argmax(radii <= 0.0))
        raise InputError(
            f"{_name(p)}: {where(i)} has diameter {float(2.0 * radii[i])!r}; diameters must be > 0"
        )
    lo, hi = RADIUS_RANGE
    outside = (radii < lo) | (radii > hi)
    if np.any(outside):
        i = int(np.argmax(outside))
        raise InputError(
            f"{_name(p)}: {where(i)}: radius {float(radii[i])!r} m is outside [{lo:.0e}, {hi:.0e}] m, the "
            "sphere radii pdem accepts (a grain's mass and moment of inertia would leave double "
            "precision); the columns are SI: metres"
        )
    for key, what in (("positions", "coordinate"), ("velocities", "velocity component")):
        arr = out[key]
        if arr is None or arr.size == 0:
            continue
        large = np.any(np.abs(arr) > MAX_MAGNITUDE, axis=1)
        if np.any(large):
            i = int(np.argmax(large))
            raise InputError(
                f"{_name(p)}: {where(i)}: a {what} of {float(np.max(np.abs(arr[i])))!r} is larger in "
                f"magnitude than {MAX_MAGNITUDE:.0e}, the most pdem accepts (its squares overflow double "
                "precision); fix the file"
            )


def write_spheres_text(
    path: str | os.PathLike[str],
    positions: ArrayLike,
    radii: ArrayLike,
    velocities: ArrayLike | None = None,
) -> None:
    """Write spheres as text: header ``x y z diameter`` (``+ vx vy vz``), values as ``%.17g``.

    The values read back bitwise identical with :func:`read_spheres`.
    """
    x = np.asarray(positions, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"write_spheres_text: positions has shape {x.shape}, expected (n, 3)")
    if r.shape != (x.shape[0],):
        raise InputError(
            f"write_spheres_text: radii has shape {r.shape}, expected ({x.shape[0]},) to match positions"
        )
    cols = [x, (2.0 * r)[:, None]]
    header = "x y z diameter"
    if velocities is not None:
        v = np.asarray(velocities, dtype=np.float64)
        if v.shape != x.shape:
            raise InputError(
                f"write_spheres_text: velocities has shape {v.shape}, expected {x.shape} like positions"
            )
        cols.append(v)
        header += " vx vy vz"
    data = np.hstack(cols)
    if not np.all(np.isfinite(data)):
        raise InputError("write_spheres_text: positions, radii or velocities contain non-finite values")
    if np.any(r <= 0.0):
        raise InputError(f"write_spheres_text: radius {float(r[np.argmax(r <= 0.0)])!r} is not > 0")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(header + "\n")
        np.savetxt(fh, data, fmt="%.17g", delimiter=" ")
