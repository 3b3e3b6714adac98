"""LAMMPS peer for the column-collapse benchmark (and its restitution calibration).

This module drives the system LAMMPS (Debian's ``lmp``, ``pair_style granular``) on the same scene pdem is
timed on, so that ``tools/bench_vs_lammps.py`` can put both codes side by side in one run:

* :func:`write_lammps_data` turns a packing (centres, diameters, density) into an ``atom_style sphere`` data
  file; :func:`read_packing` reads the shared ``x y z diameter`` text packings.
* :func:`lammps_input` generates the column-collapse input (Hertz--Mindlin from materials, Tsuji damping,
  Coulomb friction, planar walls, gravity, no output while timing, one ``RESULT`` line at the end).
* :func:`run_lammps` runs it on 1 or more MPI ranks and returns LAMMPS's own loop time (the ``run`` only),
  the wall time of the whole process, and the final front position / kinetic energies.
* :func:`measure_restitution` / :func:`calibrate_tsuji`: in LAMMPS 29 Sep 2021 the ``damping tsuji``
  parameter is *not* the realised coefficient of restitution (0.3667 realises e = 0.50), so the damping
  parameter is calibrated with a head-on particle--particle and a particle--floor collision.

The MPI launcher is OpenMPI's ``/usr/bin/mpirun`` (the one LAMMPS is linked against), always called by
absolute path: a pdem venv puts MPICH's ``mpirun`` earlier in ``PATH``.  Override the executables with the
environment variables ``PDEM_LMP`` and ``PDEM_LAMMPS_MPIRUN``.

CLI::

    python tools/lammps_peer.py calibrate [--target 0.5]
    python tools/lammps_peer.py run DATA [--ranks N] [--steps 5000] [--xmax 0.08] [--ymax 0.02] ...

``DATA`` is a LAMMPS data file or a shared ``x y z diameter`` packing (converted on the fly).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

# --------------------------------------------------------------------------------------------------------
# scene constants (see /work/shared/bench/README.md)
# --------------------------------------------------------------------------------------------------------
E_DEFAULT = 5.0e7  # Young's modulus [Pa]
NU_DEFAULT = 0.3  # Poisson ratio
MU_DEFAULT = 0.5  # Coulomb friction (particles and walls)
RHO_DEFAULT = 2500.0  # density [kg/m^3]
DT_DEFAULT = 2.0e-6  # time step [s]
STEPS_DEFAULT = 5000
SKIN_DEFAULT = 1.0e-4  # neighbour skin [m]
GRAVITY_DEFAULT = 9.81  # [m/s^2], along -z
XMAX_DEFAULT = 0.08
YMAX_DEFAULT = 0.02
#: ``damping tsuji`` parameter that realises e = 0.50 in LAMMPS 29 Sep 2021 (measured, see calibrate_tsuji)
EPAR_DEFAULT = 0.3667

LMP_DEFAULT = "/usr/bin/lmp"
MPIRUN_DEFAULT = "/usr/bin/mpirun"

# environment variables of a surrounding MPI launch (MPICH/Hydra, PMI, PMIx, OpenMPI) that must not leak
# into the child OpenMPI job
_MPI_ENV_PREFIXES = ("PMI_", "PMIX_", "HYDRA_", "MPIR_", "MPICH_", "MPIEXEC_", "OMPI_", "ORTE_", "OPAL_")

_LOOP_RE = re.compile(
    r"^Loop time of\s+(\S+)\s+on\s+(\d+)\s+procs\s+for\s+(\d+)\s+steps\s+with\s+(\d+)\s+atoms", re.M
)
_RESULT_RE = re.compile(r"^RESULT\s+(.*)$", re.M)
_COR_RE = re.compile(r"^COR\s+(.*)$", re.M)
_VERSION_RE = re.compile(r"Large-scale Atomic/Molecular Massively Parallel Simulator\s*-\s*(.+)")
# "Section |  min time  |  avg time  | ..." rows of the MPI task timing breakdown; captures the avg column
_BREAKDOWN_RE = re.compile(r"^(Pair|Neigh|Comm|Output|Modify|Other)\s*\|[^|\n]*\|\s*([-+0-9.eE]+)", re.M)


# --------------------------------------------------------------------------------------------------------
# executables
# --------------------------------------------------------------------------------------------------------
def lmp_executable() -> str:
    """Path of the LAMMPS executable (``$PDEM_LMP``, else ``/usr/bin/lmp``, else ``lmp`` on PATH)."""
    env = os.environ.get("PDEM_LMP")
    if env:
        return env
    if os.access(LMP_DEFAULT, os.X_OK):
        return LMP_DEFAULT
    return shutil.which("lmp") or LMP_DEFAULT


def mpirun_executable() -> str:
    """Path of OpenMPI's launcher (``$PDEM_LAMMPS_MPIRUN``, else ``/usr/bin/mpirun``); never from PATH."""
    return os.environ.get("PDEM_LAMMPS_MPIRUN") or MPIRUN_DEFAULT


