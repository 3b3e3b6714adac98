r"""Sphere–wall contact geometry: numba kernels on flat parameter arrays.

Every wall is described by an integer ``kind`` and a float64 parameter vector ``p`` of length
:data:`N_PARAMS` (unused trailing entries are zero). The kernel :func:`wall_contact` takes only
arrays and scalars so that it can be inlined into the contact loops; :func:`wall_contact_numpy` is
its vectorised pure-NumPy twin (same formulas, same operation order, used by tests).

Conventions (see ``physics.md`` §1; the wall is the partner *j* of an infinite radius)
---------------------------------------------------------------------------------------
For a sphere of centre x and radius r the kernel returns ``(gap, nx, ny, nz, cx, cy, cz)``:

* ``gap`` φ = (distance from the centre to the wall surface) − r; the overlap is δ = −φ.
* ``n`` = unit vector from the sphere centre towards the contact point, i.e. pointing *into* the
  wall; the wall pushes the sphere along −n.
* ``c`` = the closest point of the wall surface. Always ``c = x + (φ + r) n``.

One-sided kinds (plane, infinite cylinder) return a *signed* gap: the centre distance is measured
positive on the side where particles live, so a centre that has crossed the surface gives
φ < −r (a large overlap) and n still points into the wall, which pushes the particle back.
Two-sided thin shells (rectangle, revolved) use the unsigned distance to the closest point of the
finite surface, edges and rims included.

Parameter layout per kind (indices into ``p``)
----------------------------------------------
``KIND_PLANE = 0`` — infinite plane, one-sided half-space
    p[0:3] point on the plane, p[3:6] unit normal N pointing INTO the region where particles live.
    d = (x − p₀)·N,  φ = d − r,  n = −N,  c = x − d N.

``KIND_RECTANGLE = 1`` — finite flat plate, two-sided thin shell
    p[0:3] centre C, p[3:6] unit normal N, p[6:9] unit in-plane axis U (U ⊥ N), p[9] half-extent
    h_u along U, p[10] half-extent h_v along V = N × U.
    With ξ = x − C: a = ξ·U, b = ξ·V, h = ξ·N; a* = clamp(a, ±h_u), b* = clamp(b, ±h_v);
    Δ = (a* − a) U + (b* − b) V − h N,  φ = |Δ| − r,  n = Δ/|Δ|,  c = C + a* U + b* V.
    Degenerate direction: a centre exactly on the plate (|Δ| = 0) is treated as lying on the +N
    side: n = −N.

``KIND_REVOLVED = 2`` — surface of revolution of the meridian segment (s0, ρ0)–(s1, ρ1),
two-sided thin shell, open (no caps)
    p[0:3] axis point A, p[3:6] unit axis direction E, p[6] s0, p[7] ρ0, p[8] s1, p[9] ρ1
    (s: coordinate along E from A; ρ ≥ 0: distance from the axis). Disk: s0 = s1, ρ0 = 0;
    annulus: s0 = s1; tube: ρ0 = ρ1; cone: ρ0 = 0; frustum: general.
    With ξ = x − A: s = ξ·E, w = ξ − s E, ρ = |w|, ŵ = w/ρ. The distance from x to a point of the
    surface at azimuth offset Δθ is minimal for Δθ = 0 (ρ' ≥ 0), so the problem reduces to the
    closest point of the segment in the meridian half-plane:
    t = (s1 − s0, ρ1 − ρ0), λ = clamp(((s, ρ) − (s0, ρ0))·t/|t|², 0, 1), q = (s0, ρ0) + λ t.
    Inside the segment (0 < λ < 1) the distance uses the meridian normal
    m = (t_ρ, −t_s)/|t| (the segment direction turned by −90°): h = ((s, ρ) − (s0, ρ0))·m,
    |Δ| = |h|, Δ̂ = −sign(h) m; at an end (rim circle) Δ = q − (s, ρ).
    φ = |Δ| − r,  n = Δ̂_s E + Δ̂_ρ ŵ,  c = A + q_s E + q_ρ ŵ.
    The "+m side" is: +E for a disk/annulus with ρ0 < ρ1 (s0 = s1); the inside (m_ρ < 0) for any
    tube, cone or frustum with s0 < s1.
    Degenerate directions: a centre exactly on the surface (|Δ| = 0) is treated as lying on the
    +m side: n = −m (meridian components). A centre exactly on the axis (ρ = 0) uses the
    deterministic radial direction ŵ = :func:`unit_perp` (E) (Gram–Schmidt of the coordinate axis
    least aligned with E); a zero-length segment (|t| = 0, a bare circle) uses m = (1, 0).

``KIND_CYLINDER = 3`` — infinite circular cylinder, one-sided
    p[0:3] axis point A, p[3:6] unit axis direction E, p[6] radius R, p[7] side σ: +1 particles
    live inside (ρ < R), −1 outside.
    d = σ (R − ρ),  φ = d − r,  n = σ ŵ,  c = A + s E + R ŵ  (s, ρ, ŵ as for the revolved kind;
    ρ = 0 uses ŵ = unit_perp(E)).

``KIND_SPHERE = 4`` — sphere, one-sided
    p[0:3] centre C, p[3] radius R, p[4] side σ: +1 particles live outside, −1 inside.
    With ξ = x − C, ρ = |ξ|, ξ̂ = ξ/ρ: d = σ (ρ − R),  φ = d − r,  n = −σ ξ̂,  c = C + R ξ̂.
    ρ = 0 uses ξ̂ = (0, 0, 1).

``KIND_TRIANGLE = 5`` — triangle, two-sided thin shell (a facet of a mesh wall)
    p[0:3] vertex A, p[3:6] edge vector E1 = B − A, p[6:9] edge vector E2 = C − A.
    c = the closest point of the triangle (Voronoi regions of vertices, edges and face),
    Δ = c − x,  φ = |Δ| − r,  n = Δ/|Δ|; a centre exactly on the triangle uses n = −N, N the unit
    face normal E1 × E2/|E1 × E2|. :func:`triangle_contact` also reports whether c lies inside the
    face (not on an edge or a vertex), which mesh walls use to count each touching grain once.

Every kind keeps its anchor point in p[0:3]; :data:`PARAM_LAYOUT` says which other entries are
points (moved by translations and rotations), direction vectors (turned by rotations) or lengths,
so walls move and turn generically (:class:`pdem.geometry.walls.Wall`).

The kernels assume normalised direction vectors (the shape classes of
:mod:`pdem.geometry.shapes` normalise and validate them).
"""

