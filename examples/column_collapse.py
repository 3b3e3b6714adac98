"""Main example until the deck runner exists: pour a column of spheres, release it, watch it spread.

    python examples/column_collapse.py [--n 1500] [--out out/column_collapse]

1. Pours N glass-like spheres (d 0.9–1.1 mm) into a 10 × 10 mm footprint and lets them settle
   (pdem's pluviation: random loose fill, rain under gravity, integrate to rest).
2. Removes the side walls at x = 10 mm and lets the column collapse into a 60 mm long box.
3. Prints and writes (CSV) the front position, kinetic energy and floor load against time.
Uses only the Python API; SI units.
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

import pdem
from pdem.geometry.shapes import Plane
from pdem.sources import BoxRegion, Uniform, pluviate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1500, help="number of spheres")
    ap.add_argument("--out", default="out/column_collapse", help="output directory")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
    args = ap.parse_args()
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise SystemExit(f"error: output directory {out} exists; pass --overwrite or choose --out")
    out.mkdir(parents=True, exist_ok=True)

    glass = pdem.Material("glass", density=2500, youngs_modulus=5e7, poisson_ratio=0.3,
                          restitution=0.5, friction=0.5)
    t0 = time.perf_counter()
    x, r = pluviate(BoxRegion((0, 0, 0), (0.01, 0.01, 0.05)), Uniform(0.45e-3, 0.55e-3), args.n, glass,
                    progress=lambda t, v: print(f"settling: t = {t:.3f} s, RMS speed {v:.3g} m/s"))
    print(f"column of {len(r)} spheres settled, height {x[:, 2].max() * 1e3:.1f} mm "
          f"({time.perf_counter() - t0:.1f} s)")

    sim = pdem.Simulation()
    sim.add_material(glass)
    sim.add_particles(x, r)
    for name, point, normal in [("floor", (0, 0, 0), (0, 0, 1)), ("back", (0, 0, 0), (1, 0, 0)),
                                ("end", (0.06, 0, 0), (-1, 0, 0)), ("y0", (0, 0, 0), (0, 1, 0)),
                                ("y1", (0, 0.01, 0), (0, -1, 0))]:
        sim.add_wall(Plane(point, normal), name=name)
    sim.gravity = (0, 0, -9.81)
    sim.dt = 2e-6
    rows = []

    def record(s: pdem.Simulation) -> None:
        p = s.particles
        ke_t, ke_r = s.kinetic_energy()
        rows.append((s.time, float(p.x[:, 0].max()), ke_t, ke_r, float(s.walls["floor"].force[2])))

    t0 = time.perf_counter()
    sim.run(until=0.15, callback=record, every=2500)
    wall = time.perf_counter() - t0
    with open(out / "collapse.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", "front_x_m", "ke_trans_J", "ke_rot_J", "floor_force_z_N"])
        w.writerows(rows)
    for t, front, ke_t, _ke_r, fz in rows[:: max(1, len(rows) // 10)]:
        print(f"t = {t:.3f} s  front {front * 1e3:6.2f} mm  KE {ke_t:.3e} J  floor load {fz:.4f} N")
    weight = float(np.sum(sim.particles.mass)) * 9.81
    print(f"floor load at the end {rows[-1][4]:.4f} N vs weight {weight:.4f} N; "
          f"{sim.step_count} steps in {wall:.1f} s "
          f"({sim.n_particles * sim.step_count / wall / 1e6:.2f} M particle-steps/s); "
          f"wrote {out / 'collapse.csv'}")


if __name__ == "__main__":
    try:
        main()
    except pdem.PdemError as exc:
        raise SystemExit(f"error: {exc}") from None