def lammps_available() -> bool:
    """True if the LAMMPS executable exists and answers ``-h``."""
    return bool(lammps_version())


def mpirun_available() -> bool:
    """True if the OpenMPI launcher used for multi-rank LAMMPS runs exists."""
    return os.access(mpirun_executable(), os.X_OK)


_version_cache: dict[str, str] = {}


def lammps_version() -> str:
    """LAMMPS version string, e.g. ``'29 Sep 2021 - Update 2'``; ``''`` if LAMMPS is not available."""
    exe = lmp_executable()
    if exe in _version_cache:
        return _version_cache[exe]
    version = ""
    if os.access(exe, os.X_OK):
        try:
            proc = subprocess.run(
                [exe, "-h"],
                capture_output=True,
                text=True,
                timeout=30,
                env=_child_env(),
                stdin=subprocess.DEVNULL,
            )
            m = _VERSION_RE.search(proc.stdout)
            if m:
                version = m.group(1).strip()
        except (OSError, subprocess.SubprocessError):
            version = ""
    _version_cache[exe] = version
    return version


def _child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for a LAMMPS/OpenMPI child: no vars of an enclosing MPI job, root allowed, 1 thread."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(_MPI_ENV_PREFIXES)}
    env["OMPI_ALLOW_RUN_AS_ROOT"] = "1"
    env["OMPI_ALLOW_RUN_AS_ROOT_CONFIRM"] = "1"
    env["OMP_NUM_THREADS"] = "1"
    if extra:
        env.update(extra)
    return env


def _command(ranks: int, args: Sequence[str], mpi_args: Sequence[str] = ()) -> list[str]:
    lmp = lmp_executable()
    if ranks < 1:
        raise ValueError(f"ranks must be >= 1, got {ranks}")
    if ranks == 1:
        return [lmp, *args]
    mpirun = mpirun_executable()
    if not os.access(mpirun, os.X_OK):
        raise RuntimeError(f"OpenMPI launcher {mpirun!r} not found (needed for ranks={ranks})")
    return [mpirun, "--allow-run-as-root", "--oversubscribe", "-np", str(ranks), *mpi_args, lmp, *args]


