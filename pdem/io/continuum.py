"""Coarse-grained continuum fields written beside the grains (deck ``[output.continuum.<name>]``).

Each named grid of the deck gets one time series of the fields of :mod:`pdem.fields` (density,
solid fraction, velocity, stress, strain rate, fabric, …) on a regular grid, written at the
particle snapshots' steps (or at its own ``every_steps``), so that ParaView shows the grains and
the fields in one time line.

Files written in the output directory
-------------------------------------
``continuum_<name>.h5`` (one rank) or ``continuum_<name>.rRRRR.h5`` (one per rank)
    root attributes: the writer's ``metadata`` (strings), ``lo``, ``hi`` (3,) [m] and ``counts``
    (3,) of the whole grid (the centres of ``counts`` equal cells of the box ``lo``–``hi``),
    ``kernel`` ("gaussian" or "lucy"), ``width`` [m] (the Gaussian's standard deviation or Lucy's
    cut-off radius), ``cutoff`` (Gaussian, in widths), ``rank`` and ``n_ranks``.
    ``/batches/BBBBBB``: the frames written together (see below), stacked: one dataset per
    quantity, float64, shape (k, nz, ny, planes) for a scalar, (…, 3) for a vector, (…, 9) for a
    tensor (row-major: component 3a + b is T_ab), each frame **in ParaView's order, x fastest**;
    attributes ``numbers`` (k,) (the frames' numbers, counted over the run), ``table`` (k, 6): per
    frame the time [s], the time of its first sample [s] (``since``), the step, the number of
    samples averaged into it (1 without ``average_every_steps``), the block's first x-plane and its
    number of x-planes; and ``stages``, the frames' stage names (a JSON list).
    :func:`read_continuum` gives every frame back in pdem's (nx, ny, nz, …) order.
    On one rank a block is the whole grid. On several ranks rank k holds the slab of x-planes
    ``nx k / n`` to ``nx (k + 1) / n`` (integer division) plus the next slab's first plane, so the
    slabs drawn side by side leave no gap (a rank with no plane writes frames without datasets).
``continuum_<name>.xdmf``
    the index (rank 0): a ``Temporal`` collection, per frame a ``Spatial`` collection of one
    ``3DCoRectMesh`` grid per block (``ORIGIN_DXDYDZ``, given in XDMF's z, y, x order), with every
    quantity as a node ``Attribute`` (``Scalar``, ``Vector`` or ``Tensor``: a ``HyperSlab`` of the
    frame's row in its batch). ParaView opens it as a multiblock of image data, one dataset per time
    step, at the times of ``particles.xdmf``.

Frames are held in memory and written together, one batch, with the index, when 2 s of wall time
have passed since the last write (``FLUSH_SECONDS``: one HDF5 opening and a few objects for many
frames, where an object costs ~0.15 ms to make; the index rewritten once), before every checkpoint,
and when the run ends or fails. A run killed outright loses at most the frames after its last
checkpoint, which a resume from that checkpoint writes again.

The values are bitwise the same on any rank count (:meth:`pdem.fields.CoarseGraining.block`).
Continuing a run into its own directory (``append_after``) drops the frames after the checkpoint
from every file of this name (of any earlier rank count; a batch across the checkpoint is rewritten
with the frames before it) and rebuilds the index, as
:mod:`pdem.io.hdf5` does for the grains. The files are closed between writes and the index is
rewritten atomically, so a run killed at any moment leaves files that read back.
"""

from __future__ import annotations

import json
import math
import re
import time as _time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..errors import OutputError
from ..fields import CoarseGraining, CylindricalGrid, GaussianKernel, Grid, LucyKernel
from .base import atomic_write_text, piece_name
from .journal import discard_frame

__all__ = ["ContinuumWriter", "QUANTITIES", "read_continuum", "continuum_files", "where_of"]

#: the quantities a grid may write, and their number of components (1, 3 or 9)
QUANTITIES: dict[str, int] = {
    "density": 1,
    "solid_fraction": 1,
    "number_density": 1,
    "momentum": 3,
    "velocity": 3,
    "kinetic_stress": 9,
    "contact_stress": 9,
    "stress": 9,
    "velocity_gradient": 9,
    "strain_rate": 9,
    "contact_density": 1,
    "coordination": 1,
    "fabric": 9,
    "wall_force_density": 3,
}
_XDMF_TYPE = {1: "Scalar", 3: "Vector", 9: "Tensor"}
#: the held frames are written when this much wall time [s] has passed since the last write
FLUSH_SECONDS = 2.0


