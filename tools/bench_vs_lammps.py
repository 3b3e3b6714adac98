#!/usr/bin/env python
"""Column collapse, pdem vs LAMMPS, side by side on the same machine in the same session.

    python tools/bench_vs_lammps.py [--n 20000] [--steps 5000] [--repeats 3] [--shuffle] [--ranks 1 2]

1. Makes (once, cached in tools/_work/) a settled column of N polydisperse spheres with pdem's own
   pluviation (d uniform in 0.9–1.1 mm, ρ = 2500 kg/m³, footprint 20 × 20 mm) and writes it both as
   a pdem text packing and as a LAMMPS data file.
2. Releases it in the box x ∈ [0, 0.08], y ∈ [0, 0.02] with a floor: Hertz–Mindlin from materials,
   E = 5e7 Pa, ν = 0.3, e = 0.5, μ = 0.5, dt = 2e-6 s, skin 0.1 mm, no output while timing.
   LAMMPS uses the tsuji damping parameter that realises e = 0.5 in its build (calibrated, see
   tools/lammps_peer.py), so both codes realise the same restitution.
3. Alternates pdem and LAMMPS runs (each in its own process), ``--repeats`` times, and reports the
   medians of the loop times (the time of the stepping loop only, for both codes), particle-steps per
   second, pdem start-up time with a warm and a cold numba cache, and pdem's peak memory per particle.
4. Checks that both codes agree physically at the end: front position and kinetic energy within 10 %.

With ``--ranks 1 2`` both codes also run on 2 ranks (MPI; LAMMPS splits the box in y, pdem balances
its cut planes on particle counts) and each code's speed-up over its own serial run is reported.

With ``--shuffle`` both codes read the packing's rows in random order (the input-order test): pdem
runs as read (ids by row), with its file source's ``order = "spatial"`` (ids by cells), and on the
sorted copy, and the three times are reported with LAMMPS's.

The last line is ``ratio pdem/lammps = X.XX`` (pdem throughput over LAMMPS throughput at the first
rank count, > 1 means pdem is faster). Exit code 1 if the physical check fails.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
WORK = HERE / "_work"
XMAX, YMAX = 0.08, 0.02
FOOT = 0.02
MATERIAL = dict(density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5, friction=0.5)


def _peer():
    spec = importlib.util.spec_from_file_location("lammps_peer", HERE / "lammps_peer.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def make_packing(n: int, seed: int) -> Path:
    """Settled column made by pdem's pluviation, cached by (n, seed)."""
    WORK.mkdir(exist_ok=True)
    path = WORK / f"column_{n}_{seed}.txt"
    if path.exists():
        return path
    import pdem
    from pdem.sources import BoxRegion, Uniform, pluviate, write_spheres_text

    print(f"making a settled column of {n} spheres by pluviation (once; cached in {path})", flush=True)
    t0 = time.perf_counter()
    x, r = pluviate(BoxRegion((0, 0, 0), (FOOT, FOOT, 0.1)), Uniform(0.45e-3, 0.55e-3), n,
                    pdem.Material("glass", **MATERIAL), seed=seed, fill_fraction=0.35,
                    progress=lambda t, v: print(f"  settling: t = {t:.3f} s, v_rms = {v:.3g} m/s",
                                                flush=True))
    tmp = path.with_suffix(".tmp")
    write_spheres_text(tmp, x, r)
    tmp.replace(path)
    print(f"  done in {time.perf_counter() - t0:.0f} s; column height {x[:, 2].max():.4f} m", flush=True)
    return path


def sorted_copy(src: Path) -> Path:
    """Spatially sorted copy of a packing file (pdem assigns ids in row order; so does LAMMPS)."""
    from pdem.sources import read_spheres, spatial_order, write_spheres_text

    WORK.mkdir(exist_ok=True)
    dst = WORK / f"{src.stem}_sorted.txt"
    d = read_spheres(src)
    order = spatial_order(d["positions"], 2.0 * float(d["radii"].max()))
    write_spheres_text(dst, d["positions"][order], d["radii"][order])
    return dst


def shuffled_copy(src: Path, seed: int) -> Path:
    """A copy of a packing file with its rows in random order (both codes read it row by row)."""
    import numpy as np

    from pdem.sources import read_spheres, write_spheres_text

    dst = WORK / f"{src.stem}_shuffled{seed}.txt"
    d = read_spheres(src)
    perm = np.random.default_rng(seed).permutation(len(d["radii"]))
    write_spheres_text(dst, d["positions"][perm], d["radii"][perm])
    return dst


