"""Jacobi's relaxation bound (``Stepper.jacobi_bound``): λ_max of B N against closed forms and a
dense eigenvalue computation of D M⁻¹ Dᵀ written here from the contact geometry alone."""

from __future__ import annotations

import numpy as np
import pytest

import pdem
from pdem.geometry import shapes

G = 9.81
R = 1e-3


def make_sim(mu=0.4, mu_r=0.0, dt=2e-4, **params):
    params.setdefault("scaling", "trace")  # the dense reference below forms the trace scaling
    sim = pdem.Simulation(law="complementarity", solver="jacobi", **params)
    sim.add_material(
        "glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.0, friction=mu,
        rolling_friction=mu_r,
    )
    sim.gravity = (0.0, 0.0, -G)
    sim.dt = dt
    return sim


def pile(mu_r=0.0, steps=120, **params):
    """A jittered 4 × 4 × 4 lattice dropped into a box and left to settle (many contacts)."""
    rng = np.random.default_rng(5)
    sim = make_sim(mu_r=mu_r, tolerance=1e-8, max_iterations=400, **params)
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    x = (g * 2.2 * R + 1.2 * R).astype(float) + rng.uniform(-0.08 * R, 0.08 * R, size=g.shape)
    radii = R * rng.uniform(0.85, 1.0, size=len(x))
    sim.add_particles(x, radii, material="glass")
    for k, plane in enumerate(shapes.box_planes((0, 0, 0), (9.2 * R, 9.2 * R, 20 * R))):
        sim.add_wall(plane, material="glass", name=f"side{k}")
    sim.run(steps=steps)
    return sim


def dense_operator(sim, active=True, normal_only=False):
    """N = D M⁻¹ Dᵀ and the rows' scaling B from the rows' geometry: contact c between bodies i
    (−1: a wall) and j, normal n, lever arms a_i n and −a_j n; rows u_n, u_t (3, in the tangent
    plane) and with rolling friction R* × the relative spin (3 rows tangential, 1 about n).
    ``normal_only``: the u_n rows alone (a frictionless problem)."""
    st = sim.integrator
    p = sim.particles
    nc = st.log[-1][3]
    width = st.gam.shape[1]
    nb = p.n
    rows, scale = [], []
    for c in range(nc):
        if active and not st.gam[c, 0] > 0.0:
            continue
        i, j = st.cb[c]
        n = st.cn[c]
        ai, aj = st.ca[c]
        proj = np.eye(3) - np.outer(n, n)

        def cross_mat(r):
            return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])

        # u = v_j + ω_j × (−a_j n) − (v_i + ω_i × (a_i n)); ω × r = −[r]× ω
        J = np.zeros((4, 6 * nb))
        full = np.zeros((3, 6 * nb))
        full[:, 6 * j : 6 * j + 3] = np.eye(3)
        full[:, 6 * j + 3 : 6 * j + 6] = cross_mat(aj * n)  # −[−a_j n]×
        if i >= 0:
            full[:, 6 * i : 6 * i + 3] = -np.eye(3)
            full[:, 6 * i + 3 : 6 * i + 6] = cross_mat(ai * n)  # −(−[a_i n]×)
        J[0] = n @ full
        J[1:4] = proj @ full
        if normal_only:
            rows.append(J[:1])
            scale.append(st.cscale[c])
            continue
        rows.append(J)
        scale += [st.cscale[c]] * 4
        if width == 8 and st.croll[c, 3] > 0.0:
            spin = np.zeros((3, 6 * nb))
            spin[:, 6 * j + 3 : 6 * j + 6] = np.eye(3)
            if i >= 0:
                spin[:, 6 * i + 3 : 6 * i + 6] = -np.eye(3)
            Jr = np.zeros((4, 6 * nb))  # R* × the relative spin: rows in m/s
            Jr[0:3] = st.croll[c, 2] * (proj @ spin)
            Jr[3] = st.croll[c, 2] * (n @ spin)
            rows.append(Jr)
            scale += [st.croll[c, 3]] * 4
    D = np.vstack(rows)
    minv = np.repeat(np.stack([p.inv_m[:nb]] * 3 + [p.inv_i[:nb]] * 3, axis=1).reshape(-1), 1)
    return D @ (minv[:, None] * D.T), np.array(scale)