def continuum_files(directory: Path, name: str) -> list[Path]:
    """Every HDF5 file of grid ``name`` in ``directory`` (the one-rank file and every rank's)."""
    pat = re.compile(rf"continuum_{re.escape(name)}(\.r\d+)?\.h5")
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return sorted(p for p in directory.iterdir() if pat.fullmatch(p.name))


def _batch_table(g: h5py.Group) -> tuple[np.ndarray, list[str], np.ndarray]:
    """A batch group's (table, stages, frame numbers): table rows are [time, since, step, samples,
    first plane, planes]."""
    stages = g.attrs["stages"]
    stages = json.loads(stages.decode() if isinstance(stages, bytes) else str(stages))
    return np.asarray(g.attrs["table"], dtype=float).reshape(-1, 6), stages, np.asarray(g.attrs["numbers"])


def _keep_until(directory: Path, f: h5py.File, step: int) -> None:
    """Drop the frames after ``step`` from an open file: whole batches after it are held by a
    resume's journal (:func:`pdem.io.journal.discard_frame`); a batch across it (none is, when the
    checkpoint was written by pdem, which writes the frames held before a checkpoint) is rewritten
    with the rows kept."""
    batches = f.get("batches")
    if batches is None:
        return
    free = max((int(k) for k in batches), default=-1) + 1
    for key in sorted(batches):
        g = batches[key]
        table, stages, numbers = _batch_table(g)
        keep = table[:, 2] <= step
        if keep.all():
            continue
        if keep.any():
            new = batches.create_group(f"{free:06d}")
            free += 1
            for name, value in g.attrs.items():
                new.attrs[name] = value
            new.attrs["numbers"] = numbers[keep]
            new.attrs["table"] = table[keep]
            new.attrs["stages"] = json.dumps([s for s, k in zip(stages, keep, strict=True) if k])
            for q in g:
                new.create_dataset(q, data=g[q][np.flatnonzero(keep)])
        discard_frame(directory, batches, key)  # held while the resume is undecided


def _to_file(arr: np.ndarray, kind: str = "box") -> np.ndarray:
    """A block in pdem's order → the file's, with k components: a grid's (planes, n1, n2, …) →
    ParaView's (n2, n1, planes, k), first axis fastest (a cylinder's θ column 0 repeated after the
    last, which closes the ring in ParaView); a point list's (n, …) → (n, k)."""
    if kind == "points":
        k = int(np.prod(arr.shape[1:])) if arr.ndim > 1 else 1
        a = arr.reshape(arr.shape[0], k)
        return np.ascontiguousarray(a if k > 1 else a[:, 0])
    k = int(np.prod(arr.shape[3:])) if arr.ndim > 3 else 1
    a = arr.reshape(*arr.shape[:3], k).transpose(2, 1, 0, 3)
    if kind == "cylinder":
        a = np.concatenate([a, a[:, :1]], axis=1)
    return np.ascontiguousarray(a if k > 1 else a[..., 0])


def _from_file(arr: np.ndarray, k: int, kind: str = "box") -> np.ndarray:
    tail = () if k == 1 else (3,) if k == 3 else (3, 3)
    if kind == "points":
        return np.ascontiguousarray(arr.reshape(arr.shape[0], *tail))
    a = arr if k > 1 else arr[..., None]
    if kind == "cylinder":
        a = a[:, :-1]
    a = a.transpose(2, 1, 0, 3)
    return np.ascontiguousarray(a.reshape(*a.shape[:3], *tail))


def where_of(spec: Any) -> Grid | CylindricalGrid | np.ndarray:
    """Where a ``[output.continuum.<name>]`` table puts its fields: a :class:`~pdem.fields.Grid`
    (``type = "box"``), a :class:`~pdem.fields.CylindricalGrid` (``"cylinder"``) or an (m, 3) array
    (``"points"``)."""
    kind = getattr(spec, "type", "box")
    if kind == "cylinder":
        inner = spec.inner_radius or 0.0
        return CylindricalGrid(spec.base_center, spec.radius, spec.height, spec.counts, inner)
    if kind == "points":
        return np.ascontiguousarray(np.asarray(spec.points, dtype=float).reshape(-1, 3))
    return Grid(spec.lo, spec.hi, spec.counts)


