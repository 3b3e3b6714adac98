"""Jacobi's relaxation bound along a DEM-C run: how large ``relaxation`` (ω) may be on a scene.

Projected Jacobi updates every contact at once, γ ← Π_K(γ − ω B u). On the contacts that carry
load (γ_n > 0) the sweep is a contraction only while ω λ_max(B N) < 2; above, it amplifies the
contacts' mutual corrections from sweep to sweep and holds grains together only through the
projection and the iteration cap. This runs a deck (the same arguments as ``pdem``) and, every
``--every`` steps, measures λ_max of the step's problem by power iteration
(``Stepper.jacobi_bound``, partition-independent up to rounding), on the loaded contacts and on
every row of the problem::

    python tools/jacobi_bound.py inputs/hopper.toml --every 40 --set contact.law=complementarity ...
    mpiexec -n 2 python tools/jacobi_bound.py DECK --csv bound.csv ...

Rows ``step, contacts, loaded, lambda_loaded, omega_bound_loaded, lambda_all, omega_bound_all`` on
stdout (rank 0) and in ``--csv``; the last lines give the smallest bound seen. docs/dem_c.md,
*The hopper at each method's best settings*, has the hopper's.
"""

from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("--every", type=int, default=40, help="measure every N steps (default 40)")
    ap.add_argument("--iterations", type=int, default=200, help="power iterations per measure (default 200)")
    ap.add_argument("--csv", help="also write the rows to this file")
    args, rest = ap.parse_known_args(argv)
    if args.every < 1 or args.iterations < 1:
        ap.error("--every and --iterations must be at least 1")

    import numpy as np

    from pdem.cli import main as pdem_main
    from pdem.complementarity import method
    from pdem.parallel.exact import global_count

    rows: list[tuple] = []
    step = method.Stepper.step

    def measured_step(self) -> None:
        step(self)
        sim = self.sim
        if sim.step_count % args.every:
            return
        nc = int(self.log[-1][3])
        counted = self._counted_rows(nc)
        loaded = np.zeros(nc, dtype=bool)
        loaded[counted] = self.gam[counted, 0] > 0.0
        n_all = global_count(sim.comm, counted.size)
        n_loaded = global_count(sim.comm, int(loaded.sum()))
        lam_l = self.jacobi_bound(active=True, iterations=args.iterations)
        lam_a = self.jacobi_bound(active=False, iterations=args.iterations)
        row = (sim.step_count, int(n_all), int(n_loaded), lam_l, 2.0 / lam_l if lam_l > 0 else float("inf"),
               lam_a, 2.0 / lam_a if lam_a > 0 else float("inf"))  # fmt: skip
        rows.append(row)
        if sim.comm.rank == 0:
            print(",".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in row), flush=True)

    method.Stepper.step = measured_step
    header = "step,contacts,loaded,lambda_loaded,omega_bound_loaded,lambda_all,omega_bound_all"
    from pdem.parallel.comm import default_comm

    rank = default_comm().rank
    if rank == 0:
        print(header, flush=True)
    code = pdem_main(rest)
    if rank == 0 and not rows and code == 0:
        print(f"nothing measured: no DEM-C step (contact.law = \"complementarity\") at a multiple of "
              f"--every {args.every}", file=sys.stderr)  # fmt: skip
    if rank == 0 and rows:
        if args.csv:
            with open(args.csv, "w") as f:
                f.write(header + "\n")
                for r in rows:
                    f.write(",".join(repr(v) for v in r) + "\n")
        low = min(rows, key=lambda r: r[4])
        print(f"smallest bound on the loaded contacts: omega < {low[4]:.4g} (step {low[0]}); "
              f"on every row: omega < {min(r[6] for r in rows):.4g}", flush=True)  # fmt: skip
    return code


if __name__ == "__main__":
    sys.exit(main())