# --------------------------------------------------------------------------------------------------------
# data files
# --------------------------------------------------------------------------------------------------------
def read_packing(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a shared packing (``x y z diameter``, SI, one header line) -> (positions (N, 3), diameters)."""
    arr = np.loadtxt(path, skiprows=1, ndmin=2, dtype=np.float64)
    if arr.shape[1] < 4:
        raise ValueError(f"{path}: expected columns 'x y z diameter', got {arr.shape[1]} columns")
    return np.ascontiguousarray(arr[:, :3]), np.ascontiguousarray(arr[:, 3])


def column_box(
    positions: np.ndarray, diameters: np.ndarray, xmax: float = XMAX_DEFAULT, ymax: float = YMAX_DEFAULT
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Simulation box for the column collapse: x in [0, xmax], y in [0, ymax], z in [0, 1.5 * top + d].

    The box coincides with the walls in x and y (``processors 1 * 1`` then splits the column exactly in half
    in y) and leaves room above the column top so that no sphere is lost through the open ``f`` boundary.
    """
    pos = np.asarray(positions, dtype=np.float64)
    d = np.asarray(diameters, dtype=np.float64)
    top = float(np.max(pos[:, 2] + 0.5 * d)) if len(d) else 1.0e-3
    return (0.0, 0.0, 0.0), (float(xmax), float(ymax), 1.5 * top + float(np.max(d, initial=1.0e-3)))


def write_lammps_data(
    path: str | os.PathLike,
    positions: np.ndarray,
    diameters: np.ndarray,
    density: float | np.ndarray,
    box_lo: Sequence[float],
    box_hi: Sequence[float],
) -> Path:
    """Write an ``atom_style sphere`` LAMMPS data file.

    Atoms lines are ``id type diameter density x y z`` with ids 1..N in the given order, type 1, and every
    float written as its shortest exact (round-trip) repr.  ``density`` is a scalar or one value per
    sphere.  Every centre must lie inside [box_lo, box_hi] (LAMMPS drops atoms outside a fixed boundary).
    """
    pos = np.asarray(positions, dtype=np.float64)
    d = np.asarray(diameters, dtype=np.float64).reshape(-1)
    n = d.shape[0]
    if pos.shape != (n, 3):
        raise ValueError(f"positions must have shape ({n}, 3), got {pos.shape}")
    rho = np.broadcast_to(np.asarray(density, dtype=np.float64), (n,))
    lo = [float(v) for v in box_lo]
    hi = [float(v) for v in box_hi]
    if len(lo) != 3 or len(hi) != 3 or any(h <= low for low, h in zip(lo, hi, strict=True)):
        raise ValueError(f"invalid box {lo} .. {hi}")
    if n and (np.any(pos < np.asarray(lo)) or np.any(pos > np.asarray(hi))):
        raise ValueError("some sphere centres lie outside the box")
    if np.any(d <= 0.0) or np.any(rho <= 0.0):
        raise ValueError("diameters and densities must be positive")

    lines = [
        "LAMMPS data file (atom_style sphere) written by pdem tools/lammps_peer.py",
        "",
        f"{n} atoms",
        "1 atom types",
        "",
        f"{lo[0]!r} {hi[0]!r} xlo xhi",
        f"{lo[1]!r} {hi[1]!r} ylo yhi",
        f"{lo[2]!r} {hi[2]!r} zlo zhi",
        "",
        "Atoms # sphere",
        "",
    ]
    body = [
        f"{i + 1} 1 {di!r} {ri!r} {x!r} {y!r} {z!r}"
        for i, (di, ri, (x, y, z)) in enumerate(zip(d.tolist(), rho.tolist(), pos.tolist(), strict=True))
    ]
    out = Path(path)
    out.write_text("\n".join(lines + body) + "\n")
    return out


def data_from_packing(
    packing_path: str | os.PathLike,
    data_path: str | os.PathLike,
    *,
    density: float = RHO_DEFAULT,
    xmax: float = XMAX_DEFAULT,
    ymax: float = YMAX_DEFAULT,
) -> Path:
    """Convert a shared ``x y z diameter`` packing into a LAMMPS data file for the column-collapse box."""
    pos, d = read_packing(packing_path)
    lo, hi = column_box(pos, d, xmax, ymax)
    return write_lammps_data(data_path, pos, d, density, lo, hi)


def _is_packing_text(path: str | os.PathLike) -> bool:
    with open(path) as fh:
        first = fh.readline().split()
    return first[:4] == ["x", "y", "z", "diameter"]


# --------------------------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------------------------
def _granular_model(E: float, nu: float, mu: float, epar: float) -> str:
    # hertz/material E e nu ; tangential mindlin (k_t from materials) x_gamma_t=1 mu ; tsuji damping.
    # No rolling/twisting resistance.
    return f"hertz/material {E!r} {epar!r} {nu!r} tangential mindlin NULL 1.0 {mu!r} damping tsuji"


def _quote(path: str | os.PathLike) -> str:
    s = str(path)
    if '"' in s:
        raise ValueError(f"path with a double quote is not supported: {s!r}")
    return f'"{s}"'


def lammps_input(
    data_path: str | os.PathLike,
    *,
    steps: int = STEPS_DEFAULT,
    dt: float = DT_DEFAULT,
    E: float = E_DEFAULT,
    nu: float = NU_DEFAULT,
    mu: float = MU_DEFAULT,
    epar: float = EPAR_DEFAULT,
    xmax: float = XMAX_DEFAULT,
    ymax: float = YMAX_DEFAULT,
    skin: float = SKIN_DEFAULT,
    gravity: float = GRAVITY_DEFAULT,
) -> str:
    """LAMMPS input text for the column collapse read from ``data_path`` (an ``atom_style sphere`` data file).

    Walls: floor z = 0, planes x = 0 and x = xmax, y = 0 and y = ymax (``fix wall/gran granular``, same model
    as the pairs).  ``processors 1 * 1`` splits the domain in y only, so on 2 ranks both hold half of the
    column throughout.  Thermo output only at the first and last step; the last line printed is::

        RESULT N <n> steps <steps> front_x <m> KE_trans <J> KE_rot <J> sum_x <m> ... sum_vz <m/s> max_z <m>
    """
    steps = int(steps)
    if steps < 1:
        raise ValueError("steps must be >= 1")
    model = _granular_model(E, nu, mu, epar)
    return f"""\
# pdem tools/lammps_peer.py: column collapse, Hertz-Mindlin (pair_style granular), generated input
# E={E!r} nu={nu!r} mu={mu!r} tsuji epar={epar!r} dt={dt!r} steps={steps} skin={skin!r}
# walls z=0, x=0/{xmax!r}, y=0/{ymax!r}; gravity {gravity!r} along -z; no rolling resistance
units           si
atom_style      sphere
boundary        f f f
newton          off
comm_modify     vel yes
processors      1 * 1
read_data       {_quote(data_path)}

pair_style      granular
pair_coeff      * * {model}
neighbor        {skin!r} bin
neigh_modify    delay 0 every 1 check yes

fix             integrate all nve/sphere
fix             grav all gravity {gravity!r} vector 0 0 -1
fix             wall_z all wall/gran granular {model} zplane 0.0 NULL
fix             wall_x all wall/gran granular {model} xplane 0.0 {xmax!r}
fix             wall_y all wall/gran granular {model} yplane 0.0 {ymax!r}

compute         ke_t all ke
compute         ke_r all erotate/sphere
compute         rmax all reduce max x z
compute         rsum all reduce sum x y z vx vy vz
thermo_style    custom step atoms c_ke_t c_ke_r c_rmax[1] c_rmax[2] c_rsum[3] c_rsum[4]
thermo_modify   norm no format float %.10e
thermo          {steps}
timestep        {dt!r}
run             {steps}

print "RESULT N $(atoms) steps {steps} front_x $(c_rmax[1]:%.12e) KE_trans $(c_ke_t:%.12e) \
KE_rot $(c_ke_r:%.12e) sum_x $(c_rsum[1]:%.12e) sum_y $(c_rsum[2]:%.12e) sum_z $(c_rsum[3]:%.12e) \
sum_vx $(c_rsum[4]:%.12e) sum_vy $(c_rsum[5]:%.12e) sum_vz $(c_rsum[6]:%.12e) max_z $(c_rmax[2]:%.12e)"
"""


def restitution_input(
    epar: float,
    *,
    speed: float = 0.05,
    diameter: float = 1.0e-3,
    density: float = RHO_DEFAULT,
    E: float = E_DEFAULT,
    nu: float = NU_DEFAULT,
    mu: float = MU_DEFAULT,
    dt: float = DT_DEFAULT,
    steps: int = 2000,
) -> str:
    """LAMMPS input measuring the realised restitution for the ``damping tsuji`` parameter ``epar``.

    Two equal spheres collide head-on along x, each at ``speed`` (approach speed 2*speed); a third sphere
    hits the floor z = 0 at 2*speed (same impact speed).  No gravity.  Prints
    ``COR epar <epar> e_pp <e> e_pw <e>`` with e = separation speed / approach speed.
    """
    r = 0.5 * diameter
    gap = 0.2 * diameter  # initial surface gap, closed after 0.1 d / speed
    v_in = 2.0 * speed
    model = _granular_model(E, nu, mu, epar)
    return f"""\
# pdem tools/lammps_peer.py: restitution check for damping tsuji parameter {epar!r}
units           si
atom_style      sphere
atom_modify     map array
boundary        f f f
newton          off
comm_modify     vel yes
region          box block {-20 * r!r} {20 * r!r} {-20 * r!r} {20 * r!r} 0.0 {20 * r!r} units box
create_box      1 box
create_atoms    1 single {-(r + 0.5 * gap)!r} 0.0 {10 * r!r} units box
create_atoms    1 single {(r + 0.5 * gap)!r} 0.0 {10 * r!r} units box
create_atoms    1 single {10 * r!r} 0.0 {(r + 0.5 * gap)!r} units box
set             type 1 diameter {diameter!r}
set             type 1 density {density!r}
velocity        all set 0.0 0.0 0.0 units box
set             atom 1 vx {speed!r}
set             atom 2 vx {-speed!r}
set             atom 3 vz {-v_in!r}
pair_style      granular
pair_coeff      * * {model}
fix             wall_z all wall/gran granular {model} zplane 0.0 NULL
neighbor        {0.1 * diameter!r} bin
fix             integrate all nve/sphere
timestep        {dt!r}
thermo          {int(steps)}
run             {int(steps)}
variable        e_pp equal (vx[2]-vx[1])/{v_in!r}
variable        e_pw equal vz[3]/{v_in!r}
print "COR epar {epar!r} e_pp $(v_e_pp:%.8f) e_pw $(v_e_pw:%.8f)"
"""


# --------------------------------------------------------------------------------------------------------
# running
# --------------------------------------------------------------------------------------------------------
def _tail(text: str, n: int = 40) -> str:
    return "\n".join(text.splitlines()[-n:])


def _run(
    cmd: list[str], workdir: Path, log: Path, timeout: float, env: dict[str, str]
) -> tuple[subprocess.CompletedProcess, float, str]:
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            cmd,
            cwd=workdir,
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
            stdin=subprocess.DEVNULL,
        )
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        logtext = log.read_text(errors="replace") if log.exists() else out
        raise RuntimeError(
            f"LAMMPS timed out after {timeout} s: {' '.join(cmd)}\n--- log tail ---\n{_tail(logtext)}"
        ) from exc
    except OSError as exc:
        raise RuntimeError(f"could not start LAMMPS ({' '.join(cmd)}): {exc}") from exc
    wall = time.perf_counter() - t0
    logtext = log.read_text(errors="replace") if log.exists() else ""
    return proc, wall, logtext