def pdem_worker(packing: str, steps: int, order: str = "file") -> dict:
    """Run in a fresh process: build, time the loop, report. Called with --worker."""
    t_start = time.perf_counter()
    import numpy as np

    import pdem
    from pdem.geometry.shapes import Plane
    from pdem.parallel.comm import default_comm
    from pdem.sources import read_spheres

    t_import = time.perf_counter()
    comm = default_comm()
    d = read_spheres(packing)
    if order == "spatial":  # what a deck's file source does with order = "spatial"
        from pdem.sources import spatial_order

        o = spatial_order(d["positions"], 2.0 * float(d["radii"].max()))
        d = {"positions": d["positions"][o], "radii": d["radii"][o]}
    sim = pdem.Simulation(comm=comm)
    sim.add_material("glass", **MATERIAL)
    sim.add_particles(d["positions"], d["radii"])
    for name, point, normal in [("floor", (0, 0, 0), (0, 0, 1)), ("x0", (0, 0, 0), (1, 0, 0)),
                                ("x1", (XMAX, 0, 0), (-1, 0, 0)), ("y0", (0, 0, 0), (0, 1, 0)),
                                ("y1", (0, YMAX, 0), (0, -1, 0))]:
        sim.add_wall(Plane(point, normal), name=name)
    sim.gravity = (0.0, 0.0, -9.81)
    sim.dt = 2e-6
    sim.skin = 1e-4
    sim.run(steps=1)  # compile or load kernels, first neighbour list
    comm.Barrier()
    t_ready = time.perf_counter()
    sim.run(steps=steps - 1)
    comm.Barrier()
    t_end = time.perf_counter()
    p = sim.get_particles()
    ke_t, ke_r = sim.kinetic_energy()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    rss = comm.allreduce(rss) if comm.size > 1 else rss
    return dict(
        ranks=comm.size,
        natoms=int(sim.count_particles()), steps=steps, loop_time=t_end - t_ready,
        startup_time=t_ready - t_start, import_time=t_import - t_start,
        front_x=float(p["x"][:, 0].max()), ke_trans=ke_t, ke_rot=ke_r,
        peak_rss_bytes=rss,
        rebuilds=sim.n_rebuilds,
        finite=bool(np.all(np.isfinite(p["x"]))),
    )


