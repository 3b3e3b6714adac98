"""Independent references for the physics tests: closed forms of physics.md §1–2, a fine RK4
integration of the normal-contact ODE, sampling/interpolation helpers and scene builders.

Nothing here calls pdem's force code: the references are written from the physics reference
only, so that the tests comparing pdem against them can fail.
"""

from __future__ import annotations

import math

import numpy as np

# default soft glass (the reference studies' softened E)
RHO = 2500.0
E_MOD = 5e7
NU = 0.3


# ---------------------------------------------------------------------------------------------
# effective quantities and closed forms (physics.md §1, §2)
# ---------------------------------------------------------------------------------------------


def sphere_mass(r: float, rho: float = RHO) -> float:
    return rho * 4.0 / 3.0 * math.pi * r**3


def e_star(e1: float = E_MOD, nu1: float = NU, e2: float = E_MOD, nu2: float = NU) -> float:
    """1/E* = (1 − ν_i²)/E_i + (1 − ν_j²)/E_j."""
    return 1.0 / ((1.0 - nu1**2) / e1 + (1.0 - nu2**2) / e2)


def reduced(a: float, b: float) -> float:
    """a b / (a + b) (R* or m*)."""
    return a * b / (a + b)


def hertz_stiffness(es: float, rs: float) -> float:
    """K in F = K δ^{3/2}: (4/3) E* sqrt(R*)."""
    return 4.0 / 3.0 * es * math.sqrt(rs)


def hertz_impact(m_eff: float, r_eff: float, es: float, v: float) -> tuple[float, float, float]:
    """Closed forms of an elastic Hertz impact at approach speed v: (α_max, F_max, t_c)."""
    alpha = (15.0 * m_eff * v**2 / (16.0 * es * math.sqrt(r_eff))) ** 0.4
    fmax = hertz_stiffness(es, r_eff) * alpha**1.5
    tc = 2.868 * (m_eff**2 / (r_eff * es**2 * v)) ** 0.2
    return alpha, fmax, tc


def damping_beta(e: float) -> float:
    """β = ln e / sqrt(ln² e + π²); the limit −1 for e = 0."""
    if e <= 0.0:
        return -1.0
    le = math.log(e)
    return le / math.sqrt(le * le + math.pi**2)


def rayleigh_time(r: float, rho: float = RHO, e: float = E_MOD, nu: float = NU) -> float:
    """T_R = π r sqrt(ρ/G) / (0.1631 ν + 0.8766), G = E / (2 (1 + ν))."""
    g = e / (2.0 * (1.0 + nu))
    return math.pi * r * math.sqrt(rho / g) / (0.1631 * nu + 0.8766)


# ---------------------------------------------------------------------------------------------
# RK4 reference of the normal contact
# ---------------------------------------------------------------------------------------------


def normal_impact_rk4(e: float, m_eff: float, r_eff: float, es: float, v: float, t_end: float,
                      steps_per_tc: int = 2000, clamp: bool = False) -> dict[str, float]:
    """Integrate m* δ'' = −F_n, F_n = (4/3) E* sqrt(R*) δ^{3/2} + c_n(δ) δ',
    c_n = −2 sqrt(5/6) β sqrt(2 E* sqrt(R* δ) m*), from δ = 0, δ' = v (approach speed) for t_end
    seconds (or until δ returns to 0: afterwards the spheres fly apart force-free). ``clamp``
    replaces F_n by max(F_n, 0).

    Fixed-step classical RK4 with h = t_c / steps_per_tc (t_c of the elastic impact); the last
    step is shortened to land exactly on t_end. Returns δ and δ' at t_end (δ' < 0: separating),
    whether the contact ended, the contact duration if it did, and the attractive (negative)
    normal impulse (∫ min(F_n, 0) dt).
    """
    beta = damping_beta(e)
    k = hertz_stiffness(es, r_eff)
    cfac = -2.0 * math.sqrt(5.0 / 6.0) * beta * math.sqrt(2.0 * es * math.sqrt(r_eff) * m_eff)

    def force(d: float, u: float) -> float:
        if d <= 0.0:
            return 0.0
        f = k * d**1.5 + cfac * d**0.25 * u
        return max(f, 0.0) if clamp else f

    def acc(d: float, u: float) -> float:
        return -force(d, u) / m_eff

    tc = hertz_impact(m_eff, r_eff, es, v)[2]
    h0 = tc / steps_per_tc
    t = 0.0
    d, u = 0.0, v
    attractive = 0.0
    ended = False
    duration = math.nan
    while t < t_end * (1.0 - 1e-15):
        h = min(h0, t_end - t)
        k1d, k1u = u, acc(d, u)
        k2d, k2u = u + 0.5 * h * k1u, acc(d + 0.5 * h * k1d, u + 0.5 * h * k1u)
        k3d, k3u = u + 0.5 * h * k2u, acc(d + 0.5 * h * k2d, u + 0.5 * h * k2u)
        k4d, k4u = u + h * k3u, acc(d + h * k3d, u + h * k3u)
        dn = d + h / 6.0 * (k1d + 2.0 * k2d + 2.0 * k3d + k4d)
        un = u + h / 6.0 * (k1u + 2.0 * k2u + 2.0 * k3u + k4u)
        fa, fb = force(d, u), force(max(dn, 0.0), un)
        attractive += 0.5 * h * (min(fa, 0.0) + min(fb, 0.0))
        if t > 0.0 and dn <= 0.0:
            # contact over: interpolate the crossing, then force-free flight at constant δ'
            s = d / (d - dn)
            duration = t + s * h
            ended = True
            u = un
            d = dn + un * (t_end - t - h)
            t = t_end
            break
        t += h
        d, u = dn, un
    return {"delta": d, "rate": u, "ended": ended, "duration": duration, "attractive_impulse": attractive}