from __future__ import annotations

import math

import numpy as np

from pdem._jit import njit

__all__ = [
    "KIND_PLANE",
    "KIND_RECTANGLE",
    "KIND_REVOLVED",
    "KIND_CYLINDER",
    "KIND_SPHERE",
    "KIND_TRIANGLE",
    "KIND_NAMES",
    "PARAM_LAYOUT",
    "triangle_contact",
    "surface_velocity",
    "wall_gaps",
    "N_PARAMS",
    "unit_perp",
    "wall_contact",
    "wall_contact_numpy",
]

KIND_PLANE = 0
KIND_RECTANGLE = 1
KIND_REVOLVED = 2
KIND_CYLINDER = 3
KIND_SPHERE = 4
KIND_TRIANGLE = 5

KIND_NAMES = {
    KIND_PLANE: "plane",
    KIND_RECTANGLE: "rectangle",
    KIND_REVOLVED: "revolved",
    KIND_CYLINDER: "cylinder",
    KIND_SPHERE: "sphere",
    KIND_TRIANGLE: "triangle",
}

N_PARAMS = 16

#: per kind: (slots of 3-vectors that are directions or edge vectors, turned by rotations; the
#: anchor point p[0:3] is moved by translations and rotations)
PARAM_LAYOUT = {
    KIND_PLANE: (3,),
    KIND_RECTANGLE: (3, 6),
    KIND_REVOLVED: (3,),
    KIND_CYLINDER: (3,),
    KIND_SPHERE: (),
    KIND_TRIANGLE: (3, 6),
}


