"""Tests of pdem.sources: regions, size distributions, lattices, random fills and packing files."""

from __future__ import annotations

import math
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from pdem.errors import GeometryError, InputError
from pdem.sources import (
    BoxRegion,
    CylinderRegion,
    Normal,
    Single,
    Table,
    Uniform,
    fcc,
    hcp,
    hex2d,
    random_fill,
    read_spheres,
    simple_cubic,
    spatial_order,
    write_spheres_text,
)

SHARED_PACKING = Path("/work/shared/bench/column_packing_18k.txt")


def pair_distances(x: np.ndarray) -> np.ndarray:
    """All pairwise distances (n, n), diagonal set to +inf (O(n²), no KD-tree)."""
    d = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=-1))
    np.fill_diagonal(d, np.inf)
    return d


def assert_no_overlap(x: np.ndarray, r: np.ndarray, gap: float = 0.0) -> None:
    d = pair_distances(x)
    lim = r[:, None] + r[None, :] + gap
    worst = np.min(d - lim)
    assert worst >= -1e-12 * float(r.max()), f"overlap of {-worst} m"


def coordination(x: np.ndarray, spacing: float) -> np.ndarray:
    d = pair_distances(x)
    return np.sum(d <= spacing * (1.0 + 1e-9), axis=1)


# --------------------------------------------------------------------------------------------- regions


def test_box_region_basics():
    box = BoxRegion((0.0, -1.0, 2.0), (1.0, 1.0, 5.0))
    assert box.volume == pytest.approx(6.0)
    lo, hi = box.bounds
    np.testing.assert_array_equal(lo, [0.0, -1.0, 2.0])
    np.testing.assert_array_equal(hi, [1.0, 1.0, 5.0])
    x = np.array([[0.5, 0.0, 3.0], [0.05, 0.0, 3.0], [0.5, 0.95, 4.9], [2.0, 0.0, 3.0]])
    np.testing.assert_array_equal(box.contains_spheres(x, 0.1), [True, False, False, False])
    np.testing.assert_array_equal(box.contains_spheres(x, [0.1, 0.05, 0.05, 0.1]), [True, True, True, False])
    assert box.contains_spheres((0.1, 0.0, 3.0), 0.1).tolist() == [True]  # touching counts as inside
    pts = box.sample(np.random.default_rng(1), 20000)
    assert pts.shape == (20000, 3)
    assert np.all((pts >= lo) & (pts <= hi))
    np.testing.assert_allclose(pts.mean(axis=0), 0.5 * (lo + hi), atol=0.03)


def test_cylinder_region_basics():
    cyl = CylinderRegion((1.0, 2.0, 0.5), radius=0.5, height=2.0)
    assert cyl.volume == pytest.approx(math.pi * 0.25 * 2.0)
    lo, hi = cyl.bounds
    np.testing.assert_allclose(lo, [0.5, 1.5, 0.5])
    np.testing.assert_allclose(hi, [1.5, 2.5, 2.5])
    x = np.array([[1.0, 2.0, 1.0], [1.45, 2.0, 1.0], [1.3, 2.3, 1.0], [1.0, 2.0, 0.55], [1.0, 2.0, 2.45]])
    np.testing.assert_array_equal(cyl.contains_spheres(x, 0.1), [True, False, False, False, False])
    assert not cyl.contains_spheres((1.0, 2.0, 1.5), 0.6)[0]  # wider than the cylinder
    pts = cyl.sample(np.random.default_rng(2), 40000)
    rho = np.hypot(pts[:, 0] - 1.0, pts[:, 1] - 2.0)
    assert rho.max() <= 0.5 and pts[:, 2].min() >= 0.5 and pts[:, 2].max() <= 2.5
    # area-uniform: half the points lie inside radius R/sqrt(2)
    assert np.mean(rho < 0.5 / math.sqrt(2.0)) == pytest.approx(0.5, abs=0.01)


def test_region_errors():
    with pytest.raises(GeometryError, match=r"hi = .* along y"):
        BoxRegion((0, 0, 0), (1, 0, 1))
    with pytest.raises(InputError, match="lo = "):
        BoxRegion((0, 0), (1, 1, 1))
    with pytest.raises(InputError, match="non-finite"):
        BoxRegion((0, 0, np.nan), (1, 1, 1))
    with pytest.raises(InputError, match=r"radius = -1"):
        CylinderRegion((0, 0, 0), -1.0, 1.0)
    with pytest.raises(InputError, match=r"height = 0"):
        CylinderRegion((0, 0, 0), 1.0, 0)


def test_spatial_order_sorts_cells_z_then_y_then_x():
    rng = np.random.default_rng(3)
    x = rng.random((500, 3))
    order = spatial_order(x, 0.25, origin=(0, 0, 0))
    cells = np.floor(x[order] / 0.25).astype(int)
    key = cells[:, 2] * 100 + cells[:, 1] * 10 + cells[:, 0]
    assert np.all(np.diff(key) >= 0)
    assert sorted(order.tolist()) == list(range(500))


# --------------------------------------------------------------------------------------------- sizes


def test_single():
    s = Single(1e-3)
    r = s.sample(np.random.default_rng(0), 5)
    np.testing.assert_array_equal(r, 1e-3)
    assert s.r_min == s.r_max == 1e-3
    assert s.mean_volume() == pytest.approx(4.0 / 3.0 * math.pi * 1e-9)