# ---------------------------------------------------------------------------------------------
# sampling helpers
# ---------------------------------------------------------------------------------------------


def parabolic_peak(y: np.ndarray) -> float:
    """Maximum of the sampled signal refined by a parabola through the top sample and its
    neighbours (uniform sampling)."""
    y = np.asarray(y, float)
    k = int(np.argmax(y))
    if k == 0 or k == y.size - 1:
        return float(y[k])
    a, b, c = y[k - 1], y[k], y[k + 1]
    den = a - 2.0 * b + c
    if den == 0.0:
        return float(b)
    return float(b - (c - a) ** 2 / (8.0 * den))


def positive_interval(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Start and end of the (single) interval where the sampled y > 0, with the crossings
    interpolated linearly between samples."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    pos = np.flatnonzero(y > 0.0)
    assert pos.size, "signal never positive"
    a, b = int(pos[0]), int(pos[-1])
    assert a > 0 and b < y.size - 1, "positive interval not bracketed by the samples"
    assert np.all(y[a : b + 1] > 0.0), "more than one positive interval"
    t0 = t[a - 1] + (t[a] - t[a - 1]) * (-y[a - 1]) / (y[a] - y[a - 1])
    t1 = t[b] + (t[b + 1] - t[b]) * y[b] / (y[b] - y[b + 1])
    return float(t0), float(t1)


# ---------------------------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------------------------


def random_spheres(rng: np.random.Generator, n: int, lo, hi, rmin: float, rmax: float,
                   min_gap: float = 0.0, max_tries: int = 200000) -> tuple[np.ndarray, np.ndarray]:
    """n non-overlapping spheres (radii uniform in [rmin, rmax], placed largest first by random
    sequential addition) with centres in the box [lo + r, hi − r]."""
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    radii = np.sort(rng.uniform(rmin, rmax, n))[::-1]
    x = np.empty((n, 3))
    placed = 0
    tries = 0
    while placed < n:
        tries += 1
        if tries > max_tries:
            raise RuntimeError("random_spheres: box too small for the requested spheres")
        r = radii[placed]
        c = rng.uniform(lo + r, hi - r)
        if placed:
            d = np.linalg.norm(x[:placed] - c, axis=1)
            if np.any(d < radii[:placed] + r + min_gap):
                continue
        x[placed] = c
        placed += 1
    perm = rng.permutation(n)
    return x[perm], radii[perm]


def brute_force_touching(x: np.ndarray, r: np.ndarray, ids: np.ndarray) -> set[tuple[int, int]]:
    """All id pairs (lo, hi) whose spheres overlap (δ > 0), by an O(n²) numpy search."""
    d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=2)
    ov = r[:, None] + r[None, :] - d
    iu, ju = np.nonzero(np.triu(ov > 0.0, k=1))
    return {(int(min(ids[a], ids[b])), int(max(ids[a], ids[b]))) for a, b in zip(iu, ju, strict=True)}


def angular_momentum(p: dict[str, np.ndarray]) -> np.ndarray:
    """Orbital (about the origin) plus spin angular momentum of solid spheres."""
    orbital = np.sum(p["mass"][:, None] * np.cross(p["x"], p["v"]), axis=0)
    spin = np.sum((0.4 * p["mass"] * p["r"] ** 2)[:, None] * p["w"], axis=0)
    return orbital + spin