@njit
def unit_perp(ex: float, ey: float, ez: float) -> tuple[float, float, float]:
    r"""Deterministic unit vector perpendicular to the unit vector E.

    Takes the coordinate axis ê_k with the smallest |E_k| (ties: x before y before z) and returns
    q/|q| with q = ê_k − E_k E (one Gram–Schmidt step). For E = ±ẑ this is x̂.
    """
    ax = abs(ex)
    ay = abs(ey)
    az = abs(ez)
    if ax <= ay and ax <= az:
        qx = 1.0 - ex * ex
        qy = -ex * ey
        qz = -ex * ez
    elif ay <= az:
        qx = -ey * ex
        qy = 1.0 - ey * ey
        qz = -ey * ez
    else:
        qx = -ez * ex
        qy = -ez * ey
        qz = 1.0 - ez * ez
    qn = math.sqrt(qx * qx + qy * qy + qz * qz)
    return qx / qn, qy / qn, qz / qn


@njit
def _axial_frame(p: np.ndarray, x0: float, x1: float, x2: float) -> tuple[float, float, float, float, float]:
    """Axial coordinate s, radius ρ and radial unit vector ŵ of a point about the axis p[0:6]."""
    ex = p[3]
    ey = p[4]
    ez = p[5]
    rx = x0 - p[0]
    ry = x1 - p[1]
    rz = x2 - p[2]
    s = rx * ex + ry * ey + rz * ez
    wx = rx - s * ex
    wy = ry - s * ey
    wz = rz - s * ez
    rho = math.sqrt(wx * wx + wy * wy + wz * wz)
    if rho > 0.0:
        wx = wx / rho
        wy = wy / rho
        wz = wz / rho
    else:
        wx, wy, wz = unit_perp(ex, ey, ez)
    return s, rho, wx, wy, wz


