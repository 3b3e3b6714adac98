"""Measure pdem's per-rank costs on 1–K ranks, fit a scaling model, and predict to many ranks.

    .venv/bin/python tools/scaling.py measure --ranks 1 2 3 4 5 6 7 8 --n 20000   # writes JSON
    .venv/bin/python tools/scaling.py model out/scaling/measure.json               # fit, check, predict

**measure** runs one scene on each rank count (``mpiexec -n K``, oversubscribed when K exceeds the
cores) and records, per rank: owned grains, ghosts, listed pairs and pairs with a ghost, touching
contacts, neighbour-list rebuilds and migrations, and every MPI call the run makes (a counting
wrapper around the communicator: point-to-point messages and their bytes, collective calls and
their bytes, and the wall time spent inside them, waits included), the CPU time of the force
computation and integration (``time.process_time``, no MPI call inside), and the stepping loop's
wall time. It also checks that the final state is bitwise the one-rank state (a SHA-256 of the
positions and velocities by id). The scene is a periodic box filled with a dense fcc packing of
1 mm spheres (slightly overlapping, random velocities, no gravity): uniform, so that the model's
geometry is exact; ``--scene column`` runs the column collapse of ``tools/bench_vs_lammps.py``
from a packing file instead.

**model** fits the compute cost per rank (seconds per listed pair and per grain, owned or ghost) on
the 1- and 2-rank runs, predicts every rank's counts (ghosts, pairs with a ghost, messages, bytes)
from the geometry of the decomposition pdem chooses, compares them with what was counted at every
rank count, and predicts strong and weak scaling to 1,024 ranks and 10⁸ grains for DEM-P and DEM-C
with the network assumptions it prints (docs/performance.md, "A scaling model").
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
D = 1e-3  # grain diameter [m]


# ------------------------------------------------------------------------------------ counting comm
class Traffic:
    """Per-rank counts of MPI calls: by category, calls, bytes sent and wall seconds inside."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.calls: dict[str, int] = {}
        self.bytes: dict[str, int] = {}
        self.seconds: dict[str, float] = {}

    def add(self, name: str, nbytes: int, seconds: float) -> None:
        self.calls[name] = self.calls.get(name, 0) + 1
        self.bytes[name] = self.bytes.get(name, 0) + int(nbytes)
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds


P2P = {"Isend", "Send", "sendrecv", "Sendrecv", "send", "isend"}
COLLECTIVE = {"Allreduce", "allreduce", "Allgather", "allgather", "bcast", "Bcast", "Barrier", "alltoall",
              "gather", "Gather", "Reduce", "reduce", "Alltoall", "Alltoallv", "Allgatherv"}  # fmt: skip


def _nbytes(name: str, args, kwargs) -> int:
    if not args:
        return 0
    obj = args[0]
    if name[0].isupper():  # buffer API
        a = obj[0] if isinstance(obj, list | tuple) else obj
        return int(getattr(a, "nbytes", 0))
    try:
        return len(pickle.dumps(obj, protocol=5))
    except Exception:  # noqa: BLE001 - a count, not a result
        return 0


class CountingComm:
    """A communicator that counts what passes through it (and the communicators it creates)."""

    def __init__(self, comm, traffic: Traffic) -> None:
        self._comm = comm
        self._traffic = traffic

    def __getattr__(self, name):
        attr = getattr(self._comm, name)
        if not callable(attr):
            return attr
        if name == "Create_cart":
            return lambda *a, **k: CountingComm(attr(*a, **k), self._traffic)
        if name not in P2P and name not in COLLECTIVE:
            return attr

        def counted(*args, **kwargs):
            t0 = time.perf_counter()
            out = attr(*args, **kwargs)
            self._traffic.add(name, _nbytes(name, args, kwargs), time.perf_counter() - t0)
            return out

        return counted


# ------------------------------------------------------------------------------------ the worker
def fcc_box(n_target: int, gap: float, seed: int):
    """Positions of an fcc packing of diameter-D spheres in a cubic periodic box of about
    ``n_target`` spheres (4 per cell), nearest centres D (1 − gap) apart; random velocities."""
    cells = max(2, round((n_target / 4) ** (1 / 3)))
    a = D * (1 - gap) * math.sqrt(2.0)
    base = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    ijk = np.stack(np.meshgrid(*[np.arange(cells)] * 3, indexing="ij"), -1).reshape(-1, 3) * a
    x = (ijk[:, None, :] + base[None] + 0.25 * a).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    v = rng.normal(0.0, 0.2, x.shape)
    return x, v, cells * a


def _state_digest(sim) -> str:
    p = sim.get_particles()
    return hashlib.sha256(p["id"].tobytes() + p["x"].tobytes() + p["v"].tobytes()).hexdigest()


MATERIAL = dict(density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5, friction=0.5)
FOOT, XMAX, YMAX = 0.02, 0.08, 0.02  # the benchmark column's footprint and box


