"""Contract checks that every penalty contact law must pass; plugin authors reuse them.

    from pdem.testing.law_contract import check_law_against_twin
    check_law_against_twin(MyLaw(), my_force_numpy, materials)

The law's ``@njit`` force function (reached through its pair kernel on a two-particle scene) must
agree with the law's plain-Python twin on random contacts, history included, and must obey
Newton's third law through the generic loop (forces on i and j opposite, torques consistent).
"""

from __future__ import annotations

import numpy as np

from ..contact.law import ContactLaw
from ..materials import MaterialTable

__all__ = ["random_contacts", "check_law_against_twin"]


def random_contacts(rng: np.random.Generator, n: int, r_range=(4e-4, 6e-4)):
    """Random two-sphere contacts: positions, radii, velocities, spins (overlaps up to 2 % of r)."""
    out = []
    for _ in range(n):
        ri, rj = rng.uniform(*r_range, 2)
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        delta = rng.uniform(1e-4, 2e-2) * min(ri, rj)
        xi = rng.normal(scale=1e-3, size=3)
        xj = xi + normal * (ri + rj - delta)
        out.append((xi, xj, ri, rj, rng.normal(scale=0.05, size=(2, 3)), rng.normal(scale=20.0, size=(2, 3))))
    return out


def check_law_against_twin(
    law: ContactLaw,
    twin,
    materials: MaterialTable,
    *,
    mat=(0, 0),
    steps: int = 5,
    seed: int = 0,
    rtol: float = 1e-10,
    dt: float = 1e-6,
) -> int:
    """Compare ``law.pair_kernel`` with ``twin`` over random contacts for ``steps`` steps each.

    ``twin(delta, n, vrel, wrel, r_eff, m_eff, i_eff, coef_row, hist_row, dt) -> (F_on_j, M_on_j)``
    updates ``hist_row`` in place. Returns the number of contacts checked; raises AssertionError.
    """
    rng = np.random.default_rng(seed)
    coef = law.coefficients(materials)
    hsize = max(law.history_size, 1)
    checked = 0
    for xi, xj, ri, rj, v, w in random_contacts(rng, 50):
        x = np.array([xi, xj])
        r = np.array([ri, rj])
        rho = materials[mat[0]].density
        mass = rho * 4 / 3 * np.pi * r**3
        inv_m = 1 / mass
        inv_i = 1 / (0.4 * mass * r**2)
        hist = np.zeros((1, hsize))
        hist_twin = np.zeros(hsize)
        for _ in range(steps):
            f = np.zeros((2, 3))
            t = np.zeros((2, 3))
            fpair = np.zeros((1, 3))
            law.pair_kernel(
                np.array([0]),
                np.array([1]),
                hist,
                x,
                v,
                w,
                r,
                inv_m,
                inv_i,
                np.array(mat, dtype=np.int32),
                coef,
                f,
                t,
                fpair,
                dt,
                1.0,
            )
            d = x[1] - x[0]
            dist = np.linalg.norm(d)
            assert dist < r.sum()
            n = d / dist
            delta = r.sum() - dist
            ai, aj = r[0] - delta / 2, r[1] - delta / 2
            vrel = (v[1] - aj * np.cross(w[1], n)) - (v[0] + ai * np.cross(w[0], n))
            force, moment = twin(
                delta,
                n,
                vrel,
                w[1] - w[0],
                r[0] * r[1] / r.sum(),
                1 / inv_m.sum(),
                1 / inv_i.sum(),
                coef[mat[0], mat[1]],
                hist_twin,
                dt,
            )
            scale = max(np.abs(force).max(), 1e-30)
            assert np.allclose(f[1], force, rtol=rtol, atol=rtol * scale), (f[1], force)
            assert np.allclose(f[0], -force, rtol=rtol, atol=rtol * scale)
            tq_j = -aj * np.cross(n, force) + moment
            tq_i = -ai * np.cross(n, force) - moment
            tscale = max(np.abs(tq_j).max(), np.abs(tq_i).max(), scale * r.sum())
            assert np.allclose(t[1], tq_j, rtol=1e-9, atol=1e-9 * tscale)
            assert np.allclose(t[0], tq_i, rtol=1e-9, atol=1e-9 * tscale)
            assert np.allclose(
                hist[0, : law.history_size], hist_twin[: law.history_size], rtol=1e-9, atol=1e-15
            )
            checked += 1
            # move the pair a little to exercise the history; stop when the contact opens
            x = x + v * dt * 50
            if np.linalg.norm(x[1] - x[0]) >= r.sum():
                break
    return checked