@njit
def wall_contact(
    kind: int, p: np.ndarray, x0: float, x1: float, x2: float, r: float
) -> tuple[float, float, float, float, float, float, float]:
    """Gap, contact normal and contact point of a sphere against one wall.

    Parameters
    ----------
    kind : one of ``KIND_PLANE``, ``KIND_RECTANGLE``, ``KIND_REVOLVED``, ``KIND_CYLINDER``.
    p : float64 array of length ``N_PARAMS`` laid out as in the module docstring.
    x0, x1, x2 : sphere centre [m].
    r : sphere radius [m].

    Returns
    -------
    (gap, nx, ny, nz, cx, cy, cz): gap φ [m] (overlap δ = −φ), unit normal from the centre into the
    wall, closest point of the wall surface [m]; ``c = x + (φ + r) n``. Unknown kinds raise
    ``ValueError``.
    """
    if kind == KIND_PLANE:
        nx = p[3]
        ny = p[4]
        nz = p[5]
        d = (x0 - p[0]) * nx + (x1 - p[1]) * ny + (x2 - p[2]) * nz
        return d - r, -nx, -ny, -nz, x0 - d * nx, x1 - d * ny, x2 - d * nz
    elif kind == KIND_RECTANGLE:
        nx = p[3]
        ny = p[4]
        nz = p[5]
        ux = p[6]
        uy = p[7]
        uz = p[8]
        hu = p[9]
        hv = p[10]
        vx = ny * uz - nz * uy
        vy = nz * ux - nx * uz
        vz = nx * uy - ny * ux
        rx = x0 - p[0]
        ry = x1 - p[1]
        rz = x2 - p[2]
        a = rx * ux + ry * uy + rz * uz
        b = rx * vx + ry * vy + rz * vz
        h = rx * nx + ry * ny + rz * nz
        ac = min(max(a, -hu), hu)
        bc = min(max(b, -hv), hv)
        da = ac - a
        db = bc - b
        dh = -h
        dist = math.sqrt(da * da + db * db + dh * dh)
        if dist > 0.0:
            gx = (da * ux + db * vx + dh * nx) / dist
            gy = (da * uy + db * vy + dh * ny) / dist
            gz = (da * uz + db * vz + dh * nz) / dist
        else:
            gx = -nx
            gy = -ny
            gz = -nz
        cx = p[0] + ac * ux + bc * vx
        cy = p[1] + ac * uy + bc * vy
        cz = p[2] + ac * uz + bc * vz
        return dist - r, gx, gy, gz, cx, cy, cz
    elif kind == KIND_REVOLVED:
        s, rho, wx, wy, wz = _axial_frame(p, x0, x1, x2)
        s0 = p[6]
        r0 = p[7]
        ts = p[8] - s0
        tr = p[9] - r0
        l2 = ts * ts + tr * tr
        ps = s - s0
        pr = rho - r0
        if l2 > 0.0:
            ll = math.sqrt(l2)
            ms = tr / ll
            mr = -ts / ll
            lam = (ps * ts + pr * tr) / l2
        else:
            ms = 1.0
            mr = 0.0
            lam = 0.0
        if lam > 0.0 and lam < 1.0:
            qs = s0 + lam * ts
            qr = r0 + lam * tr
            h = ps * ms + pr * mr
            dist = abs(h)
            if h < 0.0:
                gs = ms
                gr = mr
            else:
                gs = -ms
                gr = -mr
        else:
            if lam <= 0.0:
                qs = s0
                qr = r0
            else:
                qs = p[8]
                qr = p[9]
            ds = qs - s
            dr = qr - rho
            dist = math.sqrt(ds * ds + dr * dr)
            if dist > 0.0:
                gs = ds / dist
                gr = dr / dist
            else:
                gs = -ms
                gr = -mr
        ex = p[3]
        ey = p[4]
        ez = p[5]
        return (
            dist - r,
            gs * ex + gr * wx,
            gs * ey + gr * wy,
            gs * ez + gr * wz,
            p[0] + qs * ex + qr * wx,
            p[1] + qs * ey + qr * wy,
            p[2] + qs * ez + qr * wz,
        )
    elif kind == KIND_CYLINDER:
        s, rho, wx, wy, wz = _axial_frame(p, x0, x1, x2)
        big_r = p[6]
        side = p[7]
        d = side * (big_r - rho)
        return (
            d - r,
            side * wx,
            side * wy,
            side * wz,
            p[0] + s * p[3] + big_r * wx,
            p[1] + s * p[4] + big_r * wy,
            p[2] + s * p[5] + big_r * wz,
        )
    elif kind == KIND_SPHERE:
        rx = x0 - p[0]
        ry = x1 - p[1]
        rz = x2 - p[2]
        rho = math.sqrt(rx * rx + ry * ry + rz * rz)
        if rho > 0.0:
            ux = rx / rho
            uy = ry / rho
            uz = rz / rho
        else:
            ux = 0.0
            uy = 0.0
            uz = 1.0
        side = p[4]
        d = side * (rho - p[3])
        return (
            d - r,
            -side * ux,
            -side * uy,
            -side * uz,
            p[0] + p[3] * ux,
            p[1] + p[3] * uy,
            p[2] + p[3] * uz,
        )
    elif kind == KIND_TRIANGLE:
        gap, nx, ny, nz, cx, cy, cz, _inside = triangle_contact(p, x0, x1, x2, r)
        return gap, nx, ny, nz, cx, cy, cz
    else:
        raise ValueError("wall_contact: unknown wall kind")