def test_uniform_moments():
    a, b = 0.45e-3, 0.55e-3
    u = Uniform(a, b)
    r = u.sample(np.random.default_rng(4), 200_000)
    assert r.min() >= a and r.max() <= b
    sem = (b - a) / math.sqrt(12.0) / math.sqrt(r.size)
    assert abs(r.mean() - 0.5 * (a + b)) < 5 * sem
    assert r.var() == pytest.approx((b - a) ** 2 / 12.0, rel=0.02)
    vol = 4.0 / 3.0 * math.pi * r**3
    assert u.mean_volume() == pytest.approx(vol.mean(), rel=2e-3)
    assert Uniform(1e-3, 1e-3).mean_volume() == pytest.approx(Single(1e-3).mean_volume())


def test_normal_truncated_moments():
    n = Normal(1.0e-3, 0.2e-3, r_min=0.8e-3, r_max=1.5e-3)
    r = n.sample(np.random.default_rng(5), 200_000)
    assert r.min() >= 0.8e-3 and r.max() <= 1.5e-3
    assert n.mean_radius() > 1.0e-3  # truncated more on the low side
    assert r.mean() == pytest.approx(n.mean_radius(), rel=2e-3)
    assert (4.0 / 3.0 * math.pi * r**3).mean() == pytest.approx(n.mean_volume(), rel=5e-3)
    # defaults: mean ∓ 3 std; an untruncated-looking normal keeps its moments
    wide = Normal(1.0, 0.1)
    assert (wide.r_min, wide.r_max) == pytest.approx((0.7, 1.3))
    rw = wide.sample(np.random.default_rng(6), 100_000)
    assert rw.std() == pytest.approx(0.1, rel=0.03)
    np.testing.assert_array_equal(Normal(1.0, 0.0, 0.5, 2.0).sample(np.random.default_rng(0), 3), 1.0)


def test_table_mass_fractions():
    radii = [0.5e-3, 1.0e-3, 2.0e-3]
    mass = [0.2, 0.3, 0.5]
    t = Table(radii, mass)
    num = np.array(mass) / np.array(radii) ** 3
    np.testing.assert_allclose(t.number_fractions, num / num.sum())
    assert (t.r_min, t.r_max) == (0.5e-3, 2.0e-3)
    r = t.sample(np.random.default_rng(7), 400_000)
    assert set(np.unique(r).tolist()) == set(radii)
    m = np.array([np.sum(r[r == ri] ** 3) for ri in radii])
    np.testing.assert_allclose(m / m.sum(), mass, atol=0.02)
    assert t.mean_volume() == pytest.approx((4.0 / 3.0 * math.pi * r**3).mean(), rel=0.02)
    # zero-fraction classes never appear and do not count towards r_min / r_max
    t0 = Table([1e-3, 5e-3], [1.0, 0.0])
    assert t0.r_max == 1e-3
    assert np.all(t0.sample(np.random.default_rng(0), 1000) == 1e-3)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Single(0.0), r"radius = 0.0 must be"),
        (lambda: Single(-1e-3), r"radius = -0.001"),
        (lambda: Uniform(2e-3, 1e-3), r"r_min = 0.002 exceeds r_max = 0.001"),
        (lambda: Uniform(-1e-3, 1e-3), r"r_min = -0.001"),
        (lambda: Normal(1e-3, -1e-4), r"std = -0.0001"),
        (lambda: Normal(1e-3, 5e-4), r"default r_min .* pass r_min > 0"),
        (lambda: Normal(1e-3, 1e-4, 2e-3, 1e-3), r"r_min = 0.002 exceeds"),
        (lambda: Normal(1e-3, 1e-5, 2e-3, 3e-3), r"holds only"),
        (lambda: Table([1e-3, 2e-3], [0.5, 0.4]), r"sum to 0.9.*normalise"),
        (lambda: Table([1e-3, 0.0], [0.5, 0.5]), r"radii\[1\] = 0.0"),
        (lambda: Table([1e-3, 2e-3], [1.5, -0.5]), r"mass_fractions\[1\] = -0.5"),
        (lambda: Table([1e-3, 2e-3], [1.0]), r"2 radii but 1 mass_fractions"),
        (lambda: Table([], []), r"radii is empty"),
    ],
)
def test_size_validation(make, match):
    with pytest.raises(InputError, match=match):
        make()


def test_sizes_deterministic():
    for dist in (Uniform(1e-3, 2e-3), Normal(1e-3, 2e-4, 5e-4, 2e-3), Table([1e-3, 2e-3], [0.3, 0.7])):
        a = dist.sample(np.random.default_rng(11), 1000)
        b = dist.sample(np.random.default_rng(11), 1000)
        assert a.tobytes() == b.tobytes()


# --------------------------------------------------------------------------------------------- lattices


def _interior(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float) -> np.ndarray:
    return np.all((x - lo > margin) & (hi - x > margin), axis=1)


@pytest.mark.parametrize("maker, z_interior", [(simple_cubic, 6), (fcc, 12), (hcp, 12)])
@pytest.mark.parametrize("spacing", [None, 2.5e-3])
def test_lattice_neighbours(maker, z_interior, spacing):
    r = 1e-3
    s = 2 * r if spacing is None else spacing
    box = BoxRegion((0, 0, 0), (7 * s, 6 * s, 6 * s))
    x, radii = maker(box, r, spacing=spacing)
    assert x.shape == (radii.size, 3) and np.all(radii == r)
    assert np.all(box.contains_spheres(x, r, tol=1e-12))
    d = pair_distances(x)
    assert d.min() == pytest.approx(s, rel=1e-12)
    assert np.all(d.min(axis=1) == pytest.approx(s, rel=1e-12))
    z = coordination(x, s)
    inner = _interior(x, *box.bounds, margin=1.5 * s)
    assert inner.sum() > 5
    assert np.all(z[inner] == z_interior)
    assert np.all(z <= z_interior)
    # ids in layer order: z never decreases (lattice planes are exact)
    assert np.all(np.diff(x[:, 2]) >= -1e-15)