def _fail(msg: str, cmd: list[str], proc: subprocess.CompletedProcess, logtext: str) -> RuntimeError:
    text = logtext or proc.stdout
    err = _tail(proc.stderr, 15)
    return RuntimeError(
        f"{msg} (exit code {proc.returncode}): {' '.join(cmd)}\n--- log tail ---\n{_tail(text)}"
        + (f"\n--- stderr tail ---\n{err}" if err.strip() else "")
    )


def _parse_pairs(s: str) -> dict[str, str]:
    toks = s.split()
    return {toks[i]: toks[i + 1] for i in range(0, len(toks) - 1, 2)}


def parse_loop_time(log_text: str) -> dict:
    """Parse the last ``Loop time of X on P procs for S steps with N atoms`` line (the ``run`` only)."""
    matches = list(_LOOP_RE.finditer(log_text))
    if not matches:
        raise ValueError("no 'Loop time of' line in the LAMMPS log")
    m = matches[-1]
    return dict(
        loop_time=float(m.group(1)), procs=int(m.group(2)), steps=int(m.group(3)), natoms=int(m.group(4))
    )


def parse_result(log_text: str) -> dict:
    """Parse the ``RESULT`` line of a column-collapse run into floats/ints (keys as printed)."""
    matches = list(_RESULT_RE.finditer(log_text))
    if not matches:
        raise ValueError("no RESULT line in the LAMMPS log")
    raw = _parse_pairs(matches[-1].group(1))
    out: dict = {}
    for k, v in raw.items():
        out[k] = int(v) if k in ("N", "steps") else float(v)
    return out


