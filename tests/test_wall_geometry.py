"""Sphere–wall contact geometry: kernels vs a brute-force sampled reference, NumPy twin, shapes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pdem.errors import GeometryError
from pdem.geometry._kernels import (
    KIND_CYLINDER,
    KIND_PLANE,
    KIND_RECTANGLE,
    KIND_REVOLVED,
    N_PARAMS,
    unit_perp,
    wall_contact,
    wall_contact_numpy,
)
from pdem.geometry.shapes import (
    Annulus,
    Cylinder,
    CylinderTube,
    Disk,
    Frustum,
    Plane,
    Rectangle,
    Revolved,
    box_planes,
)

# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def _kernel(kind: int, p: np.ndarray, x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(n, 7) results of the numba kernel, one call per sphere."""
    return np.array([wall_contact(kind, p, xi[0], xi[1], xi[2], ri) for xi, ri in zip(x, r, strict=True)])


def _numpy(kind: int, p: np.ndarray, x: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.stack(wall_contact_numpy(kind, p, x, r), axis=1)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _frame(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing e to an orthonormal frame."""
    e1 = np.array(unit_perp(e[0], e[1], e[2]))
    return e1, np.cross(e, e1)


def brute_min(surf, bounds, periodic, xs, n_coarse=300, keep=8, levels=5, m=21):
    """Minimum distances from the points xs (n, 3) to a 2-parameter surface, by dense sampling.

    ``surf(a, b)`` maps parameter arrays to points (..., 3). A coarse n_coarse² grid is sampled, the
    ``keep`` best distinct samples are refined ``levels`` times with an m×m grid over ±2 cells. Every
    sample is a point of the surface, so each result is an upper bound of the true distance whose
    excess shrinks with the final spacing (≈ coarse spacing · (4/(m−1))^levels).
    """
    (a0, a1), (b0, b1) = bounds
    aa, bb = np.meshgrid(np.linspace(a0, a1, n_coarse), np.linspace(b0, b1, n_coarse), indexing="ij")
    aa, bb = aa.ravel(), bb.ravel()
    pts = surf(aa, bb)
    ha = (a1 - a0) / (n_coarse - 1)
    hb = (b1 - b0) / (n_coarse - 1)
    out = np.empty(len(xs))
    for ix, x in enumerate(xs):
        d2 = np.sum((pts - x) ** 2, axis=1)
        # the keep best samples at distinct points (a degenerate parametrisation such as a cone apex
        # maps a whole grid row onto one point; refining duplicates would explore nothing)
        n_cand = min(d2.size - 1, (keep + 2) * n_coarse)
        order = np.argpartition(d2, n_cand)[:n_cand]
        best: list[int] = []
        for idx in order[np.argsort(d2[order])]:
            if all(np.linalg.norm(pts[idx] - pts[j]) > 1e-12 for j in best):
                best.append(int(idx))
                if len(best) == keep:
                    break
        best_d2 = d2[best[0]]
        for idx in best:
            ca, cb = aa[idx], bb[idx]
            wa, wb = 2.0 * ha, 2.0 * hb
            for _ in range(levels):
                la = np.linspace(ca - wa, ca + wa, m)
                lb = np.linspace(cb - wb, cb + wb, m)
                if not periodic[0]:
                    la = np.clip(la, a0, a1)
                if not periodic[1]:
                    lb = np.clip(lb, b0, b1)
                ga, gb = np.meshgrid(la, lb, indexing="ij")
                ga, gb = ga.ravel(), gb.ravel()
                ld2 = np.sum((surf(ga, gb) - x) ** 2, axis=1)
                j = int(np.argmin(ld2))
                ca, cb = ga[j], gb[j]
                best_d2 = min(best_d2, ld2[j])
                wa, wb = 4.0 * wa / (m - 1), 4.0 * wb / (m - 1)
        out[ix] = math.sqrt(best_d2)
    return out


BRUTE_TOL = 1e-6  # excess of the sampled minimum over the exact one (observed < 1e-8), shapes ~1 m


def _check_consistency(res: np.ndarray, x: np.ndarray, r: np.ndarray) -> None:
    """Unit normal and the identity c = x + (gap + r) n."""
    gap, nrm, cp = res[:, 0], res[:, 1:4], res[:, 4:7]
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cp, x + (gap + r)[:, None] * nrm, atol=1e-12)


def _check_twin(kind: int, p: np.ndarray, x: np.ndarray, r: np.ndarray) -> np.ndarray:
    res = _kernel(kind, p, x, r)
    np.testing.assert_allclose(_numpy(kind, p, x, r), res, rtol=0, atol=1e-12)
    return res


# ---------------------------------------------------------------------------------------------
# rectangle
# ---------------------------------------------------------------------------------------------


def _rect_samples(rng, c, n, u, v, hu, hv, count=40):
    a = rng.uniform(-1.3 * hu, 1.3 * hu, count)
    b = rng.uniform(-1.3 * hv, 1.3 * hv, count)
    h = rng.uniform(-0.3, 0.3, count)
    # near edges and corners
    k = count // 2
    a[:k] = rng.choice([-hu, hu], k) + rng.uniform(-0.05, 0.05, k)
    b[: k // 2] = rng.choice([-hv, hv], k // 2) + rng.uniform(-0.05, 0.05, k // 2)
    h[: k // 2] = rng.uniform(-0.02, 0.02, k // 2)
    x = c + a[:, None] * u + b[:, None] * v + h[:, None] * n
    return x, rng.uniform(0.01, 0.1, count)


def test_rectangle_vs_brute_force():
    rng = np.random.default_rng(1)
    n = _random_unit(rng)
    u0 = np.cross(n, _random_unit(rng))
    shape = Rectangle((0.1, -0.2, 0.3), n, u0, (0.7, 0.4))
    p = shape.params()
    c, n, u, v = shape.center, shape.normal, shape.u_axis, shape.v_axis
    hu, hv = shape.half_extents
    x, r = _rect_samples(rng, c, n, u, v, hu, hv)
    res = _check_twin(KIND_RECTANGLE, p, x, r)
    _check_consistency(res, x, r)

    def surf(a, b):
        return c + a[:, None] * u + b[:, None] * v

    brute = brute_min(surf, ((-hu, hu), (-hv, hv)), (False, False), x)
    for i in range(len(x)):
        dist, bd = res[i, 0] + r[i], brute[i]
        assert dist <= bd + 1e-12
        assert bd - dist <= BRUTE_TOL, (i, x[i], dist, bd)
        # contact point on the plate
        q = res[i, 4:7] - c
        assert abs(q @ n) <= 1e-12
        assert abs(q @ u) <= hu + 1e-12 and abs(q @ v) <= hv + 1e-12


def test_rectangle_on_surface_direction():
    shape = Rectangle((1.0, 2.0, 3.0), (0, 0, 1), (1, 0, 0), (0.5, 0.25))
    p = shape.params()
    # exactly on the plate: the centre counts as being on the +N side, n = -N
    g = wall_contact(KIND_RECTANGLE, p, 1.1, 2.2, 3.0, 0.05)
    assert g == pytest.approx((-0.05, 0.0, 0.0, -1.0, 1.1, 2.2, 3.0), abs=1e-15)
    # above / below: normal towards the plate
    assert wall_contact(KIND_RECTANGLE, p, 1.1, 2.2, 3.2, 0.05)[3] == -1.0
    assert wall_contact(KIND_RECTANGLE, p, 1.1, 2.2, 2.8, 0.05)[3] == 1.0
    # beside an edge in the plate's plane: the edge pushes along the in-plane direction
    g = wall_contact(KIND_RECTANGLE, p, 1.6, 2.0, 3.0, 0.2)
    assert g == pytest.approx((-0.1, -1.0, 0.0, 0.0, 1.5, 2.0, 3.0), abs=1e-14)
    # beyond a corner: the corner is the contact point
    g = wall_contact(KIND_RECTANGLE, p, 1.8, 2.65, 3.0, 0.1)
    assert g[0] == pytest.approx(0.4, abs=1e-14)
    assert g[4:] == pytest.approx((1.5, 2.25, 3.0), abs=1e-14)


# ---------------------------------------------------------------------------------------------
# surfaces of revolution
# ---------------------------------------------------------------------------------------------


def _revolved_shapes(rng):
    a = rng.uniform(-0.5, 0.5, 3)
    e = _random_unit(rng)
    return [
        Disk(a, e, 0.8),
        Annulus(a, e, 0.3, 0.9),
        CylinderTube(a, e, 0.5, 1.2),
        Frustum(a, e, 0.0, 0.6, 0.9),  # cone, apex at a
        Frustum(a, e, 0.7, 0.2, 0.8),  # narrowing frustum
        Revolved(a, e, 0.4, 0.9, -0.3, 0.1),  # general, s decreasing
    ]


def _revolved_samples(rng, shape, count=36):
    s0, r0, s1, r1 = shape.s0, shape.rho0, shape.s1, shape.rho1
    e1, e2 = _frame(shape.axis)
    lam = rng.uniform(-0.25, 1.25, count)
    lam[: count // 3] = rng.choice([0.0, 1.0], count // 3) + rng.uniform(-0.05, 0.05, count // 3)
    off = rng.uniform(-0.3, 0.3, (count, 2))
    off[: count // 3] *= 0.2
    s = s0 + lam * (s1 - s0) + off[:, 0]
    rho = r0 + lam * (r1 - r0) + off[:, 1]
    # near the axis
    k = count // 6
    rho[-k:] = rng.uniform(0.0, 0.05, k)
    th = rng.uniform(0.0, 2.0 * np.pi, count)
    radial = np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2
    x = shape.point + s[:, None] * shape.axis + rho[:, None] * radial
    return x, rng.uniform(0.01, 0.1, count)


def _seg_dist(ps, pr, s0, r0, s1, r1):
    ts, tr = s1 - s0, r1 - r0
    lam = np.clip(((ps - s0) * ts + (pr - r0) * tr) / (ts * ts + tr * tr), 0.0, 1.0)
    return np.hypot(ps - s0 - lam * ts, pr - r0 - lam * tr)


@pytest.mark.parametrize("which", range(6))
def test_revolved_vs_brute_force(which):
    rng = np.random.default_rng(10 + which)
    shape = _revolved_shapes(rng)[which]
    assert shape.kind == KIND_REVOLVED
    p = shape.params()
    a, e = shape.point, shape.axis
    s0, r0, s1, r1 = shape.s0, shape.rho0, shape.s1, shape.rho1
    e1, e2 = _frame(e)
    x, r = _revolved_samples(rng, shape)
    res = _check_twin(KIND_REVOLVED, p, x, r)
    _check_consistency(res, x, r)

    def surf(lam, th):
        s = s0 + lam * (s1 - s0)
        rho = r0 + lam * (r1 - r0)
        radial = np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2
        return a + s[:, None] * e + rho[:, None] * radial

    brute = brute_min(surf, ((0.0, 1.0), (0.0, 2.0 * np.pi)), (False, True), x)
    for i in range(len(x)):
        dist, bd = res[i, 0] + r[i], brute[i]
        assert dist <= bd + 1e-12
        assert bd - dist <= BRUTE_TOL, (i, x[i], dist, bd)
        # contact point on the surface: its meridian coordinates lie on the segment
        q = res[i, 4:7] - a
        qs = q @ e
        qr = np.linalg.norm(q - qs * e)
        assert _seg_dist(qs, qr, s0, r0, s1, r1) <= 1e-12


def test_revolved_deterministic_directions():
    ez = (0.0, 0.0, 1.0)
    # a point on the axis of a tube: radial direction = unit_perp(z) = +x, rim circle at rho = R
    tube = CylinderTube((0, 0, 0), ez, 0.5, 1.0)
    g = wall_contact(KIND_REVOLVED, tube.params(), 0.0, 0.0, 0.5, 0.1)
    assert g == pytest.approx((0.4, 1.0, 0.0, 0.0, 0.5, 0.0, 0.5), abs=1e-15)
    # a centre exactly on the tube counts as inside: n points outwards (wall pushes inwards)
    g = wall_contact(KIND_REVOLVED, tube.params(), 0.0, 0.5, 0.3, 0.1)
    assert g == pytest.approx((-0.1, 0.0, 1.0, 0.0, 0.0, 0.5, 0.3), abs=1e-15)
    # a centre exactly at the disk centre counts as on the +normal side: n = -normal
    disk = Disk((1, 1, 1), ez, 0.5)
    g = wall_contact(KIND_REVOLVED, disk.params(), 1.0, 1.0, 1.0, 0.1)
    assert g == pytest.approx((-0.1, 0.0, 0.0, -1.0, 1.0, 1.0, 1.0), abs=1e-15)
    # on the axis above / below the disk
    assert wall_contact(KIND_REVOLVED, disk.params(), 1.0, 1.0, 1.3, 0.1)[1:4] == (0.0, 0.0, -1.0)
    assert wall_contact(KIND_REVOLVED, disk.params(), 1.0, 1.0, 0.7, 0.1)[1:4] == (0.0, 0.0, 1.0)
    # a sphere near the rim of a disk touches the rim circle
    g = wall_contact(KIND_REVOLVED, disk.params(), 1.6, 1.0, 1.1, 0.1)
    assert g[0] == pytest.approx(math.hypot(0.1, 0.1) - 0.1, abs=1e-15)
    assert g[4:] == pytest.approx((1.5, 1.0, 1.0), abs=1e-15)
    # the apex of a cone, on the axis below it
    cone = Frustum((0, 0, 0), ez, 0.0, 1.0, 1.0)
    g = wall_contact(KIND_REVOLVED, cone.params(), 0.0, 0.0, -0.5, 0.1)
    assert g == pytest.approx((0.4, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), abs=1e-15)
    # inside the cone on the axis: closest to the generatrix, direction +x chosen by unit_perp
    g = wall_contact(KIND_REVOLVED, cone.params(), 0.0, 0.0, 0.5, 0.0)
    assert g[0] == pytest.approx(0.5 / math.sqrt(2.0), abs=1e-15)
    assert g[1:4] == pytest.approx((1 / math.sqrt(2.0), 0.0, -1 / math.sqrt(2.0)), abs=1e-15)
    # numpy twin takes the same choices
    for shape, pt in ((tube, (0.0, 0.0, 0.5)), (tube, (0.0, 0.5, 0.3)), (disk, (1.0, 1.0, 1.0))):
        k = np.array(wall_contact(KIND_REVOLVED, shape.params(), *pt, 0.1))
        nres = _numpy(KIND_REVOLVED, shape.params(), np.array([pt]), np.array([0.1]))[0]
        np.testing.assert_array_equal(k, nres)


def test_unit_perp():
    rng = np.random.default_rng(3)
    for _ in range(50):
        e = _random_unit(rng)
        q = np.array(unit_perp(*e))
        assert abs(q @ e) < 1e-15 and abs(np.linalg.norm(q) - 1.0) < 1e-15
    assert unit_perp(0.0, 0.0, 1.0) == (1.0, 0.0, 0.0)
    assert unit_perp(1.0, 0.0, 0.0) == (0.0, 1.0, 0.0)


# ---------------------------------------------------------------------------------------------
# one-sided kinds: plane and infinite cylinder
# ---------------------------------------------------------------------------------------------


def test_plane_vs_brute_force_and_sign():
    rng = np.random.default_rng(5)
    n = _random_unit(rng)
    pt = np.array([0.3, -0.1, 0.2])
    shape = Plane(pt, n)
    p = shape.params()
    e1, e2 = _frame(shape.normal)
    k = 30
    depth = rng.uniform(-0.4, 0.4, k)
    x = pt + rng.uniform(-1, 1, (k, 1)) * e1 + rng.uniform(-1, 1, (k, 1)) * e2 + depth[:, None] * n
    r = rng.uniform(0.01, 0.1, k)
    res = _check_twin(KIND_PLANE, p, x, r)
    _check_consistency(res, x, r)
    # signed gap, normal always -N ("into the wall")
    np.testing.assert_allclose(res[:, 0], depth - r, atol=1e-14)
    np.testing.assert_allclose(res[:, 1:4], np.broadcast_to(-n, (k, 3)), atol=0)

    def surf(a, b):
        return pt + a[:, None] * e1 + b[:, None] * e2

    brute = brute_min(surf, ((-3.0, 3.0), (-3.0, 3.0)), (False, False), x)
    for i in range(k):
        bd = brute[i]
        assert abs(res[i, 0] + r[i]) <= bd + 1e-12
        assert bd - abs(res[i, 0] + r[i]) <= BRUTE_TOL
    # a centre deep on the wrong side: large overlap, still pushed back towards +N
    g = wall_contact(KIND_PLANE, Plane((0, 0, 0), (0, 0, 2)).params(), 0.1, 0.2, -0.5, 0.1)
    assert g == pytest.approx((-0.6, 0.0, 0.0, -1.0, 0.1, 0.2, 0.0), abs=1e-15)


@pytest.mark.parametrize("inside", [True, False])
def test_cylinder_vs_brute_force_and_sign(inside):
    rng = np.random.default_rng(7 + inside)
    e = _random_unit(rng)
    a = np.array([0.2, 0.1, -0.3])
    big_r = 0.6
    shape = Cylinder(a, e, big_r, inside=inside)
    p = shape.params()
    e1, e2 = _frame(shape.axis)
    k = 30
    rho = rng.uniform(0.0, 1.2, k)
    rho[:4] = rng.uniform(0.0, 0.03, 4)  # near the axis
    s = rng.uniform(-1, 1, k)
    th = rng.uniform(0, 2 * np.pi, k)
    x = a + s[:, None] * e + rho[:, None] * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
    r = rng.uniform(0.01, 0.1, k)
    res = _check_twin(KIND_CYLINDER, p, x, r)
    _check_consistency(res, x, r)
    side = 1.0 if inside else -1.0
    np.testing.assert_allclose(res[:, 0], side * (big_r - rho) - r, atol=1e-13)
    # the normal pushes the particle back to its side: radial component sign = side
    radial = x - a - ((x - a) @ e)[:, None] * e
    assert np.all(side * np.sum(res[:, 1:4] * radial, axis=1) > 0)

    def surf(ss, tt):
        return a + ss[:, None] * e + big_r * (np.cos(tt)[:, None] * e1 + np.sin(tt)[:, None] * e2)

    brute = brute_min(surf, ((-3.0, 3.0), (0.0, 2 * np.pi)), (False, True), x)
    for i in range(k):
        dist, bd = abs(res[i, 0] + r[i]), brute[i]
        assert dist <= bd + 1e-12
        assert bd - dist <= BRUTE_TOL
    # exactly on the axis: radial direction unit_perp(axis)
    zc = Cylinder((0, 0, 0), (0, 0, 1), 0.5, inside=inside)
    g = wall_contact(KIND_CYLINDER, zc.params(), 0.0, 0.0, 0.7, 0.1)
    assert g == pytest.approx((side * 0.5 - 0.1, side, 0.0, 0.0, 0.5, 0.0, 0.7), abs=1e-15)


# ---------------------------------------------------------------------------------------------
# shapes: params layout, offsets, bounding boxes, validation
# ---------------------------------------------------------------------------------------------


def test_params_layout():
    p = Plane((1, 2, 3), (0, 0, 2)).params()
    assert p.shape == (N_PARAMS,) and p.dtype == np.float64
    np.testing.assert_array_equal(p[:6], [1, 2, 3, 0, 0, 1])
    p = Rectangle((0, 0, 0), (0, 0, 1), (3, 0, 0), (1, 2)).params()
    np.testing.assert_array_equal(p[:11], [0, 0, 0, 0, 0, 1, 1, 0, 0, 1, 2])
    np.testing.assert_array_equal(Disk((0, 0, 1), (0, 0, 1), 2).params()[6:10], [0, 0, 0, 2])
    np.testing.assert_array_equal(Annulus((0, 0, 1), (0, 0, 1), 1, 2).params()[6:10], [0, 1, 0, 2])
    np.testing.assert_array_equal(
        CylinderTube((0, 0, 0), (0, 0, 5), 1, 3).params()[3:10], [0, 0, 1, 0, 1, 3, 1]
    )
    np.testing.assert_array_equal(
        Frustum((0, 0, 0), (0, 1, 0), 0, 2, 3).params()[3:10], [0, 1, 0, 0, 0, 3, 2]
    )
    cyl = Cylinder((0, 0, 0), (0, 0, 1), 2, inside=False)
    assert cyl.kind == KIND_CYLINDER
    np.testing.assert_array_equal(cyl.params()[6:8], [2, -1])
    assert Plane((0, 0, 0), (1, 0, 0)).kind == KIND_PLANE
    assert Rectangle((0, 0, 0), (0, 0, 1), (1, 0, 0), (1, 1)).kind == KIND_RECTANGLE
    # nearly perpendicular u_axis is re-orthogonalised exactly
    rect = Rectangle((0, 0, 0), (0, 0, 1), (1, 0, 1e-9), (1, 1))
    assert rect.u_axis @ rect.normal == 0.0


def test_offset_translates_contact():
    rng = np.random.default_rng(11)
    shapes = [
        Plane((0, 0, 0), (0, 1, 1)),
        Rectangle((0, 0, 0), (0, 0, 1), (1, 1, 0), (0.5, 0.3)),
        Frustum((0, 0, 0), (1, 0, 1), 0.2, 0.5, 0.7),
        Cylinder((0, 0, 0), (1, 2, 3), 0.4),
    ]
    off = np.array([0.3, -1.2, 2.5])
    x = rng.uniform(-0.5, 0.5, (10, 3))
    r = np.full(10, 0.05)
    for sh in shapes:
        base = _numpy(sh.kind, sh.params(), x, r)
        moved = _numpy(sh.kind, sh.params(off), x + off, r)
        np.testing.assert_allclose(moved[:, :4], base[:, :4], atol=1e-12)
        np.testing.assert_allclose(moved[:, 4:], base[:, 4:] + off, atol=1e-12)


def test_reference_points():
    np.testing.assert_array_equal(Plane((1, 2, 3), (0, 0, 1)).reference_point, [1, 2, 3])
    np.testing.assert_array_equal(
        Rectangle((1, 2, 3), (0, 0, 1), (1, 0, 0), (1, 1)).reference_point, [1, 2, 3]
    )
    np.testing.assert_array_equal(Disk((1, 2, 3), (0, 0, 1), 1).reference_point, [1, 2, 3])
    np.testing.assert_array_equal(CylinderTube((1, 2, 3), (0, 0, 1), 1, 4).reference_point, [1, 2, 5])
    np.testing.assert_array_equal(Frustum((1, 2, 3), (0, 0, 1), 0, 1, 4).reference_point, [1, 2, 3])
    np.testing.assert_array_equal(Cylinder((1, 2, 3), (0, 0, 1), 1).reference_point, [1, 2, 3])


def test_bounding_boxes():
    rng = np.random.default_rng(13)
    e = _random_unit(rng)
    e1, e2 = _frame(e)
    off = np.array([1.0, 2.0, -3.0])
    rect = Rectangle((0.1, 0.2, 0.3), e, e1, (0.4, 0.2))
    tt = np.linspace(-1, 1, 101)
    a, b = np.meshgrid(tt, tt)
    pts = rect.center + 0.4 * a.ravel()[:, None] * rect.u_axis + 0.2 * b.ravel()[:, None] * rect.v_axis
    lo, hi = rect.bounding_box(off)
    np.testing.assert_allclose(lo, pts.min(0) + off, atol=1e-12)
    np.testing.assert_allclose(hi, pts.max(0) + off, atol=1e-12)
    fr = Frustum((0, 0, 0), e, 0.3, 0.8, 1.1)
    lam, th = np.meshgrid(np.linspace(0, 1, 51), np.linspace(0, 2 * np.pi, 2001))
    lam, th = lam.ravel(), th.ravel()
    rho = 0.3 + 0.5 * lam
    pts = (1.1 * lam)[:, None] * e + rho[:, None] * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
    lo, hi = fr.bounding_box()
    assert np.all(pts >= lo - 1e-12) and np.all(pts <= hi + 1e-12)
    np.testing.assert_allclose(lo, pts.min(0), atol=1e-5)
    np.testing.assert_allclose(hi, pts.max(0), atol=1e-5)
    lo, hi = Plane((1, 2, 3), (0, 0, -1)).bounding_box()
    np.testing.assert_array_equal(lo, [-np.inf, -np.inf, 3])
    np.testing.assert_array_equal(hi, [np.inf, np.inf, 3])
    assert np.all(np.isinf(Plane((1, 2, 3), (0, 1, 1)).bounding_box()[0]))
    lo, hi = Cylinder((1, 2, 3), (0, 0, 1), 0.5).bounding_box()
    np.testing.assert_array_equal(lo, [0.5, 1.5, -np.inf])
    np.testing.assert_array_equal(hi, [1.5, 2.5, np.inf])


def test_box_planes_inward():
    lo, hi = np.array([0.0, -1.0, 2.0]), np.array([1.0, 1.0, 5.0])
    planes = box_planes(lo, hi)
    assert [pl.name_hint for pl in planes] == ["xmin", "xmax", "ymin", "ymax", "zmin", "zmax"]
    centre = 0.5 * (lo + hi)
    for k, pl in enumerate(planes):
        assert pl.kind == KIND_PLANE
        axis, upper = divmod(k, 2)
        expected = np.zeros(3)
        expected[axis] = -1.0 if upper else 1.0
        np.testing.assert_array_equal(pl.normal, expected)
        g = wall_contact(KIND_PLANE, pl.params(), *centre, 0.1)
        assert g[0] == pytest.approx(0.5 * (hi - lo)[axis] - 0.1)
        # a point outside across this face overlaps it
        outside = centre.copy()
        outside[axis] = (hi if upper else lo)[axis] + (0.2 if upper else -0.2)
        assert wall_contact(KIND_PLANE, pl.params(), *outside, 0.1)[0] == pytest.approx(-0.3)
    with pytest.raises(GeometryError, match="lo"):
        box_planes(hi, lo)


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda: Plane((0, 0, 0), (0, 0, 0)), ["normal", "zero length", "non-zero"]),
        (lambda: Plane((0, 0), (0, 0, 1)), ["point", "3-vector"]),
        (lambda: Plane((0, np.nan, 0), (0, 0, 1)), ["point", "finite"]),
        (lambda: Rectangle((0, 0, 0), (0, 0, 1), (1, 0, 0.5), (1, 1)), ["u_axis", "perpendicular"]),
        (lambda: Rectangle((0, 0, 0), (0, 0, 1), (0, 0, 0), (1, 1)), ["u_axis", "zero length"]),
        (lambda: Rectangle((0, 0, 0), (0, 0, 1), (1, 0, 0), (1, -2)), ["half_extents[1]", "-2", "> 0"]),
        (lambda: Rectangle((0, 0, 0), (0, 0, 1), (1, 0, 0), (1, 2, 3)), ["half_extents", "two"]),
        (lambda: Disk((0, 0, 0), (0, 0, 1), -0.5), ["radius", "-0.5", "> 0"]),
        (lambda: Disk((0, 0, 0), (0, 0, 0), 0.5), ["normal", "zero length"]),
        (lambda: Annulus((0, 0, 0), (0, 0, 1), 2.0, 1.0), ["r_inner", "r_outer", "2.0"]),
        (lambda: Annulus((0, 0, 0), (0, 0, 1), -1.0, 1.0), ["r_inner", "-1.0", ">= 0"]),
        (lambda: CylinderTube((0, 0, 0), (0, 0, 1), 1.0, 0.0), ["length", "0.0", "> 0"]),
        (lambda: CylinderTube((0, 0, 0), (0, 0, 1), -1.0, 1.0), ["radius", "-1.0"]),
        (lambda: CylinderTube((0, 0, 0), (0, 0, 0), 1.0, 1.0), ["axis", "zero length"]),
        (lambda: Frustum((0, 0, 0), (0, 0, 1), 0.0, 0.0, 1.0), ["r0", "r1", "degenerate"]),
        (lambda: Frustum((0, 0, 0), (0, 0, 1), 0.0, 1.0, -1.0), ["length", "-1.0"]),
        (lambda: Frustum((0, 0, 0), (0, 0, 1), -0.1, 1.0, 1.0), ["r0", "-0.1"]),
        (lambda: Cylinder((0, 0, 0), (0, 0, 1), 0.0), ["radius", "0.0", "> 0"]),
        (lambda: Cylinder((0, 0, 0), (0, 0, 0), 1.0), ["axis", "zero length"]),
        (lambda: Revolved((0, 0, 0), (0, 0, 1), 1.0, 2.0, 1.0, 2.0), ["zero length"]),
        (lambda: box_planes((0, 0, 0), (1, 0, 1)), ["lo", "hi"]),
    ],
)
def test_geometry_errors(make, words):
    with pytest.raises(GeometryError) as info:
        make()
    msg = str(info.value)
    for w in words:
        assert w in msg, (w, msg)


def test_unknown_kind():
    with pytest.raises(ValueError):
        wall_contact_numpy(99, np.zeros(N_PARAMS), np.zeros((1, 3)), np.ones(1))
