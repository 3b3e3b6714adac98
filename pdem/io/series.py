"""CSV time series (wall loads, energies, … one row per output time).

:class:`SeriesWriter` writes a header row and then one row per :meth:`SeriesWriter.append`,
flushed at once, so the file is usable (``tail -f``, a plotting script) while the run goes on and
complete up to the last row if the run is killed. Floats are written with ``repr`` (shortest
string that round-trips exactly), integers as integers, strings quoted as CSV needs; a column
missing from a row is left empty. In a *count* column (:func:`is_count_column`: ``step``,
``particles``, ``…contacts``, ``…_count``, ``…iterations`` …) a float holding a whole number is
written as an integer (``100``, not ``100.0``): callers often carry every value as a float.
:func:`read_series` reads the file back into one array per column: int64 when every value is an
integer, float64 when every value is a number (empty cells → NaN), str otherwise.

Continuing a run (``pdem resume``): :func:`truncate_series` drops the rows after a step (those a
previous run wrote after the checkpoint it is resumed from), and ``SeriesWriter(..., append=True)``
appends to an existing file; a column the file lacks is added to its header (the rows already there
get empty cells), a column the new rows lack stays empty in them.
"""

from __future__ import annotations

import csv
import io
import math
import numbers
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import IO

import numpy as np

from ..errors import OutputError
from ..textutil import clip

__all__ = ["SeriesWriter", "is_count_column", "read_series", "truncate_series", "series_rows"]

#: last name components (after the last ".") of columns that hold counts
COUNT_NAMES = frozenset(
    {
        "step",
        "steps",
        "particles",
        "contacts",
        "iterations",
        "rebalances",
        "count",
        "solver_iterations",
        "solver_unconverged",
        "contacts_rank0",
    }
)


def is_count_column(column: str) -> bool:
    """True for a column that holds a count: its last ``.``-separated part is one of
    :data:`COUNT_NAMES` or ends with ``_count`` (e.g. ``hopper.discharged_count``)."""
    leaf = column.rsplit(".", 1)[-1]
    return leaf in COUNT_NAMES or leaf.endswith("_count")


def _cell(column: str, value: object, path: Path) -> str:
    if type(value) is float and not value.is_integer():  # the common case, fast (wide probe rows)
        return repr(value)
    if isinstance(value, bool | np.bool_):
        return "1" if value else "0"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        x = float(value)
        if x.is_integer() and abs(x) <= 2.0**53 and is_count_column(column):  # exact as an integer
            return str(int(x))
        return repr(x)
    if isinstance(value, str):
        return value
    if isinstance(value, np.ndarray) and value.ndim == 0:
        return _cell(column, value.item(), path)
    raise OutputError(
        f"series '{path}': column '{column}' got {type(value).__name__} {value!r}; give a number or a string "
        f"(one value per column per row: split vectors into columns such as fx, fy, fz)"
    )