def run_lammps(
    data_path: str | os.PathLike,
    *,
    ranks: int = 1,
    steps: int = STEPS_DEFAULT,
    epar: float = EPAR_DEFAULT,
    dt: float = DT_DEFAULT,
    E: float = E_DEFAULT,
    nu: float = NU_DEFAULT,
    mu: float = MU_DEFAULT,
    xmax: float = XMAX_DEFAULT,
    ymax: float = YMAX_DEFAULT,
    skin: float = SKIN_DEFAULT,
    gravity: float = GRAVITY_DEFAULT,
    workdir: str | os.PathLike | None = None,
    timeout: float = 1800.0,
    mpi_args: Sequence[str] = (),
    keep_log: bool = False,
) -> dict:
    """Run the column collapse in LAMMPS on ``ranks`` MPI ranks and return its timings and final state.

    ``wall_time`` is the whole process (launch, MPI init, reading the data, setup, run, exit) measured here;
    ``loop_time`` is LAMMPS's own ``Loop time of`` figure: the ``run`` only, without setup.  Returned keys:
    ``loop_time, wall_time, natoms, front_x, ke_trans, ke_rot, ranks, steps`` plus ``sum_x, sum_y, sum_z,
    sum_vx, sum_vy, sum_vz, max_z, breakdown`` (LAMMPS's Pair/Neigh/Comm/... seconds, averaged over ranks),
    ``lammps_version``, ``command``, ``workdir`` and, if ``keep_log``, ``log`` (the full text).

    ``workdir`` receives ``in.column_collapse`` and ``log.lammps`` (a temporary directory, removed afterwards,
    if None).  Raises RuntimeError with the tail of the log if LAMMPS fails, times out or prints no result.
    """
    data = Path(data_path).resolve()
    if not data.is_file():
        raise FileNotFoundError(data)
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="pdem_lammps_")
        wd = Path(tmp.name)
    else:
        wd = Path(workdir).resolve()
        wd.mkdir(parents=True, exist_ok=True)
    try:
        inp = wd / "in.column_collapse"
        log = wd / "log.lammps"
        if log.exists():
            log.unlink()
        inp.write_text(
            lammps_input(
                data,
                steps=steps,
                dt=dt,
                E=E,
                nu=nu,
                mu=mu,
                epar=epar,
                xmax=xmax,
                ymax=ymax,
                skin=skin,
                gravity=gravity,
            )
        )
        cmd = _command(ranks, ["-nocite", "-in", inp.name, "-log", log.name], mpi_args)
        proc, wall, logtext = _run(cmd, wd, log, timeout, _child_env())
        if proc.returncode != 0:
            raise _fail("LAMMPS failed", cmd, proc, logtext)
        text = logtext or proc.stdout
        try:
            loop = parse_loop_time(text)
            res = parse_result(text)
        except ValueError as exc:
            raise _fail(f"LAMMPS output incomplete ({exc})", cmd, proc, logtext) from exc
        if loop["procs"] != ranks:
            raise _fail(f"LAMMPS ran on {loop['procs']} procs, expected {ranks}", cmd, proc, logtext)
        breakdown = {m.group(1): float(m.group(2)) for m in _BREAKDOWN_RE.finditer(text)}
        out = dict(
            loop_time=loop["loop_time"],
            wall_time=wall,
            natoms=int(res["N"]),
            front_x=res["front_x"],
            ke_trans=res["KE_trans"],
            ke_rot=res["KE_rot"],
            ranks=int(ranks),
            steps=int(res["steps"]),
        )
        for k in ("sum_x", "sum_y", "sum_z", "sum_vx", "sum_vy", "sum_vz", "max_z"):
            if k in res:
                out[k] = res[k]
        out["breakdown"] = breakdown
        out["lammps_version"] = lammps_version()
        out["command"] = cmd
        out["workdir"] = None if tmp is not None else str(wd)
        if keep_log:
            out["log"] = text
        return out
    finally:
        if tmp is not None:
            tmp.cleanup()