def test_lattice_touches_low_corner_and_fills_box():
    r = 1e-3
    box = BoxRegion((0, 0, 0), (20 * r, 20 * r, 20 * r))  # exactly 10 diameters
    x, _ = simple_cubic(box, r)
    assert x.shape[0] == 1000
    np.testing.assert_allclose(x.min(axis=0), r)
    np.testing.assert_allclose(x.max(axis=0), 19 * r)


@pytest.mark.parametrize("maker", [fcc, hcp])
def test_close_packed_fraction(maker):
    r = 0.5
    s = 2 * r
    box = BoxRegion((0, 0, 0), (30.0, 30.0, 30.0))
    x, _ = maker(box, r)
    v = 4.0 / 3.0 * math.pi * r**3
    target = math.pi / (3.0 * math.sqrt(2.0))
    # a half-open window that spans whole lattice periods holds exactly the bulk density
    if maker is fcc:
        per = np.full(3, s * math.sqrt(2.0))
    else:
        per = np.array([s, s * math.sqrt(3.0), 2 * s * math.sqrt(2.0 / 3.0)])
    m = 4
    start = x.min(axis=0) + per - 1e-9
    w = m * per
    inside = np.all((x >= start) & (x < start + w), axis=1)
    assert inside.sum() * v / np.prod(w) == pytest.approx(target, rel=1e-12)
    # the whole block approaches it (finite-size wall effect only)
    phi = x.shape[0] * v / box.volume
    assert 0.85 * target < phi <= target


def test_lattice_in_cylinder():
    cyl = CylinderRegion((0, 0, 0), 10e-3, 8e-3)
    x, r = fcc(cyl, 1e-3)
    assert x.shape[0] > 50
    assert np.all(cyl.contains_spheres(x, r, tol=1e-12))
    assert pair_distances(x).min() == pytest.approx(2e-3)


def test_lattice_errors():
    box = BoxRegion((0, 0, 0), (1e-2, 1e-2, 1e-2))
    with pytest.raises(GeometryError, match=r"spacing = 0.0015 is smaller than the diameter"):
        fcc(box, 1e-3, spacing=1.5e-3)
    with pytest.raises(GeometryError, match="does not fit"):
        simple_cubic(box, 6e-3)
    with pytest.raises(InputError, match="radius = -1"):
        hcp(box, -1)
    with pytest.raises(InputError, match="region = "):
        fcc((0, 0, 0), 1e-3)


def test_hex2d_shock_wave_layout():
    r = 1e-3
    x, radii = hex2d(101, 100, r, origin=(0.0, 0.5, 0.0), plane="xz")
    assert x.shape == (10100, 3) and radii.shape == (10100,)
    assert np.all(x[:, 1] == 0.5)
    # rows by z then columns by x
    row_h = 2 * r * math.sqrt(3.0) / 2.0
    rows = np.rint(x[:, 2] / row_h).astype(int)
    assert np.all(np.diff(rows) >= 0) and rows.max() == 99
    np.testing.assert_allclose(x[:, 2], rows * row_h, atol=1e-15)
    assert np.all(np.bincount(rows) == 101)
    odd = x[rows == 1]
    np.testing.assert_allclose(odd[0, 0], r)  # odd rows shifted by half a spacing
    assert np.all(np.diff(odd[:, 0]) > 0)
    # neighbours on a small patch
    xs, _ = hex2d(12, 10, r, plane="xz")
    d = pair_distances(xs)
    assert d.min() == pytest.approx(2 * r)
    z = coordination(xs, 2 * r)
    lo, hi = xs.min(axis=0), xs.max(axis=0)
    inner = np.all((xs[:, [0, 2]] - lo[[0, 2]] > 2.5 * r) & (hi[[0, 2]] - xs[:, [0, 2]] > 2.5 * r), axis=1)
    assert inner.sum() > 20 and np.all(z[inner] == 6)


def test_hex2d_planes_and_spacing():
    x, _ = hex2d(3, 2, 1.0, origin=(1, 2, 3), plane="yz", spacing=3.0)
    np.testing.assert_array_equal(x[:, 0], 1.0)
    np.testing.assert_allclose(x[3], [1.0, 2.0 + 1.5, 3.0 + 3.0 * math.sqrt(3.0) / 2.0])
    assert pair_distances(x).min() == pytest.approx(3.0)
    x, _ = hex2d(2, 2, 1.0, plane="xy")
    np.testing.assert_array_equal(x[:, 2], 0.0)
    with pytest.raises(InputError, match="plane = 'xw'"):
        hex2d(2, 2, 1.0, plane="xw")
    with pytest.raises(InputError, match="n_rows = 0"):
        hex2d(2, 0, 1.0)


# --------------------------------------------------------------------------------------------- random fill


def test_random_fill_small_brute_force():
    box = BoxRegion((0, 0, 0), (10e-3, 10e-3, 10e-3))
    x, r = random_fill(box, Single(0.5e-3), n=300, seed=1)
    assert x.shape == (300, 3) and r.shape == (300,)
    assert x.dtype == np.float64 and r.dtype == np.float64
    assert np.all(box.contains_spheres(x, r))
    for i in range(1, len(r)):  # plain brute force: every earlier sphere against sphere i
        dist = np.sqrt(np.sum((x[:i] - x[i]) ** 2, axis=1))
        assert np.all(dist >= r[:i] + r[i]), f"sphere {i} overlaps"


def test_random_fill_polydisperse_no_overlap_2000():
    box = BoxRegion((0, 0, 0), (15e-3, 15e-3, 18e-3))
    x, r = random_fill(box, Uniform(0.3e-3, 0.7e-3), volume_fraction=0.3, seed=2)
    assert 1000 < r.size <= 2000
    assert_no_overlap(x, r)
    assert np.all(box.contains_spheres(x, r))
    phi = np.sum(4.0 / 3.0 * math.pi * r**3) / box.volume
    one_sphere = 4.0 / 3.0 * math.pi * 0.7e-3**3 / box.volume  # the count is rounded to whole spheres
    assert phi == pytest.approx(0.3, abs=one_sphere)