def run_pdem(packing: Path, steps: int, cold: bool = False, ranks: int = 1, order: str = "file") -> dict:
    env = dict(os.environ)
    tmpdir = None
    if cold:
        tmpdir = tempfile.TemporaryDirectory(prefix="pdem-cold-cache-")
        env["PDEM_NUMBA_CACHE_DIR"] = tmpdir.name
    cmd = [sys.executable, __file__, "--worker", str(packing), "--steps", str(steps), "--order", order]
    if ranks > 1:
        mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or "mpiexec"
        cmd = [mpiexec, "-n", str(ranks), *cmd]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if tmpdir is not None:
        tmpdir.cleanup()
    if out.returncode != 0:
        raise RuntimeError(f"pdem worker failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=20000, help="number of spheres (default 20000)")
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=3, help="runs of each code; medians are reported")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--epar", type=float, default=None,
                    help="LAMMPS tsuji damping parameter (default: calibrated to realise e = 0.5)")
    ap.add_argument("--packing", type=Path, default=None,
                    help="use this 'x y z diameter' packing instead of making one (rows are sorted "
                         "spatially, and both codes get the same sorted rows)")
    ap.add_argument("--ranks", type=int, nargs="+", default=[1],
                    help="rank counts to run both codes on, e.g. --ranks 1 2 (speed-ups are reported)")
    ap.add_argument("--shuffle", action="store_true",
                    help="give both codes the packing's rows in random order (pdem then also runs with "
                         "its file source's order = 'spatial', and both of its times are reported)")
    ap.add_argument("--order", default="file", help=argparse.SUPPRESS)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        from pdem.parallel.comm import default_comm

        comm = default_comm()
        try:
            result = pdem_worker(args.worker, args.steps, args.order)
        except BaseException:
            if comm.size > 1:  # an error on one rank must end the job, not leave the others waiting
                import traceback

                traceback.print_exc()
                sys.stderr.flush()
                comm.Abort(1)
            raise
        if comm.rank == 0:
            print(json.dumps(result))
        return 0

    peer = _peer()
    if not peer.lammps_available():
        print("LAMMPS (lmp) not found: apt-get install lammps", file=sys.stderr)
        return 2
    packing = make_packing(args.n, args.seed) if args.packing is None else sorted_copy(args.packing)
    if args.shuffle:  # the sorted copy in spatial_order's order, which order = "spatial" reproduces
        sorted_packing = sorted_copy(packing) if args.packing is None else packing
        packing = shuffled_copy(packing, args.seed)
        print(f"rows shuffled: {packing}", flush=True)
    data = WORK / f"{packing.stem}.lammps.data"
    peer.data_from_packing(packing, data, density=MATERIAL["density"], xmax=XMAX, ymax=YMAX)
    epar = args.epar if args.epar is not None else peer.calibrate_tsuji(0.5)
    print(f"LAMMPS {peer.lammps_version()}, tsuji parameter {epar:.4f} (realises e = 0.5)", flush=True)

    cold = run_pdem(packing, 50, cold=True)
    print(f"pdem start-up with a cold numba cache: {cold['startup_time']:.2f} s", flush=True)
    ranks = sorted(set(args.ranks))
    pd: dict[int, list] = {k: [] for k in ranks}
    lm: dict[int, list] = {k: [] for k in ranks}
    ps: dict[int, list] = {k: [] for k in ranks}  # --shuffle: pdem with order = "spatial"
    pz: dict[int, list] = {k: [] for k in ranks}  # --shuffle: pdem on the sorted copy
    for rep in range(args.repeats):
        for k in ranks:  # alternate the codes so both see the same machine state
            if args.shuffle:
                ps[k].append(run_pdem(packing, args.steps, ranks=k, order="spatial"))
                pz[k].append(run_pdem(sorted_packing, args.steps, ranks=k))
                print(f"  run {rep + 1}, {k} rank(s): pdem sorted copy {pz[k][-1]['loop_time']:.2f} s, "
                      f"shuffled with order = 'spatial' {ps[k][-1]['loop_time']:.2f} s", flush=True)
            pd[k].append(run_pdem(packing, args.steps, ranks=k))
            lm[k].append(peer.run_lammps(data, ranks=k, steps=args.steps, epar=epar, xmax=XMAX, ymax=YMAX,
                                         skin=1e-4, dt=2e-6))
            print(f"  run {rep + 1}, {k} rank(s): pdem loop {pd[k][-1]['loop_time']:.2f} s, "
                  f"LAMMPS loop {lm[k][-1]['loop_time']:.2f} s", flush=True)
    n = pd[ranks[0]][0]["natoms"]
    t_pd = {k: statistics.median(r["loop_time"] for r in pd[k]) for k in ranks}
    t_lm = {k: statistics.median(r["loop_time"] for r in lm[k]) for k in ranks}
    rate_pd = {k: n * (args.steps - 1) / t_pd[k] for k in ranks}
    rate_lm = {k: n * args.steps / t_lm[k] for k in ranks}
    print(f"\nN = {n}, {args.steps} steps, medians of {args.repeats}")
    for k in ranks:
        print(f"pdem   {k} rank(s): loop {t_pd[k]:.2f} s -> {rate_pd[k] / 1e6:.2f} M particle-steps/s")
        print(f"LAMMPS {k} rank(s): loop {t_lm[k]:.2f} s -> {rate_lm[k] / 1e6:.2f} M particle-steps/s")
    if args.shuffle:
        for k in ranks:
            t_s = statistics.median(r["loop_time"] for r in ps[k])
            t_z = statistics.median(r["loop_time"] for r in pz[k])
            print(f"pdem   {k} rank(s), shuffled rows: file order {t_pd[k]:.2f} s ({t_pd[k] / t_z:.3f}x the "
                  f"sorted copy's {t_z:.2f} s), order = 'spatial' {t_s:.2f} s ({t_s / t_z:.3f}x); "
                  f"LAMMPS on the shuffled rows {t_lm[k]:.2f} s")
            same = ps[k][0]["front_x"] == pz[k][0]["front_x"] and ps[k][0]["ke_trans"] == pz[k][0]["ke_trans"]
            print(f"pdem   {k} rank(s): order = 'spatial' on the shuffled rows gives the sorted copy's "
                  f"results bit for bit: {same}")
            ratio = t_lm[k] / t_s * (args.steps - 1) / args.steps
            print(f"ratio pdem(order = 'spatial')/lammps, {k} rank(s) = {ratio:.2f}")
    if 1 in ranks:
        for k in ranks[1:]:
            print(f"speed-up on {k} ranks over serial: pdem {t_pd[1] / t_pd[k]:.2f}x, "
                  f"LAMMPS {t_lm[1] / t_lm[k]:.2f}x")
        warm = statistics.median(r["startup_time"] for r in pd[1])
        mem = max(r["peak_rss_bytes"] for r in pd[1]) / n
        print(f"pdem start-up: warm cache {warm:.2f} s, cold cache {cold['startup_time']:.2f} s "
              f"(import {pd[1][0]['import_time']:.2f} s)")
        print(f"pdem peak memory: {mem:.0f} bytes per particle (whole process RSS / N, serial)")
    ok = True
    for k in ranks:
        for key in ("front_x", "ke_trans"):
            a, b = pd[k][0][key], lm[k][0][key]
            rel = abs(a - b) / abs(b)
            good = rel <= 0.10
            ok &= good
            print(f"agreement on {k} rank(s), {key}: pdem {a:.6g}, LAMMPS {b:.6g}, difference "
                  f"{100 * rel:.1f} % ({'ok' if good else 'FAILS the 10 % check'})")
    if len(ranks) > 1:
        same = all(pd[k][0]["front_x"] == pd[ranks[0]][0]["front_x"]
                   and pd[k][0]["ke_trans"] == pd[ranks[0]][0]["ke_trans"] for k in ranks)
        print(f"pdem results identical on {ranks} ranks: {same}")
    k0 = ranks[0]
    print(f"ratio pdem/lammps = {rate_pd[k0] / rate_lm[k0]:.2f}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