def build_scene(sim, args) -> list[float]:
    """Add the scene's grains and walls to ``sim``; returns the extent the grains fill [m]."""
    from pdem.geometry.shapes import Plane
    from pdem.sources import read_spheres, spatial_order

    if args.scene == "periodic":
        x, v, length = fcc_box(args.n, 1e-3, args.seed)
        sim.set_periodic([0, 0, 0], [length] * 3)
        sim.add_particles(x, D / 2, material="glass", velocities=v)
        return [length] * 3
    d = read_spheres(args.packing)
    o = spatial_order(d["positions"], 2.0 * float(d["radii"].max()))
    x, r = d["positions"][o], d["radii"][o]
    sim.add_particles(x, r, material="glass")
    xmax = XMAX if args.scene == "column" else FOOT
    for name, point, normal in [("floor", (0, 0, 0), (0, 0, 1)), ("x0", (0, 0, 0), (1, 0, 0)),
                                ("x1", (xmax, 0, 0), (-1, 0, 0)), ("y0", (0, 0, 0), (0, 1, 0)),
                                ("y1", (0, YMAX, 0), (0, -1, 0))]:  # fmt: skip
        sim.add_wall(Plane(point, normal), name=name)
    sim.gravity = (0.0, 0.0, -9.81)
    sim.skin = 1e-4
    return (x.max(axis=0) - x.min(axis=0)).tolist()