def test_random_fill_table_gap_and_cylinder():
    cyl = CylinderRegion((1.0, -1.0, 0.0), 8e-3, 12e-3)
    sizes = Table([0.4e-3, 0.8e-3], [0.5, 0.5])
    gap = 0.1e-3
    x, r = random_fill(cyl, sizes, volume_fraction=0.2, seed=3, gap=gap)
    assert r.size > 500
    assert_no_overlap(x, r, gap=gap)
    assert np.all(cyl.contains_spheres(x, r))
    assert set(np.unique(r).tolist()) == {0.4e-3, 0.8e-3}


def test_random_fill_deterministic_and_spatially_sorted():
    box = BoxRegion((0, 0, 0), (11e-3, 11e-3, 11e-3))
    sizes = Uniform(0.3e-3, 0.5e-3)
    a = random_fill(box, sizes, n=800, seed=7)
    b = random_fill(box, sizes, n=800, seed=7)
    c = random_fill(box, sizes, n=800, seed=8)
    assert a[0].tobytes() == b[0].tobytes() and a[1].tobytes() == b[1].tobytes()
    assert a[0].tobytes() != c[0].tobytes()
    x, r = a
    cells = np.floor(x / (2 * r.max())).astype(np.int64)
    key = (cells[:, 2] * 1000 + cells[:, 1]) * 1000 + cells[:, 0]
    assert np.all(np.diff(key) >= 0)
    # a Generator may be passed instead of a seed
    d = random_fill(box, sizes, n=800, seed=np.random.default_rng(7))
    assert d[0].tobytes() == a[0].tobytes()


def test_random_fill_20k_is_fast():
    sizes = Uniform(0.45e-3, 0.55e-3)
    box = BoxRegion((0, 0, 0), (0.02, 0.02, 0.1))
    random_fill(box, sizes, n=10, seed=0)  # warm up the kernel (compilation / cache load)
    t0 = time.perf_counter()
    x, r = random_fill(box, sizes, n=20_000, seed=0)
    elapsed = time.perf_counter() - t0
    assert r.size == 20_000
    assert elapsed < 3.0, f"random_fill of 20,000 spheres took {elapsed:.2f} s"
    # spot-check non-overlap on a spatially compact slab of the sorted output
    sl = slice(5000, 6500)
    assert_no_overlap(x[sl], r[sl])


def test_random_fill_places_larger_spheres_first():
    # one big sphere that only fits if placed before the small ones crowd the box
    box = BoxRegion((0, 0, 0), (4e-3, 4e-3, 4e-3))
    sizes = Table([0.25e-3, 1.9e-3], [0.5, 0.5])
    x, r = random_fill(box, sizes, n=60, seed=5)
    assert_no_overlap(x, r)
    assert r.size == 60


def test_random_fill_jams_with_helpful_error():
    box = BoxRegion((0, 0, 0), (10e-3, 10e-3, 10e-3))
    with pytest.raises(GeometryError) as info:
        random_fill(box, Single(0.5e-3), volume_fraction=0.5, seed=0, max_attempts=2000)
    msg = str(info.value)
    assert "placed only" in msg and "of 955 spheres" in msg
    assert "0.5000 asked" in msg and "0.38" in msg and "settle" in msg
    placed_phi = float(msg.split("(volume fraction ")[1].split()[0])
    assert 0.15 < placed_phi < 0.4


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        (dict(n=10, volume_fraction=0.1), InputError, "exactly one of n"),
        (dict(), InputError, "exactly one of n"),
        (dict(volume_fraction=1.2), InputError, r"volume_fraction = 1.2 must lie in \(0, 1\)"),
        (dict(n=-1), InputError, "n = -1"),
        (dict(n=10, gap=-1.0), InputError, "gap = -1.0"),
        (dict(n=10, max_attempts=0), InputError, "max_attempts = 0"),
    ],
)
def test_random_fill_argument_errors(kwargs, exc, match):
    box = BoxRegion((0, 0, 0), (1e-2, 1e-2, 1e-2))
    with pytest.raises(exc, match=match):
        random_fill(box, Single(1e-3), **kwargs)


def test_random_fill_sphere_too_large():
    with pytest.raises(
        GeometryError, match=r"radius 0.002 do not fit .* \(largest radius that fits: 0.0015\)"
    ):
        random_fill(BoxRegion((0, 0, 0), (3e-3, 1e-2, 1e-2)), Single(2e-3), n=1)


def test_random_fill_empty():
    x, r = random_fill(BoxRegion((0, 0, 0), (1, 1, 1)), Single(0.1), n=0)
    assert x.shape == (0, 3) and r.shape == (0,)


# --------------------------------------------------------------------------------------------- files


def test_text_round_trip_bitwise(tmp_path):
    rng = np.random.default_rng(9)
    x = rng.random((50, 3)) * 1e-2 - 3e-3
    r = rng.uniform(0.4e-3, 0.6e-3, 50)
    v = rng.normal(size=(50, 3))
    p = tmp_path / "pack.txt"
    write_spheres_text(p, x, r)
    assert p.read_text().splitlines()[0] == "x y z diameter"
    out = read_spheres(p)
    assert out["positions"].tobytes() == x.tobytes()
    assert out["radii"].tobytes() == r.tobytes()
    assert out["velocities"] is None
    write_spheres_text(p, x, r, velocities=v)
    assert p.read_text().splitlines()[0] == "x y z diameter vx vy vz"
    out = read_spheres(p)
    assert out["positions"].tobytes() == x.tobytes()
    assert out["radii"].tobytes() == r.tobytes()
    assert out["velocities"].tobytes() == v.tobytes()