def dense_bound(sim, active=True, normal_only=False):
    """λ_max of B^½ D M⁻¹ Dᵀ B^½ (:func:`dense_operator`)."""
    N, B = dense_operator(sim, active, normal_only)
    b = np.sqrt(B)
    return float(np.linalg.eigvalsh(b[:, None] * N * b[None, :]).max())


def test_sphere_on_a_floor_has_the_closed_form_bound():
    """One contact with a fixed floor: B = 3/trace = 3m/8; N's normal entry 1/m (B N: 3/8), its
    tangential entries 1/m + a²/I = 7/(2m) (B N: 21/16), so λ_max = 21/16 and ω < 32/21."""
    sim = make_sim(tolerance=1e-10)
    sim.add_particles([[0.0, 0.0, R]], R, material="glass")
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), material="glass", name="floor")
    sim.run(steps=3)
    assert sim.integrator.gam[0, 0] > 0.0
    assert sim.integrator.jacobi_bound() == pytest.approx(21.0 / 16.0, rel=1e-12)


def test_block_scaling_bound_of_a_sphere_on_a_floor_is_one():
    """With ``scaling = "block"`` each row is scaled by the inverse of its own diagonal entry of the
    Delassus block (B_n = m, B_t = 2m/7 for a solid sphere on a fixed floor): B N = I, λ_max = 1."""
    sim = make_sim(tolerance=1e-10, scaling="block")
    sim.add_particles([[0.0, 0.0, R]], R, material="glass")
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), material="glass", name="floor")
    sim.run(steps=3)
    assert sim.integrator.gam[0, 0] > 0.0
    assert sim.integrator.jacobi_bound() == pytest.approx(1.0, rel=1e-12)


@pytest.mark.parametrize("mu_r", [0.0, 0.05])
def test_pile_bound_matches_a_dense_eigenvalue_computation(mu_r):
    sim = pile(mu_r=mu_r)
    st = sim.integrator
    nc = st.log[-1][3]
    active = int(np.count_nonzero(st.gam[:nc, 0] > 0.0))
    assert active > 60 and active < nc  # a pile, and rows in the problem that carry nothing
    for act in (True, False):
        ref = dense_bound(sim, active=act)
        assert st.jacobi_bound(active=act, iterations=3000) == pytest.approx(ref, rel=1e-6), act
    # the active set's bound is the tighter one that matters: more rows only raise λ_max
    assert dense_bound(sim, active=True) <= dense_bound(sim, active=False) * (1 + 1e-12)


def test_bound_leaves_the_state_and_the_run_unchanged():
    a = pile(steps=60)
    b = pile(steps=60)
    v0 = a.particles.v.copy()
    a.integrator.jacobi_bound()
    assert np.array_equal(a.particles.v, v0)
    a.run(steps=20)
    b.run(steps=20)
    assert np.array_equal(a.particles.x, b.particles.x)
    assert np.array_equal(a.particles.v, b.particles.v)


def test_jacobi_converges_below_the_bound_and_diverges_above_it():
    """On the pile's active set held fixed (the linear part N γ + r = 0 with every row kept, no
    projection), Jacobi's sweep γ ← γ − ω B (N γ − r) stays bounded for ω λ_max < 2 and diverges
    beyond: the meaning of the bound. On the normal rows (built here from the geometry), whose
    λ_max cannot exceed the full problem's."""
    sim = pile()
    lam = sim.integrator.jacobi_bound(iterations=3000)
    assert lam == pytest.approx(dense_bound(sim), rel=1e-6)
    # the normal rows only (a frictionless problem): their spectrum lies within the full one's
    N, B = dense_operator(sim, normal_only=True)
    lam_n = dense_bound(sim, normal_only=True)
    assert lam_n <= lam * (1 + 1e-9)
    rhs = np.ones(len(B))
    for omega, grows in ((0.95 * 2.0 / lam_n, False), (1.05 * 2.0 / lam_n, True)):
        g = np.zeros(len(B))
        for _ in range(3000):
            g = g - omega * B * (N @ g - rhs)
        res = np.linalg.norm(N @ g - rhs)
        assert (res > 1e3) == grows, omega