@njit
def triangle_contact(p, x0, x1, x2, r):
    """Sphere against the triangle p (layout of ``KIND_TRIANGLE``): (gap, n, c, inside face).

    The closest point is found by the Voronoi regions of the vertices, edges and face (barycentric
    tests on dot products with the edge vectors)."""
    ax = p[0]
    ay = p[1]
    az = p[2]
    e1x = p[3]
    e1y = p[4]
    e1z = p[5]
    e2x = p[6]
    e2y = p[7]
    e2z = p[8]
    apx = x0 - ax
    apy = x1 - ay
    apz = x2 - az
    d1 = e1x * apx + e1y * apy + e1z * apz
    d2 = e2x * apx + e2y * apy + e2z * apz
    # with P − B = AP − E1 and P − C = AP − E2:
    e11 = e1x * e1x + e1y * e1y + e1z * e1z
    e12 = e1x * e2x + e1y * e2y + e1z * e2z
    e22 = e2x * e2x + e2y * e2y + e2z * e2z
    d3 = d1 - e11
    d4 = d2 - e12
    d5 = d1 - e12
    d6 = d2 - e22
    inside = False
    if d1 <= 0.0 and d2 <= 0.0:  # vertex A
        u = 0.0
        v = 0.0
    elif d3 >= 0.0 and d4 <= d3:  # vertex B
        u = 1.0
        v = 0.0
    elif d6 >= 0.0 and d5 <= d6:  # vertex C
        u = 0.0
        v = 1.0
    else:
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:  # edge AB
            u = d1 / (d1 - d3)
            v = 0.0
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:  # edge AC
            u = 0.0
            v = d2 / (d2 - d6)
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:  # edge BC
            v = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            u = 1.0 - v
        else:  # the face
            den = 1.0 / (va + vb + vc)
            u = vb * den
            v = vc * den
            inside = True
    cx = ax + u * e1x + v * e2x
    cy = ay + u * e1y + v * e2y
    cz = az + u * e1z + v * e2z
    dx = cx - x0
    dy = cy - x1
    dz = cz - x2
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    if dist > 0.0:
        nx = dx / dist
        ny = dy / dist
        nz = dz / dist
    else:
        fx = e1y * e2z - e1z * e2y
        fy = e1z * e2x - e1x * e2z
        fz = e1x * e2y - e1y * e2x
        fn = math.sqrt(fx * fx + fy * fy + fz * fz)
        nx = -fx / fn
        ny = -fy / fn
        nz = -fz / fn
    return dist - r, nx, ny, nz, cx, cy, cz, inside


@njit(inline="always")
def surface_velocity(kind, p, vel, omega, centre, k, px, py, pz):
    """Velocity of wall k's surface at the point (px, py, pz): V + Ω × (p − centre), plus, when the
    wall's size changes (``vel[k, 3]`` = rate of its radius [m/s], revolved, cylinder and sphere
    kinds), that rate along the radial direction of the point."""
    qx = px - centre[k, 0]
    qy = py - centre[k, 1]
    qz = pz - centre[k, 2]
    vwx = vel[k, 0] + omega[k, 1] * qz - omega[k, 2] * qy
    vwy = vel[k, 1] + omega[k, 2] * qx - omega[k, 0] * qz
    vwz = vel[k, 2] + omega[k, 0] * qy - omega[k, 1] * qx
    rate = vel[k, 3]  # (vel[k, 4] is the mass of a free rigid-body wall, not a velocity)
    if rate != 0.0:
        if kind == KIND_SPHERE:
            wx = px - p[0]
            wy = py - p[1]
            wz = pz - p[2]
        elif kind == KIND_REVOLVED or kind == KIND_CYLINDER:
            rx = px - p[0]
            ry = py - p[1]
            rz = pz - p[2]
            s = rx * p[3] + ry * p[4] + rz * p[5]
            wx = rx - s * p[3]
            wy = ry - s * p[4]
            wz = rz - s * p[5]
        else:
            wx = 0.0
            wy = 0.0
            wz = 0.0
        wn = math.sqrt(wx * wx + wy * wy + wz * wz)
        if wn > 0.0:
            vwx += rate * wx / wn
            vwy += rate * wy / wn
            vwz += rate * wz / wn
    return vwx, vwy, vwz, qx, qy, qz