def test_text_variants(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text(
        "# packing written by hand\n\n1.0, 2.0, 3.0, 0.002  # first\n4,5,6,0.004\n  7\t8   9  0.006\n"
    )
    out = read_spheres(p)
    np.testing.assert_array_equal(out["positions"], [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    np.testing.assert_array_equal(out["radii"], [0.001, 0.002, 0.003])
    p.write_text("radius,vx,vy,vz,z,y,x\n0.5,1,2,3,30,20,10\n")
    out = read_spheres(p)
    np.testing.assert_array_equal(out["positions"], [[10, 20, 30]])
    np.testing.assert_array_equal(out["radii"], [0.5])
    np.testing.assert_array_equal(out["velocities"], [[1, 2, 3]])
    p.write_text("0 0 0 1 0.1 0.2 0.3\n")
    np.testing.assert_array_equal(read_spheres(p)["velocities"], [[0.1, 0.2, 0.3]])


@pytest.mark.parametrize(
    "text, match",
    [
        ("x y z diameter\n0 0 0 1\n1 1 1\n", r"line 3: expected 4 columns .* found 3"),
        ("0 0 0 1 2\n", r"line 1: expected 4 columns 'x y z diameter' or 7 .* found 5"),
        ("x y z diameter\n0 0 0 1\n0 0 abc 1\n", r"line 3: cannot read 'abc' as a number"),
        ("# c\nx y z diameter\n0 0 0 -1\n", r"line 3: diameter -1.0 is not > 0"),
        ("x y z diameter\n0 0 nan 1\n", r"line 2: non-finite"),
        ("x y z mass\n0 0 0 1\n", r"line 1: unknown column 'mass'"),
        ("x y z diameter vx\n0 0 0 1 0\n", r"line 1: header names 1 of vx vy vz"),
        ("x y z\n0 0 0\n", r"line 1: header 'x y z' must name x, y, z and exactly one of diameter"),
        ("# nothing\n", r"no sphere rows"),
        ("x y z diameter\n", r"no sphere rows"),
    ],
)
def test_text_errors(tmp_path, text, match):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as info:
        read_spheres(p)
    assert "bad.txt" in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_spheres(tmp_path / "nope.txt")


def test_hdf5(tmp_path):
    rng = np.random.default_rng(10)
    x = rng.random((20, 3))
    d = rng.uniform(1.0, 2.0, 20)
    v = rng.random((20, 3))
    p = tmp_path / "a.h5"
    with h5py.File(p, "w") as f:
        f["x"] = x
        f["diameter"] = d
    out = read_spheres(p)
    assert out["positions"].tobytes() == x.tobytes()
    np.testing.assert_array_equal(out["radii"], 0.5 * d)
    assert out["velocities"] is None
    p = tmp_path / "b.hdf5"
    with h5py.File(p, "w") as f:
        f["position"] = x
        f["radius"] = 0.5 * d
        f["velocity"] = v
    out = read_spheres(p)
    np.testing.assert_array_equal(out["radii"], 0.5 * d)
    np.testing.assert_array_equal(out["velocities"], v)


@pytest.mark.parametrize(
    "datasets, match",
    [
        (dict(diameter=np.ones(3)), r"no dataset 'x' or 'position'"),
        (dict(x=np.zeros((3, 3))), r"no dataset 'diameter' or 'radius'"),
        (dict(x=np.zeros((3, 2)), diameter=np.ones(3)), r"shape \(3, 2\), expected \(n, 3\)"),
        (dict(x=np.zeros((3, 3)), diameter=np.ones(4)), r"shape \(4,\), expected \(3,\)"),
        (dict(x=np.zeros((3, 3)), diameter=np.ones(3), radius=np.ones(3)), "keep only one"),
        (dict(x=np.zeros((3, 3)), diameter=np.array([1.0, 0.0, 1.0])), r"sphere 1 .* diameter 0.0"),
        (dict(x=np.zeros((3, 3)), radius=np.ones(3), velocity=np.zeros(3)), r"velocity .* expected \(3, 3\)"),
    ],
)
def test_hdf5_errors(tmp_path, datasets, match):
    p = tmp_path / "bad.h5"
    with h5py.File(p, "w") as f:
        for k, val in datasets.items():
            f[k] = val
    with pytest.raises(InputError, match=match) as info:
        read_spheres(p)
    assert "bad.h5" in str(info.value)


def test_not_really_hdf5(tmp_path):
    p = tmp_path / "fake.h5"
    p.write_text("0 0 0 1\n")
    with pytest.raises(InputError, match="cannot open as HDF5"):
        read_spheres(p)


@pytest.mark.skipif(not SHARED_PACKING.is_file(), reason="shared benchmark packing not available")
def test_shared_column_packing():
    out = read_spheres(SHARED_PACKING)
    x, r = out["positions"], out["radii"]
    assert x.shape == (18_000, 3) and r.shape == (18_000,)
    assert out["velocities"] is None
    # diameters uniform in 0.9–1.1 mm, footprint [0, 0.02]², about 0.042 m tall
    assert 0.45e-3 - 1e-9 <= r.min() and r.max() <= 0.55e-3 + 1e-9
    assert r.mean() == pytest.approx(0.5e-3, rel=0.01)
    tol = 1e-5  # a settled packing presses a few micrometres into its walls
    assert np.all(x[:, :2] - r[:, None] >= -tol) and np.all(x[:, :2] + r[:, None] <= 0.02 + tol)
    assert np.all(x[:, 2] - r >= -tol)
    assert 0.03 < x[:, 2].max() < 0.05
    with SHARED_PACKING.open() as fh:
        fh.readline()
        first = [float(t) for t in fh.readline().split()]
    np.testing.assert_array_equal(x[0], first[:3])
    assert r[0] == 0.5 * first[3]


_FILE_DECK = """\
[run]
gravity = [0.0, 0.0, -9.81]
dt = 2e-6
[contact]
law = "hertz_mindlin"
[materials.glass]
density = 2500.0
youngs_modulus = 5e7
poisson_ratio = 0.3
restitution = 0.5
friction = 0.5
[[particles]]
source = "file"
path = "{path}"
order = "{order}"
material = "glass"
[boundaries.box]
type = "box"
material = "glass"
lo = [0.0, 0.0, 0.0]
hi = [0.01, 0.01, 0.02]
[[stages]]
name = "settle"
[stages.end]
steps = 400
[output]
formats = ["hdf5"]
every_steps = 400
"""


def test_file_source_spatial_order_makes_results_independent_of_row_order(tmp_path):
    """order = "spatial": a packing file and a shuffled copy of it give the same ids and bitwise the
    same run (the sorted order is that of pdem.sources.spatial_order); order = "file" gives ids by
    row, so the shuffled copy's run differs."""
    from pdem.cli import main
    from pdem.io.checkpoint import read_checkpoint

    # a dense packing (solid fraction ≈ 0.3) with random velocities of up to 1 m/s: most grains
    # collide within the run's 150 steps, so the order of the contact sums matters
    x, r = random_fill(BoxRegion((0, 0, 0), (0.006, 0.006, 0.006)), Uniform(0.45e-3, 0.55e-3), n=120, seed=4)
    v = np.random.default_rng(3).uniform(-1.0, 1.0, (len(r), 3))
    perm = np.random.default_rng(9).permutation(len(r))
    write_spheres_text(tmp_path / "a.txt", x, r, v)
    write_spheres_text(tmp_path / "b.txt", x[perm], r[perm], v[perm])
    states = {}
    for name in ("a", "b"):
        for order in ("spatial", "file"):
            deck = tmp_path / f"{name}_{order}.toml"
            deck.write_text(_FILE_DECK.format(path=f"{name}.txt", order=order).replace("400", "150"))
            out = tmp_path / f"out_{name}_{order}"
            assert main([str(deck), "--output", str(out), "--quiet"]) == 0
            state, _ = read_checkpoint(out / "checkpoints" / "latest.h5")
            states[name, order] = {k: np.asarray(state[f"particles/{k}"]) for k in ("id", "x", "v", "w", "r")}
    sa, sb = states["a", "spatial"], states["b", "spatial"]
    for k in sa:
        assert np.array_equal(sa[k], sb[k]), k
    # the grains interacted (contacts spin them: measured, 93 of the 120) and file order really differs
    assert np.count_nonzero(np.abs(sa["w"]).max(axis=1)) > 60
    assert not np.array_equal(states["a", "file"]["x"], states["b", "file"]["x"])


def test_pluviation_is_not_at_rest_before_its_column_has_fallen():
    """The spheres start at rest in a tall column: a short step (here checked every 5 steps, as a
    stiff material's 0.2 T_R makes the default 500) put the first check before they had gathered
    speed, and the pour ended there, the column still in the air. Settled, the packing lies on the
    floor: its highest sphere far below the column's top, many spheres touching the floor."""
    from pdem.materials import Material
    from pdem.sources import pluviate
    from pdem.sources.regions import BoxRegion
    from pdem.sources.sizes import Uniform

    mat = Material("g", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.1, friction=0.3)
    box = BoxRegion((0.0, 0.0, 0.0), (0.006, 0.006, 0.05))
    x, r = pluviate(box, Uniform(0.9e-3, 1.1e-3), 60, mat, seed=2, check_every=5)
    column = 60 * (4 / 3 * np.pi * 1.0e-9) / 0.3 / 0.006**2  # the loose column, about 23 mm
    packed = 60 * (4 / 3 * np.pi * 1.0e-9) / 0.6 / 0.006**2  # at a solid fraction of 0.6
    assert float(np.max(x[:, 2] + r)) < 0.5 * (column + packed)
    assert int(np.sum(x[:, 2] - r < 0.05e-3)) >= 5  # a floor layer

    with pytest.raises(GeometryError, match="max_time"):
        pluviate(box, Uniform(0.9e-3, 1.1e-3), 60, mat, seed=2, max_time=0.01)


def test_file_rows_are_kept_in_every_snapshot_and_checkpoint(tmp_path):
    """A packing file's spheres get ids in space (the default order) and each keeps its file row as
    the particle field ``row``: every snapshot (HDF5 and VTK) and the checkpoint carry it, and the
    first frame's positions are the file's rows it names. ``order = "file"`` gives ids = rows. Grains
    of another table (a lattice) have row -1."""
    import h5py
    import meshio

    from pdem.cli import main
    from pdem.io.checkpoint import read_checkpoint

    x, r = random_fill(BoxRegion((0, 0, 0), (0.006, 0.006, 0.006)), Uniform(0.45e-3, 0.55e-3), n=80, seed=4)
    perm = np.random.default_rng(9).permutation(len(r))
    x, r = x[perm], r[perm]
    write_spheres_text(tmp_path / "a.txt", x, r)
    lattice = (
        '\n[[particles]]\nsource = "lattice"\nmaterial = "glass"\nlattice = "sc"\nradius = 4e-4\n'
        "region = { type = \"box\", lo = [0.0, 0.0, 0.012], hi = [0.0041, 0.0041, 0.0141] }\n"
    )
    rows = {}
    for order in (None, "file"):
        text = _FILE_DECK.format(path="a.txt", order=order or "x").replace("400", "20")
        text = text.replace('order = "x"\n', "").replace('formats = ["hdf5"]', 'formats = ["hdf5", "vtk"]')
        text = text.replace("every_steps = 20", "every_steps = 10")
        text = text.replace("[boundaries.box]", lattice + "[boundaries.box]")
        deck = tmp_path / f"{order}.toml"
        deck.write_text(text)
        out = tmp_path / f"out_{order}"
        assert main([str(deck), "--output", str(out), "--quiet"]) == 0
        with h5py.File(out / "particles.h5", "r") as f:
            frames = [f[f"frames/{k}"] for k in sorted(f["frames"])]
            first = {k: frames[0][k][()] for k in ("id", "x", "row")}
            assert all("row" in g for g in frames)
            assert all(np.array_equal(g["row"][()], first["row"]) for g in frames)  # rows follow the grains
        file_rows = first["row"] >= 0
        assert np.count_nonzero(~file_rows) >= 25 and np.all(first["row"][~file_rows] == -1)
        assert sorted(first["row"][file_rows].tolist()) == list(range(80))
        assert np.array_equal(first["x"][file_rows], x[first["row"][file_rows]])  # the row maps back
        vtk = sorted((out / "vtk").glob("*.vtu")) if (out / "vtk").is_dir() else sorted(out.rglob("*.vtu"))
        mesh = meshio.read(vtk[0])
        assert np.array_equal(np.sort(mesh.point_data["row"]), np.sort(first["row"]))
        state, _ = read_checkpoint(out / "checkpoints" / "latest.h5")
        order_ids = np.argsort(state["particles/id"])
        assert np.array_equal(np.asarray(state["particles/row"])[order_ids], first["row"])
        rows[order] = first
    # the default is space order: not the file's; "file" numbers the grains by row
    assert not np.array_equal(rows[None]["row"][:80], np.arange(80))
    assert np.array_equal(rows["file"]["row"][:80], np.arange(80))
    assert np.array_equal(rows["file"]["id"][:80], np.arange(80))


@pytest.mark.parametrize("lattice", ["sc", "fcc", "hcp"])
@pytest.mark.parametrize("region", [
    {"type": "box", "lo": [0.0, 0.0, 0.0], "hi": [0.011, 0.013, 0.017]},
    {"type": "cylinder", "base_center": [0.001, 0.002, 0.0], "radius": 0.006, "height": 0.012},
])  # fmt: skip
def test_the_lattice_source_is_partitioned_by_contract(lattice, region):
    """Each rank can make only its own lattice spheres: any box's part is bitwise generate()'s
    spheres at the indices it names, and holds every sphere centred in the box; the survey counts,
    bounds and samples them (pdem.testing.source_contract)."""
    from pdem.materials import Material
    from pdem.sources.builtin import LatticeParams, LatticeSource
    from pdem.testing.source_contract import check_partitioned

    params = LatticeParams.model_validate(
        {"source": "lattice", "material": "glass", "lattice": lattice, "radius": 0.5e-3, "spacing": 1.05e-3,
         "region": region}  # fmt: skip
    )
    source = LatticeSource(params)
    assert source.partitioned
    glass = Material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3)
    check_partitioned(source, base_dir=Path("."), seed=3, material=glass)


@pytest.mark.parametrize("order", ["spatial", "file"])
@pytest.mark.parametrize("fmt", ["txt", "h5"])
def test_the_file_source_is_partitioned_by_contract(tmp_path, order, fmt):
    """A packing file in shuffled row order (polydisperse, with velocities): any box's part is
    bitwise generate()'s spheres, rows and velocities at the ids it names, in both id orders, read
    from text and from HDF5 in chunks."""
    import h5py

    from pdem.materials import Material
    from pdem.sources import random_fill
    from pdem.sources.builtin import FileParams, FileSource
    from pdem.sources.files import write_spheres_text
    from pdem.sources.regions import BoxRegion
    from pdem.sources.sizes import Uniform
    from pdem.testing.source_contract import check_partitioned

    x, r = random_fill(BoxRegion((0, 0, 0), (0.02, 0.015, 0.03)), Uniform(0.4e-3, 0.6e-3), n=3000, seed=5)
    rng = np.random.default_rng(2)
    perm = rng.permutation(len(r))
    x, r = x[perm], r[perm]
    v = rng.normal(size=x.shape)
    path = tmp_path / f"packing.{fmt}"
    if fmt == "h5":
        with h5py.File(path, "w") as f:
            f["position"], f["radius"], f["velocity"] = x, r, v
    else:
        write_spheres_text(path, x, r, velocities=v)
    params = FileParams.model_validate(
        {"source": "file", "material": "glass", "path": str(path), "order": order}
    )
    source = FileSource(params)
    source.chunk = 317  # (many chunks, the last one short)
    glass = Material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3)
    check_partitioned(source, base_dir=tmp_path, seed=1, material=glass, pieces=4)


@pytest.fixture
def small_blocks(monkeypatch):
    """Random fills in blocks of about 300 spheres (the default block holds 100,000)."""
    import sys

    import pdem.sources.random_fill  # noqa: F401  (the module; the package exports the function)

    monkeypatch.setattr(sys.modules["pdem.sources.random_fill"], "BLOCK_SPHERES", 300)


@pytest.mark.parametrize("region, amount", [
    ({"type": "box", "lo": [0.0, 0.0, 0.0], "hi": [0.03, 0.02, 0.025]}, {"n": 2000}),
    ({"type": "box", "lo": [0.0, 0.0, 0.0], "hi": [0.03, 0.027, 0.025]}, {"volume_fraction": 0.2}),
    ({"type": "cylinder", "base_center": [0.001, 0.002, 0.0], "radius": 0.013, "height": 0.03}, {"n": 2500}),
    ({"type": "cylinder", "base_center": [0.001, 0.002, 0.0], "radius": 0.013, "height": 0.03},
     {"volume_fraction": 0.2}),
])  # fmt: skip
def test_a_random_fill_in_blocks_is_partitioned_by_contract(small_blocks, region, amount):
    """A fill larger than a block is made block by block: the spheres do not overlap (brute force
    over all pairs), lie in the region, number n (or fill the fraction to within a sphere per
    block), and any box's part is bitwise generate()'s spheres at the indices it names."""
    import sys

    from pdem.materials import Material
    from pdem.sources.builtin import RandomFillParams, RandomFillSource
    from pdem.testing.source_contract import check_partitioned

    params = RandomFillParams.model_validate(
        {"source": "random_fill", "material": "glass", "region": region,
         "sizes": {"type": "uniform", "r_min": 0.4e-3, "r_max": 0.6e-3}, **amount}  # fmt: skip
    )
    source = RandomFillSource(params)
    plan = source._plan(3)
    assert not plan.single and plan.count >= 2, plan.count  # blocks are really used
    glass = Material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3)
    out = source.generate(base_dir=Path("."), seed=3, material=glass)
    x, r = out.positions, out.radii
    d = np.linalg.norm(x[:, None] - x[None], axis=2) - (r[:, None] + r[None])
    np.fill_diagonal(d, np.inf)
    assert d.min() >= 0.0
    reg = params.region.build()
    assert reg.contains_spheres(x, r).all()
    if "n" in amount:
        assert len(r) == amount["n"]
    else:
        filled = float(np.sum(4.0 / 3.0 * np.pi * r**3)) / reg.volume
        assert abs(filled - 0.2) < plan.count * 4.0 / 3.0 * np.pi * 0.6e-3**3 / reg.volume + 0.01
    check_partitioned(source, base_dir=Path("."), seed=3, material=glass)
    assert sys.modules["pdem.sources.random_fill"].BLOCK_SPHERES == 300