def measure_restitution(
    epar: float,
    *,
    speed: float = 0.05,
    workdir: str | os.PathLike | None = None,
    timeout: float = 120.0,
    **kw,
) -> tuple[float, float]:
    """Realised restitution ``(e_pp, e_pw)`` for the ``damping tsuji`` parameter ``epar``.

    1 mm spheres, rho = 2500, E = 5e7, nu = 0.3, mu = 0.5 (overridable via ``kw``, see
    :func:`restitution_input`); head-on pair at +-``speed`` each, and a sphere hitting the floor at 2*speed.
    """
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="pdem_lammps_cor_")
        wd = Path(tmp.name)
    else:
        wd = Path(workdir).resolve()
        wd.mkdir(parents=True, exist_ok=True)
    try:
        inp = wd / "in.restitution"
        log = wd / "log.restitution"
        if log.exists():
            log.unlink()
        inp.write_text(restitution_input(epar, speed=speed, **kw))
        cmd = _command(1, ["-nocite", "-in", inp.name, "-log", log.name, "-screen", "none"])
        proc, _wall, logtext = _run(cmd, wd, log, timeout, _child_env())
        if proc.returncode != 0:
            raise _fail("LAMMPS restitution check failed", cmd, proc, logtext)
        matches = list(_COR_RE.finditer(logtext))
        if not matches:
            raise _fail("no COR line in the LAMMPS restitution log", cmd, proc, logtext)
        vals = _parse_pairs(matches[-1].group(1))
        return float(vals["e_pp"]), float(vals["e_pw"])
    finally:
        if tmp is not None:
            tmp.cleanup()