def _geometry(where, kind: str, first: int, planes: int) -> np.ndarray:
    """The nodes of a block in the file's order: a cylinder's (nz, nθ + 1, planes, 3), a point
    list's (planes, 3)."""
    if kind == "points":
        return np.ascontiguousarray(where[first : first + planes])
    pts = where.points().reshape(*where.counts, 3)[first : first + planes]
    return _to_file(pts, kind)


class ContinuumWriter:
    """Writes the fields of one ``[output.continuum.<name>]`` grid (collective on ``comm``).

    ``spec``: the deck's table (``lo``, ``hi``, ``counts``, ``kernel``, ``width``, ``cutoff``,
    ``quantities``, ``walls``, ``every_steps``, ``average_every_steps``); ``metadata``: strings stored
    in the files; ``append_after``: ``(step, time)`` to continue the output of a resumed run.
    The kernel's default width, one mean grain diameter, is fixed at the first frame."""

    def __init__(
        self,
        directory: Path | str,
        name: str,
        spec: Any,
        *,
        comm: Any,
        metadata: dict[str, str] | None = None,
        append_after: tuple[int, float] | None = None,
    ) -> None:
        self.directory = Path(directory)
        self.name = name
        self.spec = spec
        self.comm = comm
        self.rank = int(comm.rank)
        self.size = int(comm.size)
        self.metadata = dict(metadata or {})
        self.kind = getattr(spec, "type", "box")
        self.grid = where_of(spec)
        #: points per plane of the first axis (a point list: 1, its blocks are runs of points)
        self.plane = 1 if self.kind == "points" else self.grid.counts[1] * self.grid.counts[2]
        self.quantities = list(spec.quantities) if spec.quantities else list(QUANTITIES)
        self.cg: CoarseGraining | None = None
        self.width: float | None = spec.width
        self.frame_count = 0
        self.last_step: int | None = None
        self._sum: dict[str, np.ndarray] | None = None
        self._samples = 0
        self._t_first = math.nan
        self._last_sample: int | None = None
        self.index_path = self.directory / f"continuum_{name}.xdmf"
        self.path = (
            self.directory / f"continuum_{name}.h5"
            if self.size == 1
            else self.directory / f"continuum_{name}.{piece_name(self.rank)}.h5"
        )
        self._headers: list[dict[str, Any]] = []  # rank 0: each frame's blocks, for the index
        self._pending: list = []  # frames computed, not yet written
        self._unplaced: list[dict[str, Any]] = []  # rank 0: their headers
        self._batch = 0  # the next batch's number
        self._flushed = _time.monotonic()
        #: frames are written to disk together at most this often [s of wall time], and at close
        self.flush_seconds = FLUSH_SECONDS
        self._collective(lambda: self._start(append_after))

    # ------------------------------------------------------------------ errors on every rank
    def _collective(self, action) -> Any:
        """Run ``action`` here; if it fails on any rank, raise the same OutputError on every rank."""
        err = None
        out = None
        try:
            out = action()
        except (OSError, ValueError, KeyError, RuntimeError) as exc:
            err = f"{type(exc).__name__}: {exc}"
        errs = self.comm.allgather(err)
        bad = [(k, e) for k, e in enumerate(errs) if e is not None]
        if bad:
            k, e = bad[0]
            raise OutputError(
                f"continuum fields '{self.name}': writing {self.directory} failed on rank {k}: {e}; "
                "check the output directory's space and permissions"
            )
        return out

    def _start(self, append_after: tuple[int, float] | None) -> None:
        if append_after is None:
            if self.path.exists():
                raise OutputError(f"{self.path} exists; pdem does not overwrite it")
            return
        step = int(append_after[0])
        if self.rank == 0:  # keep the frames up to the checkpoint in every file of this name
            for p in continuum_files(self.directory, self.name):
                with h5py.File(p, "a") as f:
                    _keep_until(self.directory, f, step)
        self.comm.barrier()
        kept = self._read_headers() if self.rank == 0 else None
        kept, self._batch = self.comm.bcast(kept, root=0)
        self._headers = kept if self.rank == 0 else []
        self.frame_count = max((h["number"] for h in kept), default=-1) + 1
        self.last_step = kept[-1]["step"] if kept else None
        if self.rank == 0:
            self._write_index()

    def _read_headers(self) -> tuple[list[dict[str, Any]], int]:
        """Rank 0: every frame on disk (by number), with its blocks, from all files of this name;
        and the first batch number free in every file."""
        frames: dict[int, dict[str, Any]] = {}
        free = 0
        for p in continuum_files(self.directory, self.name):
            with h5py.File(p, "r") as f:
                for key, g in f.get("batches", {}).items():
                    free = max(free, int(key) + 1)
                    table, stages, numbers = _batch_table(g)
                    names = sorted(k for k in g.keys())
                    for row, (number, info, stage) in enumerate(zip(numbers, table, stages, strict=True)):
                        h = frames.setdefault(
                            int(number),
                            {"number": int(number), "time": float(info[0]), "step": int(info[2]),
                             "stage": stage, "blocks": []},
                        )  # fmt: skip
                        if int(info[5]) > 0:
                            h["blocks"].append((p.name, int(info[4]), int(info[5]), names, int(key), row,
                                                len(numbers)))  # fmt: skip
        return [frames[k] for k in sorted(frames)], free

    # ------------------------------------------------------------------ the fields
    def _coarse_graining(self, sim) -> CoarseGraining | None:
        """The grid's coarse graining; None while the default width waits for grains (collective)."""
        if self.cg is None:
            if self.width is None:  # one mean grain diameter, the same bits on any rank count
                from ..parallel.exact import exact_sum, global_count

                p = sim.own_particles()
                n = global_count(self.comm, len(p["r"]))
                total = exact_sum(self.comm, 2.0 * np.asarray(p["r"], dtype=float))
                if n == 0:  # e.g. before a later stage's source: no frame until there are grains
                    return None
                self.width = total / n
            kern = (
                GaussianKernel(self.width, self.spec.cutoff)
                if self.spec.kernel == "gaussian"
                else LucyKernel(self.width)
            )
            computed = list(self.quantities)
            if self._weighted():  # the mass-weighted mean velocity needs the density and momentum
                computed += [q for q in ("density", "momentum") if q not in computed]
            self.cg = CoarseGraining(kern, self.grid, walls=self.spec.walls, quantities=computed)
        return self.cg

    def _weighted(self) -> bool:
        """Frames are time averages that include the velocity (averaged by mass)."""
        return bool(self.spec.average_every_steps) and "velocity" in self.quantities

    def _block(self, sim, extra: tuple[str, ...] = ()) -> tuple[dict[str, np.ndarray], int]:
        fields, first = self._coarse_graining(sim).block(sim)
        arrays = fields.arrays()
        out = {q: arrays[q] for q in self.quantities}
        out.update({f"_{q}": arrays[q] for q in extra})
        return out, first

    def sample(self, sim) -> None:
        """Add the current state to the running time average (collective; ``average_every_steps``)."""
        step = int(sim.step_count)
        if self._last_sample == step or self._coarse_graining(sim) is None:
            return
        # the mean velocity is the mean momentum over the mean density (mass-weighted, as MercuryCG
        # averages it): a mean of each sample's velocity would count a node's empty samples as at
        # rest, and under an intermittent flow (an orifice) understate the flux
        block, self._first = self._block(sim, ("density", "momentum") if self._weighted() else ())
        if self._sum is None:
            self._sum = {k: v.copy() for k, v in block.items()}
            self._t_first = float(sim.time)
        else:
            for k, v in block.items():
                self._sum[k] += v
        self._samples += 1
        self._last_sample = step

    def write(self, sim, stage: str) -> None:
        """One frame at the current step (collective): the fields now, or with
        ``average_every_steps`` the mean of the samples since the previous frame (this step's
        included)."""
        step = int(sim.step_count)
        if self.last_step == step or self._coarse_graining(sim) is None:
            return
        time = float(sim.time)
        if self.spec.average_every_steps:
            self.sample(sim)
            block = {k: v / self._samples for k, v in self._sum.items() if not k.startswith("_")}
            if "_momentum" in self._sum:
                rho, mom = self._sum["_density"], self._sum["_momentum"]
                held = (rho > 0.0)[..., None]
                block["velocity"] = np.where(held, mom / np.where(held, rho[..., None], 1.0), 0.0)
            first, samples, since = self._first, self._samples, self._t_first
            self._sum, self._samples, self._last_sample = None, 0, step
        else:
            block, first = self._block(sim)
            samples, since = 1, time
        planes = next(iter(block.values())).shape[0] if block else 0
        number = self.frame_count
        self._pending.append((number, block, first, planes, (samples, since, time, step, stage)))
        # rank 0's clock decides, for every rank alike, whether the frames held are written now
        due = _time.monotonic() - self._flushed >= self.flush_seconds
        # the index names a block by its first plane (``first`` is a point index)
        blocks = self.comm.allgather((self.path.name, first // self.plane, planes, due))
        if self.rank == 0:  # the blocks' batch and row are known when the frames are written
            self._headers.append({
                "number": number, "time": time, "step": step, "stage": stage,
                "blocks": [(n, f0, k, sorted(self.quantities)) for n, f0, k, _ in blocks if k > 0],
            })  # fmt: skip
            self._unplaced.append(self._headers[-1])
        self.frame_count += 1
        self.last_step = step
        if blocks[0][3]:
            self.flush()

    def flush(self) -> None:
        """Write the frames held to this rank's file, as one batch, and, on rank 0, the index
        (collective; a failure on any rank raises the same OutputError on every rank)."""
        pending, self._pending = self._pending, []
        batch = self._batch
        self._collective(lambda: self._write_batch(batch, pending))
        self._batch += 1 if pending else 0
        if self.rank == 0:
            self._place(batch, len(pending))
        self._collective(self._write_index if self.rank == 0 else (lambda: None))
        self._flushed = _time.monotonic()

    def _place(self, batch: int, count: int) -> None:
        """Rank 0: the frames just written are rows 0… of ``batch`` in every rank's file."""
        for row, h in enumerate(self._unplaced):
            h["blocks"] = [(*b[:4], batch, row, count) for b in h["blocks"]]
        self._unplaced = []

    def _write_batch(self, batch: int, pending: list) -> None:
        """``pending`` frames as group ``/batches/<batch>``: per quantity one dataset of the frames
        stacked, (k, nz, ny, planes[, components]); attributes ``numbers`` (the frame numbers),
        ``table`` (k × [time, since, step, samples, first plane, planes]) and ``stages``. One group
        and a few datasets per batch rather than per frame: an HDF5 object costs ~0.15 ms to make."""
        if not pending:
            return
        self.directory.mkdir(parents=True, exist_ok=True)
        plane = self.plane
        with h5py.File(self.path, "a") as f:
            if "kernel" not in f.attrs:  # the file's first batch (every type writes the kernel)
                for k, v in self.metadata.items():
                    f.attrs[k] = v
                f.attrs["type"] = self.kind
                if self.kind == "box":
                    f.attrs["lo"] = self.grid.lo
                    f.attrs["hi"] = self.grid.hi
                if self.kind == "cylinder":
                    f.attrs["base_center"] = self.grid.base_center
                    f.attrs["radius"] = self.grid.radius
                    f.attrs["height"] = self.grid.height
                    f.attrs["inner_radius"] = self.grid.inner_radius
                if self.kind == "points":
                    f.attrs["count"] = np.int64(len(self.grid))
                else:
                    f.attrs["counts"] = np.array(self.grid.counts, dtype=np.int64)
                f.attrs["kernel"] = self.spec.kernel
                f.attrs["width"] = float(self.width)
                f.attrs["cutoff"] = float(self.spec.cutoff)
                f.attrs["rank"] = self.rank
                f.attrs["n_ranks"] = self.size
            g = f.require_group("batches").create_group(f"{batch:06d}")
            table = [[when[2], when[1], when[3], when[0], first // plane, planes]
                     for _, _, first, planes, when in pending]  # fmt: skip
            g.attrs["numbers"] = np.array([fr[0] for fr in pending], dtype=np.int64)
            g.attrs["table"] = np.array(table, dtype=np.float64)
            g.attrs["stages"] = json.dumps([fr[4][4] for fr in pending])
            if pending[0][3]:
                for q in pending[0][1]:
                    g.create_dataset(q, data=np.stack([_to_file(fr[1][q], self.kind) for fr in pending]))
                first, planes = pending[0][2] // plane, pending[0][3]
                geo = f"{first}_{planes}"
                if self.kind != "box" and geo not in f.require_group("geometry"):
                    f["geometry"].create_dataset(geo, data=_geometry(self.grid, self.kind, first, planes))
            f.flush()

    # ------------------------------------------------------------------ the index
    def _write_index(self) -> None:
        """Rewrite the index (rank 0): every frame's grid is serialized once and kept, so a rewrite
        costs the file's bytes, not the building of every frame again."""
        head = (
            '<?xml version="1.0" ?>\n<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>\n<Xdmf Version="3.0">\n  <Domain>\n'
            '    <Information Name="metadata">pdem continuum fields</Information>\n'
            f'    <Grid Name="continuum_{self.name}" GridType="Collection" CollectionType="Temporal">\n'
        )
        frames = []
        for h in self._headers:
            if h["blocks"]:
                if "xml" not in h:
                    h["xml"] = self._frame_xml(h)
                frames.append(h["xml"])
        atomic_write_text(self.index_path, head + "".join(frames) + "    </Grid>\n  </Domain>\n</Xdmf>\n")

    def _frame_xml(self, h: dict[str, Any]) -> str:
        """One frame of the index: a spatial collection of the blocks' grids (a box's
        3DCoRectMesh, a cylinder's 3DSMesh, a point list's Polyvertex)."""
        frame = ET.Element("Grid", Name=f"frame_{h['number']:06d}", GridType="Collection",
                           CollectionType="Spatial")  # fmt: skip
        ET.SubElement(frame, "Time", Value=repr(float(h["time"])))
        ET.SubElement(frame, "Information", Name="step", Value=str(h["step"]))
        ET.SubElement(frame, "Information", Name="stage", Value=str(h["stage"]))
        three = {"Dimensions": "3", "Format": "XML", "NumberType": "Float", "Precision": "8"}
        for fname, first, planes, names, batch, row, count in h["blocks"]:
            part = re.fullmatch(r".*\.(r\d+)\.h5", fname)
            grid = ET.SubElement(frame, "Grid", Name=part.group(1) if part else "grid", GridType="Uniform")
            if self.kind == "points":
                dims = f"{planes}"
                ET.SubElement(grid, "Topology", TopologyType="Polyvertex", NumberOfElements=dims,
                              NodesPerElement="1")  # fmt: skip
            else:
                _, n1, n2 = self.grid.counts
                n1 += 1 if self.kind == "cylinder" else 0  # the ring closed: θ column 0 repeated
                dims = f"{n2} {n1} {planes}"
                topology = "3DCoRectMesh" if self.kind == "box" else "3DSMesh"
                ET.SubElement(grid, "Topology", TopologyType=topology, Dimensions=dims)
            if self.kind == "box":
                dx, dy, dz = (float(v) for v in self.grid.spacing)
                x0, y0, z0 = (float(v) for v in self.grid.lo + 0.5 * self.grid.spacing)
                geo = ET.SubElement(grid, "Geometry", GeometryType="ORIGIN_DXDYDZ")
                o = ET.SubElement(geo, "DataItem", three)
                o.text = f"{z0!r} {y0!r} {x0 + first * dx!r}"
                d = ET.SubElement(geo, "DataItem", three)
                d.text = f"{dz!r} {dy!r} {dx!r}"
            else:
                geo = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
                item = ET.SubElement(geo, "DataItem", Dimensions=f"{dims} 3", Format="HDF",
                                     NumberType="Float", Precision="8")  # fmt: skip
                item.text = f"{fname}:/geometry/{first}_{planes}"
            space = len(dims.split())
            for q in names:
                k = QUANTITIES[q]
                att = ET.SubElement(grid, "Attribute", Name=q, AttributeType=_XDMF_TYPE[k], Center="Node")
                shape = dims if k == 1 else f"{dims} {k}"
                rank = space + 1 if k == 1 else space + 2
                slab = ET.SubElement(att, "DataItem", ItemType="HyperSlab", Dimensions=shape,
                                     Type="HyperSlab")  # fmt: skip
                sel = ET.SubElement(slab, "DataItem", Dimensions=f"3 {rank}", Format="XML")
                start = " ".join(["0"] * (rank - 1))
                sel.text = f"{row} {start}  {' '.join(['1'] * rank)}  1 {shape}"
                item = ET.SubElement(slab, "DataItem", Dimensions=f"{count} {shape}", Format="HDF",
                                     NumberType="Float", Precision="8")  # fmt: skip
                item.text = f"{fname}:/batches/{batch:06d}/{q}"
        ET.indent(frame, space="  ", level=3)
        return "      " + ET.tostring(frame, encoding="unicode").rstrip() + "\n"

    def close(self) -> None:
        """Write what is held, without a collective call (a rank may close alone on a failure):
        this rank's frames to its file, on rank 0 the index of every frame it heard of."""
        pending, self._pending = self._pending, []
        self._write_batch(self._batch, pending)
        if self.rank == 0:
            self._place(self._batch, len(pending))
        self._batch += 1 if pending else 0
        if self.rank == 0 and self._headers:
            self._write_index()


def _where_in(f: h5py.File, files: list[Path]) -> tuple[str, Any]:
    """The kind and the nodes' description of a grid's files (``f`` one of them): a box's or a
    cylinder's grid, or a point list's (m, 3) points gathered from every file's blocks."""
    kind = f.attrs.get("type", "box")
    kind = kind.decode() if isinstance(kind, bytes) else str(kind)
    if kind == "cylinder":
        a = f.attrs
        return kind, CylindricalGrid(a["base_center"], float(a["radius"]), float(a["height"]), a["counts"],
                                     float(a["inner_radius"]))  # fmt: skip
    if kind == "points":
        pts = np.full((int(f.attrs["count"]), 3), np.nan)
        for p in files:
            with h5py.File(p, "r") as g:
                for key, ds in g.get("geometry", {}).items():
                    first, planes = (int(v) for v in key.split("_"))
                    pts[first : first + planes] = ds[()]
        return kind, pts
    return kind, Grid(f.attrs["lo"], f.attrs["hi"], f.attrs["counts"])


def read_continuum(directory: Path | str, name: str) -> list[dict[str, Any]]:
    """Every frame of grid ``name`` in ``directory``, its blocks joined: a list (in frame order) of
    dicts with ``time``, ``step``, ``stage``, ``samples`` and each quantity in pdem's order (a grid's
    (n0, n1, n2, …): (nx, ny, nz) or a cylinder's (nr, nθ, nz); a point list's (m, …)), plus
    ``points``, the nodes' positions (…, 3) [m], and ``where``, the :class:`~pdem.fields.Grid`,
    :class:`~pdem.fields.CylindricalGrid` or (m, 3) points."""
    files = continuum_files(Path(directory), name)
    if not files:
        raise OutputError(f"no continuum_{name}*.h5 in {directory}")
    out: dict[int, dict[str, Any]] = {}
    kind, where = None, None
    for p in files:
        with h5py.File(p, "r") as f:
            if where is None and "batches" in f:
                kind, where = _where_in(f, files)
            for _key, g in f.get("batches", {}).items():
                table, stages, numbers = _batch_table(g)
                for row, (number, info, stage) in enumerate(zip(numbers, table, stages, strict=True)):
                    head = {"time": float(info[0]), "since": float(info[1]), "step": int(info[2]),
                            "stage": stage, "samples": int(info[3])}  # fmt: skip
                    fr = out.setdefault(int(number), head)
                    first, planes = int(info[4]), int(info[5])
                    for q in g:
                        k = QUANTITIES[q]
                        arr = _from_file(g[q][row], k, kind)
                        if q not in fr:
                            shape = (len(where),) if kind == "points" else where.counts
                            fr[q] = np.full((*shape, *arr.shape[len(shape) :]), np.nan)
                        fr[q][first : first + planes] = arr
    if where is None:
        return []
    pts = where if kind == "points" else where.points().reshape(*where.counts, 3)
    frames = [out[k] for k in sorted(out)]
    for fr in frames:
        fr["points"] = pts
        fr["where"] = where
    return frames