def test_a_random_fill_of_one_block_is_partitioned_by_contract():
    """A fill of one block (the default block holds 100,000 spheres) is made whole on each rank
    and cut: the contract holds there too."""
    from pdem.materials import Material
    from pdem.sources.builtin import RandomFillParams, RandomFillSource
    from pdem.testing.source_contract import check_partitioned

    params = RandomFillParams.model_validate(
        {"source": "random_fill", "material": "glass", "n": 800,
         "region": {"type": "cylinder", "base_center": [0.0, 0.0, 0.0], "radius": 0.01, "height": 0.02},
         "sizes": {"type": "uniform", "r_min": 0.4e-3, "r_max": 0.6e-3}}  # fmt: skip
    )
    source = RandomFillSource(params)
    assert source._plan(1).single
    glass = Material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3)
    check_partitioned(source, base_dir=Path("."), seed=1, material=glass)


def test_a_random_fill_of_one_block_is_the_classic_fill(small_blocks):
    """A fill that fits one block (or a region too small to cut) is random sequential addition
    from the one stream default_rng(seed), as before blocks existed: redone here by hand."""
    from pdem.sources import random_fill
    from pdem.sources.regions import BoxRegion
    from pdem.sources.sizes import Uniform

    region, sizes = BoxRegion((0, 0, 0), (0.008, 0.008, 0.008)), Uniform(0.4e-3, 0.6e-3)
    x, r = random_fill(region, sizes, n=250, seed=4)
    rng = np.random.default_rng(4)
    radii = np.asarray(sizes.sample(rng, 250))
    assert np.array_equal(np.sort(r), np.sort(radii))
    # a 600-sphere fill of a region too narrow for two 10-diameter blocks is one block too
    x2, r2 = random_fill(BoxRegion((0, 0, 0), (0.008, 0.008, 0.02)), sizes, n=600, seed=4)
    assert np.array_equal(np.sort(r2), np.sort(np.asarray(sizes.sample(np.random.default_rng(4), 600))))