def calibrate_tsuji(
    target_e: float = 0.5,
    *,
    tol: float = 1.0e-3,
    use: str = "mean",
    bracket: tuple[float, float] = (0.05, 0.95),
    guess: float = EPAR_DEFAULT,
    max_iter: int = 40,
    verbose: bool = False,
    **kw,
) -> float:
    """``damping tsuji`` parameter whose realised restitution is ``target_e`` to within ``tol`` (in e).

    ``use`` selects the measure matched: ``'pp'`` (particle--particle), ``'pw'`` (particle--wall) or
    ``'mean'`` of both (default; the two differ by ~1e-3 in this build).  The realised e grows monotonically
    with the parameter; a safeguarded secant (Illinois regula falsi) search starts from ``guess`` and its
    neighbour inside ``bracket``.  Extra keywords go to :func:`measure_restitution`.
    """
    if use not in ("pp", "pw", "mean"):
        raise ValueError("use must be 'pp', 'pw' or 'mean'")
    if not 0.0 < target_e < 1.0:
        raise ValueError("target_e must be in (0, 1)")

    def f(p: float) -> float:
        e_pp, e_pw = measure_restitution(p, **kw)
        e = {"pp": e_pp, "pw": e_pw, "mean": 0.5 * (e_pp + e_pw)}[use]
        if verbose:
            print(f"  epar {p:.6f}: e_pp {e_pp:.5f} e_pw {e_pw:.5f} -> {use} {e:.5f}", file=sys.stderr)
        return e - target_e

    lo, hi = float(bracket[0]), float(bracket[1])
    g = min(max(float(guess), lo), hi)
    fg = f(g)
    if abs(fg) <= tol:
        return g
    # second point: a step towards the target (de/dp ~ 1 near the default), clipped into the bracket
    g2 = min(max(g - fg, lo), hi)
    if g2 == g:
        g2 = hi if fg < 0 else lo
    fg2 = f(g2)
    if abs(fg2) <= tol:
        return g2
    # grow a sign-changing bracket from (g, g2): e(p) increases with p
    a, fa, b, fb = (g, fg, g2, fg2) if g < g2 else (g2, fg2, g, fg)
    n = 2
    while fa * fb > 0:
        if n >= max_iter:
            raise RuntimeError(f"calibrate_tsuji: target e={target_e} not bracketed in {bracket}")
        width = b - a
        if fa > 0:  # both above the target: move the lower end down
            if a <= lo:
                raise RuntimeError(f"calibrate_tsuji: e({lo}) already exceeds the target {target_e}")
            b, fb = a, fa
            a = max(lo, a - 2.0 * width)
            fa = f(a)
            if abs(fa) <= tol:
                return a
        else:  # both below the target: move the upper end up
            if b >= hi:
                raise RuntimeError(f"calibrate_tsuji: e({hi}) stays below the target {target_e}")
            a, fa = b, fb
            b = min(hi, b + 2.0 * width)
            fb = f(b)
            if abs(fb) <= tol:
                return b
        n += 1
    # Illinois regula falsi on [a, b] with fa < 0 < fb
    side = 0
    while n < max_iter:
        c = b - fb * (b - a) / (fb - fa)
        if not (a < c < b) or not math.isfinite(c):
            c = 0.5 * (a + b)
        fc = f(c)
        n += 1
        if abs(fc) <= tol:
            return c
        if fc * fb > 0:
            b, fb = c, fc
            if side == 1:
                fa *= 0.5
            side = 1
        else:
            a, fa = c, fc
            if side == -1:
                fb *= 0.5
            side = -1
    raise RuntimeError(f"calibrate_tsuji: no convergence to tol={tol} in {max_iter} evaluations")


