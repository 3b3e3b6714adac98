#!/usr/bin/env python
"""Where DEM-C fails, measured: three small studies, results as a table and JSON.

    python tools/dem_c_study.py [--out DIR] [--quick]

1. **Iterations vs column height.** A column of N touching spheres on a floor (2 mm glass beads,
   h = 1e-4 s), solved from a cold start (no warm start) to a residual of 1e-8 m/s: iterations per
   solver for N = 2 … 32. Projected Jacobi is expected to need O(N²) (a load crosses one contact per
   iteration and the error decays diffusively), Gauss–Seidel in contact order fewer, APGD ~O(N).
2. **Apparent wave speed in a chain.** A chain of N touching spheres, no gravity; the first is
   struck at v0 = 1 m/s. The time at which the far end reaches 1 % of v0 gives an apparent front
   speed L / t. DEM-P (Hertz, E = 5e7 Pa) transmits a physical wave; rigid contact with an exact
   solve moves the whole chain at once (infinite speed), and with an iteration cap k the front moves
   at most k contacts per step, i.e. ≤ k d / h: the speed is a numerical artefact of k and h, which is
   why DEM-C cannot capture shock propagation (the study's conclusion).
3. **Cost per iteration per contact** of the Jacobi sweep (its three passes and the whole iteration)
   against one DEM-P pair-force evaluation per contact, on the same block of touching spheres.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

import pdem
from pdem.errors import InstabilityError
from pdem.geometry import shapes

R = 1e-3
MAT = dict(density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5, friction=0.5)


def column_iterations(
    n: int, solver: str, tol: float = 1e-8, cap: int = 200000, scaling: str = "block"
) -> int:
    relax = {"jacobi": 1.0, "gauss_seidel": 1.0, "apgd": 1.0}[solver]
    sim = pdem.Simulation(
        law="complementarity", solver=solver, tolerance=tol, max_iterations=cap, relaxation=relax,
        scaling=scaling,
    )
    sim.add_material("glass", **MAT)
    x = np.zeros((n, 3))
    x[:, 2] = R + 2 * R * np.arange(n)
    sim.add_particles(x, R, material="glass")
    sim.add_wall(shapes.Plane((0, 0, 0), (0, 0, 1)), material="glass", name="floor")
    sim.gravity = (0, 0, -9.81)
    sim.dt = 1e-4
    sim.step()
    it = sim.integrator.log[-1][1]
    return it if sim.integrator.n_unconverged == 0 else -1


def chain_front_speed(n: int, method: str, dt: float, cap: int | None = None, t_end: float = 0.02) -> float:
    """Apparent front speed [m/s]: chain length over the time the last sphere reaches 1 % of v0;
    −1 if the run became unstable (grains pushed through each other: too few iterations)."""
    if method == "DEM-P":
        sim = pdem.Simulation(law="hertz_mindlin")
    else:
        sim = pdem.Simulation(
            law="complementarity", solver="jacobi", tolerance=1e-12, max_iterations=cap, relaxation=1.0
        )
    sim.add_material("glass", **MAT)
    x = np.zeros((n, 3))
    x[:, 0] = 2 * R * np.arange(n)
    v = np.zeros((n, 3))
    v[0, 0] = 1.0
    ids = sim.add_particles(x, R, material="glass", velocities=v)
    sim.dt = dt
    last = int(ids[-1])
    steps = int(math.ceil(t_end / dt))
    for _ in range(steps):
        try:
            sim.step()
        except InstabilityError:
            return -1.0
        p = sim.particles
        k = int(np.flatnonzero(p.id[: p.n_owned] == last)[0])
        if p.v[k, 0] >= 0.01:
            return 2 * R * (n - 1) / sim.time
    return float("nan")


def cost_per_contact(repeat: int = 9, rolling: bool = False) -> dict[str, float]:
    """Kernel time per contact on a simple-cubic block of 4,000 spheres overlapping their six
    neighbours by 0.5 % of the diameter (every neighbour pair is a contact for both methods).
    ``rolling``: the material has rolling and spinning friction (DEM-C's rolling rows active)."""
    from pdem.complementarity import _kernels as ck

    g = np.stack(np.meshgrid(np.arange(20), np.arange(20), np.arange(10), indexing="ij"), -1).reshape(-1, 3)
    x = g * 1.99 * R
    roll = {"rolling_friction": 0.1, "spinning_friction": 0.05} if rolling else {}

    def block_step(**params):
        """The block with DEM-C after one step (its contact rows assembled)."""
        s = pdem.Simulation(law="complementarity", max_iterations=1, envelope=0.0, **params)
        s.add_material("glass", **(MAT | roll))
        s.add_particles(x, R, material="glass")
        s.dt = 1e-4
        s.max_overlap = 1.0
        s.step()
        return s

    sim = block_step(solver="jacobi")
    st = sim.integrator
    p = sim.particles
    nc = st.log[-1][3]
    width = st.gam.shape[1]
    P = np.zeros((p.n, 3))
    L = np.zeros((p.n, 3))
    v0, w0 = p.v[: p.n].copy(), p.w[: p.n].copy()
    G = np.ascontiguousarray(st.gam[:nc].T)
    IB, CR = ck.jacobi_columns(st.cscale, st.croll, nc, width == 8)
    BLK = ck.block_columns(st.cb, st.ca, st.cmu, st.cscale, st.IM, st.II, nc, False)
    U = np.empty((width, nc))
    RES = np.empty(nc)

    def gather():
        ck.jacobi_gather(st.cb, st.cn, st.ca, st.cvw, st.cbias, st.croll, p.v, p.w, nc, U)

    def project(check):
        ck.jacobi_project(U, G, st.cmu, st.cscale, IB, BLK, CR, nc, 0.3, True, check, RES)

    def scatter():
        ck.accumulate_columns(st.cb, st.cn, st.ca, st.croll, G, nc, P, L)

    def velocities():
        ck.velocities(p.v, p.w, v0, w0, P, L, p.inv_m, p.inv_i, p.dof, p.n_owned)

    def iteration(check):  # the kernels of one sweep, as Stepper._jacobi runs them
        gather()
        project(check)
        scatter()
        if check:
            ck.max_nonneg(RES, nc)
        velocities()

    hm = pdem.Simulation(law="hertz_mindlin")
    hm.add_material("glass", **(MAT | roll))
    hm.add_particles(x, R, material="glass")
    hm.dt = 1e-7
    hm.prepare()
    cs = hm.contact_store
    touching = int(np.count_nonzero(np.any(cs.force[: len(cs.pi)] != 0.0, axis=1)))

    def gauss_seidel():
        ck.gauss_seidel_sweep(
            st.cb, st.cn, st.ca, st.cvw, st.cbias, st.cmu, st.cscale, BLK, st.croll, st.gam, p.v, p.w,
            st.IM, st.II, st.DOF, nc, 0.3, True,
        )  # fmt: skip

    # (kernel, contacts it runs over); timed in rounds, each kernel once per round (20 calls), so
    # that the machine's drift touches every kernel alike; ratios to DEM-P are medians over rounds
    kernels = {
        "gather": (gather, nc),
        "project": (lambda: project(True), nc),
        "project_unchecked": (lambda: project(False), nc),
        "scatter": (scatter, nc),
        "iteration": (lambda: iteration(True), nc),
        "iteration_unchecked": (lambda: iteration(False), nc),
        "gauss_seidel": (gauss_seidel, nc),
        "dem_p": (hm.compute_forces, max(touching, 1)),
    }
    times = {k: [] for k in kernels}
    for fn, _count in kernels.values():
        fn()  # compiled and warm
    for _ in range(repeat):
        for name, (fn, count) in kernels.items():
            t0 = time.perf_counter()
            for _ in range(20):
                fn()
            times[name].append((time.perf_counter() - t0) / 20 / count)
    med = {k: float(np.median(v)) for k, v in times.items()}

    def over_dem_p(name):
        return float(np.median(np.array(times[name]) / np.array(times["dem_p"])))

    t_gather, t_project, t_project_u = med["gather"], med["project"], med["project_unchecked"]
    t_scatter, t_it, t_unchecked = med["scatter"], med["iteration"], med["iteration_unchecked"]
    t_gs, t_p = med["gauss_seidel"], med["dem_p"]
    # an APGD iteration as the solver runs it (line-search trials, exact sums, Python between the
    # kernels), on the rows of the first step: solves capped at 41 and at 1 iteration (tolerance out
    # of reach), the difference per iteration and contact
    vf = np.zeros((p.n, 3))
    wf = np.zeros((p.n, 3))
    Pa = np.zeros((p.n, 3))
    La = np.zeros((p.n, 3))

    def solver_iteration(solver: str, check_every: int) -> float:
        """Seconds per iteration and contact of the solver as the stepper runs it (its kernels and
        the Python between them), on the rows of the first step: solves capped at 41 and at 1
        iteration (tolerance out of reach), the difference per iteration and contact."""
        sta = block_step(solver=solver, tolerance=1e-30).integrator
        nca = sta.log[-1][3]
        step_times, step_its = {}, {}
        for cap in (1, 41):
            sta.law.params = sta.p.model_copy(update={"max_iterations": cap, "check_every": check_every})
            ts, its = [], []
            for _ in range(repeat):
                sta.gam[:nca] = 0.0
                t0 = time.perf_counter()
                it, _res = sta._solve(nca, vf, wf, Pa, La)
                ts.append(time.perf_counter() - t0)
                its.append(it)
            step_times[cap], step_its[cap] = float(np.median(ts)), float(np.median(its))
        return (step_times[41] - step_times[1]) / (step_its[41] - step_its[1]) / nca

    apgd_it = solver_iteration("apgd", 1)
    apgd_it5 = solver_iteration("apgd", 5)  # the residual on every 5th iteration
    jacobi_solver_it = solver_iteration("jacobi", 1)
    jacobi_solver_it5 = solver_iteration("jacobi", 5)
    ns = 1e9
    return {
        "contacts_dem_c": nc,
        "touching_pairs_dem_p": touching,
        "dem_p_force_ns_per_contact": ns * t_p,
        "jacobi_gather_ns_per_contact": ns * t_gather,
        "jacobi_project_ns_per_contact": ns * t_project,
        "jacobi_project_unchecked_ns_per_contact": ns * t_project_u,
        "jacobi_scatter_ns_per_contact": ns * t_scatter,
        "jacobi_iteration_ns_per_contact": ns * t_it,
        "jacobi_iteration_unchecked_ns_per_contact": ns * t_unchecked,
        "jacobi_solver_iteration_ns_per_contact": ns * jacobi_solver_it,
        "jacobi_solver_iteration_check_every_5_ns_per_contact": ns * jacobi_solver_it5,
        "gauss_seidel_iteration_ns_per_contact": ns * t_gs,
        "apgd_iteration_ns_per_contact": ns * apgd_it,
        "apgd_iteration_check_every_5_ns_per_contact": ns * apgd_it5,
        "iteration_over_dem_p": over_dem_p("iteration"),
        "unchecked_iteration_over_dem_p": over_dem_p("iteration_unchecked"),
        "jacobi_solver_iteration_over_dem_p": jacobi_solver_it / t_p,
        "jacobi_solver_iteration_check_every_5_over_dem_p": jacobi_solver_it5 / t_p,
        "apgd_iteration_over_dem_p": apgd_it / t_p,
        "apgd_iteration_check_every_5_over_dem_p": apgd_it5 / t_p,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/dem_c_study"))
    ap.add_argument("--quick", action="store_true", help="fewer sizes (a smoke run)")
    ap.add_argument("--parts", type=int, nargs="+", default=[1, 2, 3], help="which studies to run")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, object] = {}

    heights = [2, 4, 8] if args.quick else [2, 4, 8, 16, 32]
    if 1 not in args.parts:
        heights = []
    print("1. iterations to 1e-8 m/s from a cold start, column of N spheres on a floor")
    print("   (Jacobi and Gauss-Seidel at omega = 1 with the block scaling, the default, and the trace one)")
    runs = {
        "jacobi": ("jacobi", "block"),
        "jacobi_trace": ("jacobi", "trace"),
        "gauss_seidel": ("gauss_seidel", "block"),
        "gauss_seidel_trace": ("gauss_seidel", "trace"),
        "apgd": ("apgd", "block"),
    }
    print(f"{'N':>4s}" + "".join(f" {k:>18s}" for k in runs))
    col = []
    for n in heights:
        row = {"N": n, **{k: column_iterations(n, s, scaling=sc) for k, (s, sc) in runs.items()}}
        col.append(row)
        print(f"{n:4d}" + "".join(f" {row[k]:18d}" for k in runs))
    results["column_iterations"] = col

    n_chain = 20 if args.quick else 40
    if 2 not in args.parts:
        n_chain = 0
    print(f"\n2. apparent front speed (−1: unstable) in a chain of {n_chain} spheres struck at 1 m/s [m/s]")
    chain = []
    probe = pdem.Simulation(law="hertz_mindlin")
    probe.add_material("glass", **MAT)
    probe.add_particles([[0, 0, 0]], R, material="glass")
    probe._prepare()
    dt_p = probe.dt
    speed_p = chain_front_speed(n_chain, "DEM-P", dt_p) if n_chain else float("nan")
    chain.append({"method": "DEM-P", "dt": dt_p, "cap": None, "speed": speed_p})
    print(f"DEM-P  h = {dt_p:.2e} s: {speed_p:8.1f}")
    for dt in (1e-5, 1e-4) if n_chain else ():
        for cap in (1, 5, 25, 200):
            s = chain_front_speed(n_chain, "DEM-C", dt, cap)
            chain.append({"method": "DEM-C", "dt": dt, "cap": cap, "speed": s, "bound": cap * 2 * R / dt})
            print(
                f"DEM-C  h = {dt:.0e} s, cap {cap:4d}: {s:10.1f}   (bound k d/h = {cap * 2 * R / dt:10.1f})"
            )
    results["chain_front_speed"] = chain

    print("\n3. cost per contact (medians of 9 rounds of 20 calls, kernels interleaved)")
    cost = cost_per_contact() if 3 in args.parts else {}
    for k, v in cost.items():
        print(f"{k:32s} {v:10.2f}")
    results["cost"] = cost
    print("   with rolling and spinning friction (mu_r = 0.1, mu_s = 0.05)")
    cost_r = cost_per_contact(rolling=True) if 3 in args.parts else {}
    for k, v in cost_r.items():
        print(f"{k:32s} {v:10.2f}")
    results["cost_rolling"] = cost_r
    (args.out / "dem_c_study.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"\nresults: {args.out / 'dem_c_study.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