def _latencies(world, repeats: int = 400) -> dict:
    """Median seconds of a one-integer Allreduce (the rebuild test), and of an exchange of a small
    (64 B) and a large (1 MiB) message with the next and previous rank, as pdem's ghost forward does."""
    from mpi4py import MPI

    out = {}
    one, got = np.zeros(1, np.int32), np.zeros(1, np.int32)
    times = []
    for _ in range(repeats):
        world.Barrier()
        t0 = time.perf_counter()
        world.Allreduce(one, got, op=MPI.MAX)
        times.append(time.perf_counter() - t0)
    out["allreduce"] = float(np.median(times))
    nxt, prv = (world.rank + 1) % world.size, (world.rank - 1) % world.size
    for name, size in (("p2p_64B", 8), ("p2p_1MiB", 131072)):
        buf, back = np.zeros(size), np.zeros(size)
        times = []
        for _ in range(repeats // 4 if size > 8 else repeats):
            world.Barrier()
            t0 = time.perf_counter()
            req = [world.Irecv(back, source=prv, tag=1), world.Isend(buf, dest=nxt, tag=1)]
            MPI.Request.Waitall(req)
            times.append(time.perf_counter() - t0)
        out[name] = float(np.median(times))
    return out


def worker(args) -> None:
    from mpi4py import MPI

    import pdem
    import pdem.parallel.exchange as exchange

    traffic = Traffic()
    world = MPI.COMM_WORLD
    comm = CountingComm(world, traffic)
    phases = {"forward": 0.0, "borders": 0.0, "migrate": 0.0}
    migrations = [0]

    def timed(name, fn):
        def run(*a, **k):
            t0 = time.perf_counter()
            out = fn(*a, **k)
            phases[name] += time.perf_counter() - t0
            if name == "migrate":
                migrations[0] += 1
            return out

        return run

    exchange.forward = timed("forward", exchange.forward)
    exchange.forward_values = timed("forward", exchange.forward_values)
    exchange.borders = timed("borders", exchange.borders)
    exchange.migrate = timed("migrate", exchange.migrate)
    law = {"dem-p": ("hertz_mindlin", {}), "dem-c": ("complementarity", {"solver": args.solver,
           "max_iterations": args.iterations, "tolerance": 1e-12})}[args.law]  # fmt: skip
    sim = pdem.Simulation(comm=comm, law=law[0], **law[1])
    sim.add_material("glass", **MATERIAL)
    extent = build_scene(sim, args)
    sim.dt = args.dt if args.law == "dem-p" else args.dt_c
    sim.run(steps=args.warmup)
    cpu = [0.0]
    integ = sim.integrator
    # CPU time of the force computation and the integration (no MPI call inside them)
    compute = sim.compute_forces

    def timed_compute():
        t0 = time.process_time()
        out = compute()
        cpu[0] += time.process_time() - t0
        return out

    sim.compute_forces = timed_compute
    traffic.reset()
    phases.update(dict.fromkeys(phases, 0.0))
    migrations[0] = 0
    rebuilds0 = sim.neighbours.n_rebuilds
    iterations0 = getattr(integ, "total_iterations", 0)
    world.Barrier()
    t0 = time.perf_counter()
    c0 = time.process_time()
    sim.run(steps=args.steps)
    wall = time.perf_counter() - t0
    cpu_all = time.process_time() - c0
    p = sim.particles
    store = sim.contact_store
    n_own = int(p.n_owned)
    pi, pj = store.pi, store.pj
    with_ghost = int(np.count_nonzero((pi >= n_own) | (pj >= n_own)))
    touching = int(sim.own_contacts()["id_i"].shape[0])
    dx = np.abs(p.x[pi] - p.x[pj]) if pi.size else np.zeros((0, 3))
    dist = np.linalg.norm(dx, axis=1)
    record = {
        "rank": world.rank,
        "ranks": world.size,
        "n_total": sim.count_particles(),
        "owned": n_own,
        "ghosts": int(p.n_ghost),
        "pairs": int(pi.size),
        "pairs_with_ghost": with_ghost,
        "touching_counted": touching,
        "mean_pair_distance": float(dist.mean()) if dist.size else 0.0,
        "mean_abs_dx": dx.mean(axis=0).tolist() if dx.size else [0.0, 0.0, 0.0],
        "bounds": [p.x[:n_own].min(axis=0).tolist(), p.x[:n_own].max(axis=0).tolist()] if n_own else None,
        "rebuilds": sim.neighbours.n_rebuilds - rebuilds0,
        "migrations": migrations[0],
        "ghost_width": float(sim.neighbours.ghost_width),
        "skin": float(sim.neighbours.skin),
        "dims": list(sim.decomposition.dims) if sim.decomposition is not None else [1, 1, 1],
        "extent": extent,
        "scene": args.scene,
        "steps": args.steps,
        "wall": wall,
        "cpu": cpu_all,
        "cpu_forces": cpu[0],
        "phases": dict(phases),
        "calls": traffic.calls,
        "bytes": traffic.bytes,
        "seconds": traffic.seconds,
    }
    if args.law == "dem-c":
        record["iterations"] = float(integ.total_iterations - iterations0)
    if world.size > 1:
        record["latency"] = _latencies(world)
    digest = _state_digest(sim)
    records = world.gather(record, root=0)
    if world.rank == 0:
        Path(args.json).write_text(json.dumps({"digest": digest, "ranks": records}, indent=1))


# ------------------------------------------------------------------------------------ measure
def measure(args) -> None:
    if args.scene != "periodic" and not args.packing:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_vs_lammps import make_packing

        args.packing = str(make_packing(20000, 1))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mpiexec = Path(sys.executable).parent / "mpiexec"
    env = dict(os.environ, MPIR_CVAR_CH4_PROGRESS_THROTTLE="1")
    runs = []
    for rep in range(args.repeats):  # alternating rank counts: drifts of the machine hit all alike
        for k in args.ranks:
            target = out / f"{args.scene}_{args.law}_n{args.n}_k{k}_r{rep}.json"
            cmd = [str(mpiexec), "-n", str(k), sys.executable, __file__, "_worker", "--json", str(target),
                   "--n", str(args.n), "--steps", str(args.steps), "--law", args.law, "--solver", args.solver,
                   "--iterations", str(args.iterations), "--warmup", str(args.warmup),
                   "--scene", args.scene, "--packing", str(args.packing)]  # fmt: skip
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if proc.returncode:
                sys.exit(f"{k} ranks failed:\n{proc.stderr[-3000:]}")
            data = json.loads(target.read_text())
            runs.append(data)
            wall = max(r["wall"] for r in data["ranks"])
            print(f"{k} rank(s) #{rep}: {wall:.2f} s stepping ({time.perf_counter() - t0:.0f} s in all), "
                  f"digest {data['digest'][:12]}", flush=True)  # fmt: skip
    digests = {r["digest"] for r in runs}
    print("bitwise identical on every rank count:", len(digests) == 1)
    summary = out / f"measure_{args.scene}_{args.law}.json"
    summary.write_text(json.dumps({"law": args.law, "scene": args.scene, "runs": runs}, indent=1))
    print(f"wrote {summary}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("measure", "_worker"):
        p = sub.add_parser(name)
        p.add_argument("--scene", choices=["bed", "column", "periodic"], default="bed",
                       help="bed: a packing at rest in its box; column: its collapse; periodic: fcc")
        p.add_argument("--packing", default="", help="packing file (bed, column; default: made once)")
        p.add_argument("--n", type=int, default=20000, help="grains (periodic scene; about)")
        p.add_argument("--steps", type=int, default=300)
        p.add_argument("--warmup", type=int, default=20)
        p.add_argument("--law", choices=["dem-p", "dem-c"], default="dem-p")
        p.add_argument("--solver", default="jacobi")
        p.add_argument("--iterations", type=int, default=50, help="DEM-C iterations per step (a fixed count)")
        p.add_argument("--dt", type=float, default=2e-6)
        p.add_argument("--dt-c", type=float, default=1e-4)
        p.add_argument("--seed", type=int, default=1)
        if name == "measure":
            p.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6, 7, 8])
            p.add_argument("--repeats", type=int, default=1)
            p.add_argument("--out", default=str(ROOT / "out" / "scaling"))
        else:
            p.add_argument("--json", required=True)
    m = sub.add_parser("model")
    m.add_argument("measurements", nargs="+")
    args = ap.parse_args(argv)
    if args.cmd == "_worker":
        worker(args)
    elif args.cmd == "measure":
        measure(args)
    else:
        from scaling_model import report  # noqa: PLC0415

        report(args.measurements)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