class SeriesWriter:
    """Append-only CSV time series.

    Parameters
    ----------
    path : CSV file to create (parent directories are created).
    columns : column names, in order (unique, non-empty).
    overwrite : replace an existing file instead of raising :class:`~pdem.errors.OutputError`.
    append : continue an existing file (written by a SeriesWriter) instead: rows are added after
        its last row; columns it lacks are added to its header (see the module doc). A missing
        file is created as usual.
    """

    def __init__(
        self, path: Path | str, columns: Sequence[str], *, overwrite: bool = False, append: bool = False
    ) -> None:
        self.path = Path(path)
        cols = [columns] if isinstance(columns, str) else list(columns)
        if not cols or any(not isinstance(c, str) or not c for c in cols):
            raise OutputError(
                f"series '{self._shown}': columns must be non-empty strings, got {clip(repr(columns))}"
            )
        dup = sorted({c for c in cols if cols.count(c) > 1})
        if dup:
            raise OutputError(
                f"series '{self._shown}': duplicate column(s) {clip(', '.join(dup))}; give each once"
            )
        exists = self._exists()
        if append and exists:
            cols = self._widen(cols)
        self.columns: tuple[str, ...] = tuple(cols)
        self._index = {c: i for i, c in enumerate(cols)}
        self.n_rows = 0
        if append and exists:
            try:
                self._fh: IO[str] | None = open(self.path, "a", newline="", encoding="utf-8")
            except OSError as exc:
                raise OutputError(f"series '{self._shown}': cannot append to it: {exc}") from exc
            self._csv = csv.writer(self._fh, lineterminator="\n")
            return
        if exists and not overwrite:
            raise OutputError(
                f"series '{self._shown}' already exists; remove it, choose another path or pass "
                f"overwrite=True (--overwrite) to replace it"
            )
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = open(self.path, "w", newline="", encoding="utf-8")
        except OSError as exc:
            raise OutputError(
                f"series '{self._shown}': cannot create it: {exc}; check the path and permissions"
            ) from exc
        self._csv = csv.writer(self._fh, lineterminator="\n")
        self._row(list(self.columns))

    @property
    def _shown(self) -> str:
        """The path as named in messages (at most ~200 characters)."""
        return clip(str(self.path))

    def _exists(self) -> bool:
        """Whether the file exists; a path the file system refuses (a name longer than 255 bytes, a
        symbolic-link loop) is an OutputError naming it."""
        try:
            return self.path.exists()
        except OSError as exc:
            raise OutputError(
                f"series '{self._shown}': the file system refuses this path ({exc.strerror or exc}); a file "
                "name is at most 255 bytes: use shorter stage and boundary names"
            ) from None

    def _widen(self, cols: list[str]) -> list[str]:
        """Append mode: the existing header, plus ``cols`` it lacks (the file is rewritten with the
        wider header and empty cells in its rows, atomically)."""
        header, body = _read_rows(self.path)
        if not header:
            raise OutputError(f"series '{self._shown}' has no header row; it was not written by SeriesWriter")
        extra = [c for c in cols if c not in header]
        if extra:
            from .base import atomic_write_text

            width = len(header) + len(extra)
            atomic_write_text(
                self.path, _csv_text([header + extra] + [r + [""] * (width - len(r)) for r in body])
            )
        return header + extra

    def _row(self, cells: list[str]) -> None:
        assert self._fh is not None
        try:
            self._csv.writerow(cells)
            self._fh.flush()
        except OSError as exc:
            raise OutputError(f"series '{self._shown}': write failed: {exc}; check free disk space") from exc

    def append(self, values: dict[str, object]) -> None:
        """Write one row; ``values`` maps column names to numbers or strings (missing → empty cell)."""
        if self._fh is None:
            raise OutputError(
                f"series '{self._shown}' is closed; create a new SeriesWriter to write more rows"
            )
        unknown = [k for k in values if k not in self._index]
        if unknown:
            raise OutputError(
                f"series '{self._shown}': unknown column(s) {clip(', '.join(map(repr, unknown)))}; "
                f"the columns are {clip(', '.join(self.columns), 1000)}"
            )
        cells = [""] * len(self.columns)
        for k, v in values.items():
            cells[self._index[k]] = _cell(k, v, self.path)
        self._row(cells)
        self.n_rows += 1

    def close(self) -> None:
        """Close the file; further calls do nothing."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    @property
    def closed(self) -> bool:
        return self._fh is None

    def __enter__(self) -> SeriesWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _convert(cells: list[str]) -> np.ndarray:
    try:
        return np.array([int(c) for c in cells], dtype=np.int64)
    except (ValueError, OverflowError):
        pass
    try:
        return np.array([float(c) if c != "" else math.nan for c in cells], dtype=np.float64)
    except ValueError:
        return np.array(cells, dtype=str)


def _read_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise OutputError(f"cannot read series '{path}': {exc}; check the path") from exc
    if not rows:
        return [], []
    return rows[0], rows[1:]


def _csv_text(rows: list[list[str]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    for r in rows:
        w.writerow(r)
    return buf.getvalue()


def _step_of(row: list[str], col: int) -> float:
    try:
        return float(row[col])
    except (IndexError, ValueError):
        return math.inf  # a damaged row (a kill mid-write): dropped with the later rows


def truncate_series(path: Path | str, last_step: int, *, inclusive: bool = True) -> int:
    """Keep the header and the rows of ``path`` whose ``step`` is at most ``last_step`` (below it
    if not ``inclusive``), in order, dropping the others and a damaged last line; rewritten
    atomically only if something is dropped. Returns the number of rows kept. A file without a
    ``step`` column is left alone (all rows kept)."""
    path = Path(path)
    header, body = _read_rows(path)
    if "step" not in header:
        return len(body)
    col = header.index("step")
    limit = last_step if inclusive else last_step - 0.5
    keep = [r for r in body if len(r) == len(header) and _step_of(r, col) <= limit]
    if len(keep) != len(body):
        from .base import atomic_write_text

        atomic_write_text(path, _csv_text([header] + keep))
    return len(keep)


def series_rows(path: Path | str) -> list[dict[str, float]]:
    """The rows of a series CSV as ``{column: float}`` (empty cells left out), e.g. to continue the
    in-memory series of a resumed run. Non-numeric cells are left out."""
    header, body = _read_rows(Path(path))
    out = []
    for r in body:
        row: dict[str, float] = {}
        for name, cell in zip(header, r, strict=False):
            if cell == "":
                continue
            try:
                row[name] = float(cell)
            except ValueError:
                continue
        out.append(row)
    return out


def read_series(path: Path | str) -> dict[str, np.ndarray]:
    """Read a CSV written by :class:`SeriesWriter`: ``{column: values}`` (see the module doc for dtypes)."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise OutputError(f"cannot read series '{path}': {exc}; check the path") from exc
    if not rows:
        raise OutputError(f"series '{path}' is empty (no header row); it was not written by SeriesWriter")
    header, body = rows[0], rows[1:]
    bad = [i + 2 for i, r in enumerate(body) if len(r) != len(header)]
    if bad:
        raise OutputError(
            f"series '{path}': row(s) at line(s) {bad[:5]} have a different number of cells than the "
            f"header ({len(header)}); the file is damaged or not a SeriesWriter file"
        )
    return {name: _convert([r[i] for r in body]) for i, name in enumerate(header)}