# --------------------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="lammps_peer.py", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)

    pc = sub.add_parser("calibrate", help="print the tsuji damping parameter realising the target e")
    pc.add_argument("--target", type=float, default=0.5)
    pc.add_argument("--tol", type=float, default=1.0e-3)
    pc.add_argument("--use", choices=("pp", "pw", "mean"), default="mean")
    pc.add_argument("-v", "--verbose", action="store_true")

    pr = sub.add_parser("run", help="run the column collapse and print the result as JSON")
    pr.add_argument("data", help="LAMMPS data file, or an 'x y z diameter' packing (converted)")
    pr.add_argument("--ranks", type=int, default=1)
    pr.add_argument("--steps", type=int, default=STEPS_DEFAULT)
    pr.add_argument("--epar", type=float, default=EPAR_DEFAULT)
    pr.add_argument("--dt", type=float, default=DT_DEFAULT)
    pr.add_argument("--xmax", type=float, default=XMAX_DEFAULT)
    pr.add_argument("--ymax", type=float, default=YMAX_DEFAULT)
    pr.add_argument("--skin", type=float, default=SKIN_DEFAULT)
    pr.add_argument("--density", type=float, default=RHO_DEFAULT, help="for a packing input only")
    pr.add_argument("--workdir", default=None)
    pr.add_argument("--timeout", type=float, default=1800.0)

    sub.add_parser("version", help="print the LAMMPS version")

    args = ap.parse_args(argv)
    if args.cmd == "version":
        v = lammps_version()
        print(v or "LAMMPS not available")
        return 0 if v else 1
    if not lammps_available():
        print(f"LAMMPS not available ({lmp_executable()})", file=sys.stderr)
        return 2
    if args.cmd == "calibrate":
        epar = calibrate_tsuji(args.target, tol=args.tol, use=args.use, verbose=args.verbose)
        e_pp, e_pw = measure_restitution(epar)
        print(f"{epar:.6g}")
        print(
            f"# target e {args.target}: e_pp {e_pp:.4f} e_pw {e_pw:.4f} (LAMMPS {lammps_version()})",
            file=sys.stderr,
        )
        return 0

    data = Path(args.data)
    if not data.is_file():
        print(f"no such file: {data}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="pdem_lammps_data_") as tmpd:
        if _is_packing_text(data):
            data = data_from_packing(
                data, Path(tmpd) / (data.stem + ".data"), density=args.density, xmax=args.xmax, ymax=args.ymax
            )
        res = run_lammps(
            data,
            ranks=args.ranks,
            steps=args.steps,
            epar=args.epar,
            dt=args.dt,
            xmax=args.xmax,
            ymax=args.ymax,
            skin=args.skin,
            workdir=args.workdir,
            timeout=args.timeout,
        )
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
