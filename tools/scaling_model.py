"""The scaling model of pdem's decomposition: fitted on 1–2 ranks, checked on every rank count
measured, and used to predict strong and weak scaling (``tools/scaling.py model FILE…``).

Per rank r of P, with the grid ``dims`` pdem chooses for the grains' extent E
(:func:`pdem.parallel.decomposition.choose_dims`) and subdomains of equal width L_d = E_d / dims_d
(pdem cuts at count quantiles: equal widths for a uniform packing), f_d ∈ {0, 1, 2} the faces of
the subdomain along d that have a neighbour, n the grains' number density, g the ghost width
(2 r_max + skin), λ the listed pairs per grain and ⟨|Δx_d|⟩ their mean extent along d (all from the
one-rank run):

* owned grains        N_r = n Π L_d
* ghosts              G_r = n [Π (L_d + f_d g) − Π L_d]
* pairs with a ghost  X_r = Σ_d f_d A_d n λ ⟨|Δx_d|⟩  (A_d the face area: pairs crossing it, listed on
                      both ranks: the duplicated pair work bitwise identity costs)
* listed pairs        L_r = λ N_r + X_r / 2
* forward messages    Σ_d f_d per forward, 72 B per ghost sent (x, v, ω)
* CPU time of the force computation per step: a L_r + b (N_r + G_r), a and b fitted on the 1- and
  2-rank runs; the rest of a step (integration, list upkeep) ρ N_r from the 1-rank run;
* wall time per step: the slowest rank's CPU time + its forward (latency per message + bytes at
  the bandwidth) + the collectives per step × an Allreduce's latency, with latencies and bandwidth
  measured on the same machine (``scaling.py`` times them) or, for a cluster, assumed (printed).
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np

from pdem.parallel.decomposition import choose_dims

COLLECTIVE = ("Allreduce", "allreduce", "Allgather", "allgather", "bcast", "Barrier", "alltoall")
#: a cluster's network, assumed for the predictions (InfiniBand-class): point-to-point latency [s],
#: bandwidth [B/s], Allreduce latency per doubling of the ranks [s]
CLUSTER = {"alpha": 2e-6, "bandwidth": 10e9, "allreduce_per_level": 2.5e-6}


def _runs(paths):
    """The runs of the measurement files; of repeats at one rank count, law and scene, the one with
    the median wall time."""
    groups: dict[tuple, list[dict]] = {}
    for path in paths:
        data = json.loads(Path(path).read_text())
        for run in data["runs"]:
            run = {"law": data["law"], "scene": data.get("scene", "bed"), **run}
            groups.setdefault((run["law"], run["scene"], run["ranks"][0]["ranks"]), []).append(run)
    out = []
    for runs in groups.values():
        runs.sort(key=lambda r: max(q["wall"] for q in r["ranks"]))
        out.append(runs[len(runs) // 2])
    return out


class Geometry:
    """What the model takes from the one-rank run."""

    def __init__(self, one: dict) -> None:
        r = one["ranks"][0]
        lo, hi = (np.array(b) for b in r["bounds"])
        self.extent = hi - lo + 2 * 0.5e-3  # centres' box widened by a grain radius
        self.n_total = r["owned"]
        self.n = self.n_total / float(np.prod(self.extent))
        self.g = r["ghost_width"]
        self.lam = r["pairs"] / r["owned"]
        self.dx = np.array(r["mean_abs_dx"])
        self.periodic = r.get("scene") == "periodic"

    def scaled(self, n_total: float) -> Geometry:
        """The same packing in a box of the same shape holding ``n_total`` grains."""
        other = Geometry.__new__(Geometry)
        other.__dict__.update(self.__dict__)
        other.extent = self.extent * (n_total / self.n_total) ** (1 / 3)
        other.n_total = n_total
        return other

    def dims(self, ranks: int) -> tuple[int, int, int]:
        return tuple(choose_dims(ranks, self.extent, (self.periodic,) * 3, self.g))

    def ranks(self, ranks: int, dims=None) -> list[dict]:
        """Predicted counts per rank (row-major over the grid, as MPI's Cartesian ranks)."""
        dims = dims or self.dims(ranks)
        L = self.extent / np.array(dims)
        out = []
        for c in itertools.product(*(range(k) for k in dims)):
            if self.periodic:
                f = np.full(3, 2.0)
                talk = np.array([2.0 if k > 1 else 0.0 for k in dims])
            else:
                f = np.array([(c[d] > 0) + (c[d] < dims[d] - 1) for d in range(3)], float)
                talk = f
            owned = self.n * np.prod(L)
            ghosts = self.n * (np.prod(L + f * self.g) - np.prod(L))
            area = np.array([L[1] * L[2], L[0] * L[2], L[0] * L[1]])
            cross = float(np.sum(f * area * self.n * self.lam * self.dx))
            out.append({
                "owned": owned, "ghosts": ghosts, "pairs_with_ghost": cross,
                "pairs": self.lam * owned + cross / 2, "messages": float(talk.sum()),
                "bytes": 72.0 * ghosts * (talk.sum() / max(f.sum(), 1e-300)),
            })  # fmt: skip
        return out


def _measured(run: dict) -> list[dict]:
    out = []
    for r in sorted(run["ranks"], key=lambda q: q["rank"]):
        steps = r["steps"]
        out.append({
            "owned": r["owned"], "ghosts": r["ghosts"], "pairs_with_ghost": r["pairs_with_ghost"],
            "pairs": r["pairs"],
            "messages": r["calls"].get("Isend", 0) / steps,
            "bytes": r["bytes"].get("Isend", 0) / steps,
            "collectives": sum(r["calls"].get(k, 0) for k in COLLECTIVE) / steps,
            "cpu": r["cpu_forces"] / steps, "wall": r["wall"] / steps,
        })  # fmt: skip
    return out


def fit_compute(runs: list[dict]) -> tuple[float, float]:
    """a (s per listed pair) and b (s per grain held) of the force computation's CPU time, least
    squares over every rank of the 1- and 2-rank runs."""
    rows, y = [], []
    for run in runs:
        if run["ranks"][0]["ranks"] <= 2:
            for m in _measured(run):
                rows.append([m["pairs"], m["owned"] + m["ghosts"]])
                y.append(m["cpu"])
    A, y = np.array(rows, float), np.array(y)
    (a, b), *_ = np.linalg.lstsq(A, y, rcond=None)
    if a < 0 or b < 0:  # the two are nearly proportional on 1-2 ranks: one term, the better one
        fits = []
        for col in (0, 1):
            c = float(A[:, col] @ y / (A[:, col] @ A[:, col]))
            fits.append((float(np.sum((A[:, col] * c - y) ** 2)), col, c))
        _, col, c = min(fits)
        a, b = (c, 0.0) if col == 0 else (0.0, c)
    return float(a), float(b)


def step_time(geo: Geometry, ranks: int, a: float, b: float, rho: float, net: dict, coll: float,
              dims=None) -> float:  # fmt: skip
    """Modelled wall time per step on ``ranks`` ranks."""
    if ranks == 1:
        (r,) = geo.ranks(1)
        return a * r["pairs"] + b * (r["owned"] + r["ghosts"]) + rho * r["owned"]
    worst = 0.0
    for r in geo.ranks(ranks, dims):
        t = a * r["pairs"] + b * (r["owned"] + r["ghosts"]) + rho * r["owned"]
        t += r["messages"] * net["alpha"] + r["bytes"] / net["bandwidth"]
        worst = max(worst, t)
    return worst + coll * net["allreduce_per_level"] * math.log2(ranks)


def report_dem_c(runs: list[dict], geo: Geometry) -> None:
    """DEM-C: per solver iteration, a sweep over the listed pairs, a forward of the ghosts' v and ω
    and the solver's collectives (Jacobi's convergence test, APGD's dot products); fitted on the
    one-rank run (seconds per pair and iteration), checked at 2 ranks, predicted like DEM-P."""
    one = [r for r in runs if r["ranks"][0]["ranks"] == 1]
    if not one:
        return
    r1 = one[0]["ranks"][0]
    its = r1["iterations"] / r1["steps"]
    c_it = r1["wall"] / r1["steps"] / its / r1["pairs"]
    print(f"\nDEM-C: {its:.0f} iterations a step, {c_it * 1e9:.1f} ns per listed pair and iteration (1 rank)")
    per_it = {}
    for run in runs:
        k = run["ranks"][0]["ranks"]
        if k == 1:
            continue
        meas = _measured(run)
        steps_its = run["ranks"][0]["steps"] * its
        coll = np.mean([m["collectives"] * run["ranks"][0]["steps"] / steps_its for m in meas])
        msgs = np.mean([m["messages"] * run["ranks"][0]["steps"] / steps_its for m in meas])
        per_it[k] = (coll, msgs)
        lat = run["ranks"][0].get("latency") or {}
        model = geo.ranks(k, tuple(run["ranks"][0]["dims"]))
        worst = 0.0
        for q in model:
            t = c_it * q["pairs"] + q["messages"] * lat.get("p2p_64B", 0.0)
            t += 48.0 * q["ghosts"] / (1048576 / lat["p2p_1MiB"] if lat.get("p2p_1MiB") else math.inf)
            worst = max(worst, t)
        t = its * (worst + coll * lat.get("allreduce", 0.0))
        wall = max(m["wall"] for m in meas)
        print(f"  {k} ranks: {coll:.2f} collectives and {msgs:.2f} messages per iteration; wall per step "
              f"model {t * 1e3:.2f} ms, measured {wall * 1e3:.2f} ms ({t / wall - 1:+.1%})")
    if not per_it:
        return
    coll = float(np.mean([v[0] for v in per_it.values()]))
    print(f"  predictions at {its:.0f} iterations a step (the count grows with the packing's size for a given"
          " accuracy; held fixed here):")
    for total in (1e6, 1e8):
        g = geo.scaled(total)
        t1 = its * c_it * g.lam * total
        line = []
        for k in (64, 512, 1024):
            net = CLUSTER
            worst = max(
                c_it * q["pairs"] + q["messages"] * net["alpha"] + 48.0 * q["ghosts"] / net["bandwidth"]
                for q in g.ranks(k)
            )
            t = its * (worst + coll * CLUSTER["allreduce_per_level"] * math.log2(k))
            line.append(f"{k} ranks {t * 1e3:.1f} ms (efficiency {t1 / t / k:.0%})")
        print(f"    {total:.0e} grains, one rank {t1:.2f} s a step: " + "; ".join(line))


def report(paths) -> None:
    every = _runs(paths)
    runs = [r for r in every if r["law"] == "dem-p"]
    if not runs:
        c = [r for r in every if r["law"] == "dem-c"]
        report_dem_c(c, Geometry([r for r in c if r["ranks"][0]["ranks"] == 1][0]))
        return
    one = [r for r in runs if r["ranks"][0]["ranks"] == 1]
    if not one:
        raise SystemExit("the model needs a one-rank run")
    geo = Geometry(one[0])
    a, b = fit_compute(runs)
    m1 = _measured(one[0])[0]
    rho = max(m1["wall"] - m1["cpu"], 0.0) / m1["owned"]
    extent = np.round(geo.extent * 1e3, 1).tolist()
    print(f"scene {one[0]['scene']}: {geo.n_total} grains, extent {extent} mm, "
          f"ghost width {geo.g * 1e3:.3f} mm, {geo.lam:.2f} listed pairs per grain, "
          f"<|dx|> {np.round(geo.dx * 1e3, 3).tolist()} mm")  # fmt: skip
    print(f"fitted: {a * 1e9:.1f} ns per listed pair, {b * 1e9:.1f} ns per grain held (forces), "
          f"{rho * 1e9:.1f} ns per owned grain (rest of the step)")
    print("\ncounts, model / measured (mean over ranks; max over ranks):")
    print(f"{'ranks':>5} {'dims':>9} {'owned':>13} {'ghosts':>13} {'pairs':>13} {'with ghost':>13} "
          f"{'messages':>13} {'bytes':>13} {'cpu':>13}")  # fmt: skip
    worst = {}
    for run in sorted(runs, key=lambda q: q["ranks"][0]["ranks"]):
        k = run["ranks"][0]["ranks"]
        dims = tuple(run["ranks"][0]["dims"])
        meas = _measured(run)
        model = geo.ranks(k, dims)
        for p in model:
            p["cpu"] = a * p["pairs"] + b * (p["owned"] + p["ghosts"])
        cells = []
        for key in ("owned", "ghosts", "pairs", "pairs_with_ghost", "messages", "bytes", "cpu"):
            mv = np.array([m[key] for m in meas], float)
            pv = np.array([p[key] for p in model], float)
            if mv.mean() == 0 and pv.mean() == 0:
                cells.append(f"{'—':>13}")
                continue
            ratio_mean = pv.mean() / mv.mean() if mv.mean() else math.inf
            ratio_max = pv.max() / mv.max() if mv.max() else math.inf
            if k > 1 or key in ("owned", "pairs", "cpu"):
                worst[key] = max(worst.get(key, 0.0), abs(ratio_mean - 1), abs(ratio_max - 1))
            cells.append(f"{ratio_mean:6.3f};{ratio_max:6.3f}")
        print(f"{k:>5} {str(list(dims)):>9} " + " ".join(cells))
    print("largest deviation per quantity: " + ", ".join(f"{k} {v * 100:.1f} %" for k, v in worst.items()))
    # wall time at 1 and 2 ranks (no core shared), with the latencies measured in the same run
    print("\nwall time per step, model against measured (latencies measured in the run):")
    for run in sorted(runs, key=lambda q: q["ranks"][0]["ranks"]):
        k = run["ranks"][0]["ranks"]
        if k > 2:
            continue
        meas = _measured(run)
        lat = run["ranks"][0].get("latency") or {}
        net = {"alpha": lat.get("p2p_64B", 0.0),
               "bandwidth": 1048576 / lat["p2p_1MiB"] if lat.get("p2p_1MiB") else math.inf,
               "allreduce_per_level": lat.get("allreduce", 0.0)}  # fmt: skip
        coll = float(np.mean([m["collectives"] for m in meas]))
        t = step_time(geo, k, a, b, rho, net, coll, tuple(run["ranks"][0]["dims"]))
        wall = max(m["wall"] for m in meas)
        print(f"  {k} rank(s): model {t * 1e6:8.1f} µs, measured {wall * 1e6:8.1f} µs ({t / wall - 1:+.1%})"
              + (f"; latencies: Allreduce {net['allreduce_per_level'] * 1e6:.1f} µs, "
                 f"64 B {net['alpha'] * 1e6:.1f} µs,"
                 f" 1 MiB {lat.get('p2p_1MiB', 0) * 1e6:.0f} µs" if k > 1 else ""))  # fmt: skip
    many = [run for run in runs if run["ranks"][0]["ranks"] > 1]
    coll = float(np.mean([m["collectives"] for run in many for m in _measured(run)]))
    print(f"\ncollectives per step: {coll:.2f}; predictions assume a network with {CLUSTER}")
    predict(geo, a, b, rho, coll)
    report_dem_c([r for r in every if r["law"] == "dem-c"], geo)


def predict(geo: Geometry, a: float, b: float, rho: float, coll: float) -> None:
    """Strong scaling of 10⁶ and 10⁸ grains and weak scaling at 10⁵ grains per rank, to 1,024 ranks."""
    ranks = [1, 2, 8, 64, 512, 1024]
    for total in (1e6, 1e8):
        g = geo.scaled(total)
        t1 = step_time(g, 1, a, b, rho, CLUSTER, coll)
        print(f"\nstrong scaling, {total:.0e} grains (one rank: {t1 * 1e3:.1f} ms a step):")
        for k in ranks:
            t = step_time(g, k, a, b, rho, CLUSTER, coll)
            r = g.ranks(k)
            ghost = max(q["ghosts"] / q["owned"] for q in r)
            dup = sum(q["pairs_with_ghost"] for q in r) / 2 / (g.lam * total)
            grid = str(list(g.dims(k)))
            print(f"  {k:>5} ranks {grid:>14}: {t * 1e3:9.3f} ms a step, speed-up {t1 / t:8.1f}, "
                  f"efficiency {t1 / t / k:6.1%}, ghosts/owned {ghost:6.1%}, "
                  f"duplicated pairs {dup:6.2%}")  # fmt: skip
    print("\nweak scaling, 10⁵ grains per rank:")
    base = step_time(geo.scaled(1e5), 1, a, b, rho, CLUSTER, coll)
    for k in ranks:
        g = geo.scaled(1e5 * k)
        t = step_time(g, k, a, b, rho, CLUSTER, coll)
        print(f"  {k:>5} ranks ({1e5 * k:.0e} grains): {t * 1e3:8.3f} ms a step, efficiency {base / t:6.1%}")