@njit
def _gaps(kind, p, x, r, n, out):
    for i in range(n):
        out[i] = wall_contact(kind, p, x[i, 0], x[i, 1], x[i, 2], r[i])[0]


def wall_gaps(kind: int, p: np.ndarray, x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Gaps φ of the spheres (x, r) against one wall, by the force loop's own kernel (compiled; the
    NumPy twin, used here before for the analytic kinds, cost a hopper 6 % of its run in the
    neighbour-list rebuilds' wall candidates)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    r = np.ascontiguousarray(np.broadcast_to(np.asarray(r, dtype=np.float64), (x.shape[0],)))
    n = x.shape[0]
    out = np.empty(n)
    _gaps(kind, np.asarray(p, dtype=np.float64), x, r, n, out)
    return out


# ---------------------------------------------------------------------------------------------
# Pure-NumPy twin (same formulas, same operation order)
# ---------------------------------------------------------------------------------------------


def _unit_perp_numpy(ex: float, ey: float, ez: float) -> tuple[float, float, float]:
    """Python twin of :func:`unit_perp` (scalar: the axis is the same for every particle)."""
    ax, ay, az = abs(ex), abs(ey), abs(ez)
    if ax <= ay and ax <= az:
        qx, qy, qz = 1.0 - ex * ex, -ex * ey, -ex * ez
    elif ay <= az:
        qx, qy, qz = -ey * ex, 1.0 - ey * ey, -ey * ez
    else:
        qx, qy, qz = -ez * ex, -ez * ey, 1.0 - ez * ez
    qn = math.sqrt(qx * qx + qy * qy + qz * qz)
    return qx / qn, qy / qn, qz / qn


def _axial_frame_numpy(
    p: np.ndarray, x0: np.ndarray, x1: np.ndarray, x2: np.ndarray
) -> tuple[np.ndarray, ...]:
    ex, ey, ez = float(p[3]), float(p[4]), float(p[5])
    rx = x0 - p[0]
    ry = x1 - p[1]
    rz = x2 - p[2]
    s = rx * ex + ry * ey + rz * ez
    wx = rx - s * ex
    wy = ry - s * ey
    wz = rz - s * ez
    rho = np.sqrt(wx * wx + wy * wy + wz * wz)
    pos = rho > 0.0
    safe = np.where(pos, rho, 1.0)
    px, py, pz = _unit_perp_numpy(ex, ey, ez)
    wx = np.where(pos, wx / safe, px)
    wy = np.where(pos, wy / safe, py)
    wz = np.where(pos, wz / safe, pz)
    return s, rho, wx, wy, wz


def wall_contact_numpy(
    kind: int, p: np.ndarray, x: np.ndarray, r: np.ndarray | float
) -> tuple[np.ndarray, ...]:
    """Vectorised NumPy twin of :func:`wall_contact`.

    Parameters
    ----------
    kind : wall kind constant.
    p : parameter vector (length ``N_PARAMS``).
    x : sphere centres, shape (n, 3) [m].
    r : radii, shape (n,) or scalar [m].

    Returns
    -------
    Seven arrays of shape (n,): gap, nx, ny, nz, cx, cy, cz (see :func:`wall_contact`).
    """
    p = np.asarray(p, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), (x.shape[0],))
    x0 = x[:, 0]
    x1 = x[:, 1]
    x2 = x[:, 2]
    if kind == KIND_PLANE:
        nx, ny, nz = float(p[3]), float(p[4]), float(p[5])
        d = (x0 - p[0]) * nx + (x1 - p[1]) * ny + (x2 - p[2]) * nz
        one = np.ones_like(d)
        return d - r, -nx * one, -ny * one, -nz * one, x0 - d * nx, x1 - d * ny, x2 - d * nz
    if kind == KIND_RECTANGLE:
        nx, ny, nz = float(p[3]), float(p[4]), float(p[5])
        ux, uy, uz = float(p[6]), float(p[7]), float(p[8])
        hu, hv = float(p[9]), float(p[10])
        vx = ny * uz - nz * uy
        vy = nz * ux - nx * uz
        vz = nx * uy - ny * ux
        rx = x0 - p[0]
        ry = x1 - p[1]
        rz = x2 - p[2]
        a = rx * ux + ry * uy + rz * uz
        b = rx * vx + ry * vy + rz * vz
        h = rx * nx + ry * ny + rz * nz
        ac = np.minimum(np.maximum(a, -hu), hu)
        bc = np.minimum(np.maximum(b, -hv), hv)
        da = ac - a
        db = bc - b
        dh = -h
        dist = np.sqrt(da * da + db * db + dh * dh)
        pos = dist > 0.0
        safe = np.where(pos, dist, 1.0)
        gx = np.where(pos, (da * ux + db * vx + dh * nx) / safe, -nx)
        gy = np.where(pos, (da * uy + db * vy + dh * ny) / safe, -ny)
        gz = np.where(pos, (da * uz + db * vz + dh * nz) / safe, -nz)
        cx = p[0] + ac * ux + bc * vx
        cy = p[1] + ac * uy + bc * vy
        cz = p[2] + ac * uz + bc * vz
        return dist - r, gx, gy, gz, cx, cy, cz
    if kind == KIND_REVOLVED:
        s, rho, wx, wy, wz = _axial_frame_numpy(p, x0, x1, x2)
        s0, r0 = float(p[6]), float(p[7])
        ts = float(p[8]) - s0
        tr = float(p[9]) - r0
        l2 = ts * ts + tr * tr
        ps = s - s0
        pr = rho - r0
        if l2 > 0.0:
            ll = math.sqrt(l2)
            ms = tr / ll
            mr = -ts / ll
            lam = (ps * ts + pr * tr) / l2
        else:
            ms, mr = 1.0, 0.0
            lam = np.zeros_like(s)
        inner = (lam > 0.0) & (lam < 1.0)
        # interior of the segment
        qs_i = s0 + lam * ts
        qr_i = r0 + lam * tr
        h = ps * ms + pr * mr
        dist_i = np.abs(h)
        neg = h < 0.0
        gs_i = np.where(neg, ms, -ms)
        gr_i = np.where(neg, mr, -mr)
        # ends (rim circles)
        lo = lam <= 0.0
        qs_e = np.where(lo, s0, float(p[8]))
        qr_e = np.where(lo, r0, float(p[9]))
        ds = qs_e - s
        dr = qr_e - rho
        dist_e = np.sqrt(ds * ds + dr * dr)
        pos = dist_e > 0.0
        safe = np.where(pos, dist_e, 1.0)
        gs_e = np.where(pos, ds / safe, -ms)
        gr_e = np.where(pos, dr / safe, -mr)
        qs = np.where(inner, qs_i, qs_e)
        qr = np.where(inner, qr_i, qr_e)
        dist = np.where(inner, dist_i, dist_e)
        gs = np.where(inner, gs_i, gs_e)
        gr = np.where(inner, gr_i, gr_e)
        ex, ey, ez = float(p[3]), float(p[4]), float(p[5])
        return (
            dist - r,
            gs * ex + gr * wx,
            gs * ey + gr * wy,
            gs * ez + gr * wz,
            p[0] + qs * ex + qr * wx,
            p[1] + qs * ey + qr * wy,
            p[2] + qs * ez + qr * wz,
        )
    if kind == KIND_CYLINDER:
        s, rho, wx, wy, wz = _axial_frame_numpy(p, x0, x1, x2)
        big_r = float(p[6])
        side = float(p[7])
        d = side * (big_r - rho)
        return (
            d - r,
            side * wx,
            side * wy,
            side * wz,
            p[0] + s * p[3] + big_r * wx,
            p[1] + s * p[4] + big_r * wy,
            p[2] + s * p[5] + big_r * wz,
        )
    raise ValueError(f"wall_contact_numpy: unknown wall kind {kind!r}; expected one of {sorted(KIND_NAMES)}")