def test_blocks_of_a_fill_leave_no_sphere_across_their_faces(small_blocks):
    """Each block's spheres lie wholly inside it (that is what lets blocks be made alone)."""
    import sys

    from pdem.sources.regions import BoxRegion
    from pdem.sources.sizes import Uniform

    rf = sys.modules["pdem.sources.random_fill"]
    plan = rf.fill_plan(BoxRegion((0, 0, 0), (0.03, 0.03, 0.02)), Uniform(0.4e-3, 0.6e-3), n=3000, seed=2)
    assert plan.count >= 4
    total = 0
    for b, start, x, r in plan.blocks():
        lo, hi = plan.bounds(b)
        assert np.all(x - r[:, None] >= lo) and np.all(x + r[:, None] <= hi), b
        assert start == total
        total += len(r)
    assert total == 3000 == plan.total()


def test_the_pour_is_partitioned_by_contract():
    """A pour (collective, checked on one rank): any box's part is bitwise generate()'s spheres at
    the indices it names; the survey counts, bounds and samples them."""
    from pdem.materials import Material
    from pdem.sources.builtin import PluviateParams, PluviateSource
    from pdem.testing.source_contract import check_partitioned

    params = PluviateParams.model_validate(
        {"source": "pluviate", "material": "glass", "n": 200,
         "region": {"type": "cylinder", "base_center": [0.0, 0.0, 0.0], "radius": 0.006, "height": 0.02},
         "sizes": {"type": "uniform", "r_min": 0.45e-3, "r_max": 0.55e-3}}  # fmt: skip
    )
    source = PluviateSource(params)
    glass = Material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.1,
                     friction=0.3)  # fmt: skip
    check_partitioned(source, base_dir=Path("."), seed=2, material=glass, pieces=2)
