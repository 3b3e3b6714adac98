"""Walls that turn, change shape, are meshes, or are free rigid bodies.

References: a run whose neighbour list (and wall candidate lists) is rebuilt at every step — a
brute-force wall search — must give the same result bit for bit as the normal run, whose rebuild
test relies on the walls' swept distance (a missed contact would change it); a triangle's closest
point against an independent construction (projection, then the three edges); a mesh box against
the six analytic planes; free fall of a rigid body in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

import pdem
from pdem.boundaries.api import Boundary, BoundaryParams
from pdem.geometry import shapes
from pdem.geometry._kernels import KIND_TRIANGLE, triangle_contact, wall_contact
from pdem.geometry.walls import Controlled, Resize, RigidBody, Rotation

R = 1e-3
RHO = 2500.0


class RebuildEveryStep(Boundary):
    def __init__(self):
        super().__init__("brute_force", BoundaryParams(type="probe"))

    def before_step(self, sim):
        sim.request_rebuild()


def _sim(law="hertz_mindlin", friction=0.3, gravity=(0, 0, -9.81)):
    sim = pdem.Simulation(law=law)
    sim.add_material("glass", density=RHO, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                     friction=friction)
    sim.gravity = gravity
    return sim


def _column(n_side=4, layers=3, spacing=2.2 * R, origin=(0.0, 0.0, R)):
    k = np.arange(n_side * n_side * layers)
    ix, iy, iz = k % n_side, (k // n_side) % n_side, k // (n_side * n_side)
    c = (n_side - 1) / 2
    return np.stack([(ix - c) * spacing, (iy - c) * spacing, iz * spacing], 1) + np.asarray(origin)


def _run_shrinking_cylinder(brute: bool, law="hertz_mindlin", steps=3000):
    sim = _sim(law)
    x = _column()
    sim.add_particles(x, R * (1 + 0.05 * np.sin(np.arange(len(x)))))
    sim.add_wall(shapes.Plane((0, 0, 0), (0, 0, 1)), name="floor")
    r0 = 6.5 * R
    cyl = sim.add_wall(shapes.Cylinder((0, 0, 0), (0, 0, 1), r0), name="cell",
                       motion=Resize({"radius": -0.2}))  # 0.2 m/s inwards
    if brute:
        sim.add_boundary(RebuildEveryStep())
    sim.dt = 2e-6 if law == "hertz_mindlin" else 5e-5
    sim.skin = 0.2 * R
    sim.run(steps=steps)
    return sim, cyl


@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_shrinking_cylinder_misses_no_contact(law):
    steps = 3000 if law == "hertz_mindlin" else 120
    sim, cyl = _run_shrinking_cylinder(False, law, steps)
    ref, _ = _run_shrinking_cylinder(True, law, steps)
    a, b = sim.get_particles(), ref.get_particles()
    for k in ("x", "v", "w", "f"):
        assert np.array_equal(a[k], b[k]), k
    assert ref.n_rebuilds >= steps  # the reference rebuilt every step
    assert sim.n_rebuilds < ref.n_rebuilds / 5  # the normal run rebuilt only when the wall had moved
    assert cyl.sizes["radius"] == pytest.approx(6.5 * R - 0.2 * steps * sim.dt, rel=1e-9)
    # the cell really squeezed the grains (radial load) and kept them inside
    rho = np.hypot(a["x"][:, 0], a["x"][:, 1]) + a["r"]
    assert rho.max() < cyl.sizes["radius"] + 0.25 * R
    assert cyl.n_contacts > 0


def test_size_rate_enters_the_contact_velocity():
    """A grain at rest against a cylinder whose radius shrinks at 0.05 m/s is pushed inwards by
    the wall's surface velocity at once (damping and overlap)."""
    sim = _sim(gravity=(0, 0, 0), friction=0.0)
    sim.add_particles([[5 * R - R, 0, 0]], R)
    sim.add_wall(shapes.Cylinder((0, 0, 0), (0, 0, 1), 5 * R), name="cell", motion=Resize({"radius": -0.05}))
    sim.dt = 1e-6
    sim.run(steps=400)
    v = sim.get_particles()["v"][0]
    assert v[0] < -0.04  # moving inwards with (at least about) the wall
    assert abs(v[1]) < 1e-12 and abs(v[2]) < 1e-12


def test_tilting_plane_misses_no_contact_and_rotates_geometry():
    def run(brute):
        sim = _sim()
        x = _column(n_side=5, layers=2, origin=(0, 0, 1.05 * R))
        sim.add_particles(x, R)
        floor = sim.add_wall(shapes.Plane((0, 0, 0), (0, 0, 1)), name="floor",
                             motion=Rotation((0.0, 2.0, 0.0)))  # 2 rad/s about y
        if brute:
            sim.add_boundary(RebuildEveryStep())
        sim.dt = 2e-6
        sim.skin = 0.2 * R
        sim.run(steps=4000)
        return sim, floor

    sim, floor = run(False)
    ref, _ = run(True)
    a, b = sim.get_particles(), ref.get_particles()
    for k in ("x", "v", "w"):
        assert np.array_equal(a[k], b[k]), k
    angle = 2.0 * 4000 * 2e-6
    assert floor.params[3:6] == pytest.approx([math.sin(angle), 0.0, math.cos(angle)], abs=1e-12)
    assert sim.n_rebuilds < ref.n_rebuilds / 5
    assert floor.n_contacts > 0


def test_controlled_wall_checkpoint_resumes_bitwise():
    def build(particles=True):
        sim = _sim()
        if particles:
            sim.add_particles(_column(), R)
        sim.add_wall(shapes.Plane((0, 0, 0), (0, 0, 1)), name="floor")
        ctl = Controlled(size_rates={"radius": -0.1}, angular_velocity=np.array([0.0, 0.0, 3.0]))
        sim.add_wall(shapes.Cylinder((0, 0, 0), (0, 0, 1), 6.5 * R), name="cell", motion=ctl)
        sim.dt = 2e-6
        return sim

    full = build().run(steps=1200)
    half = build().run(steps=600)
    state = half.state_dict()
    rest = build(particles=False)
    rest.walls["cell"].motion.size_rates = {}  # restored from the checkpoint
    rest.load_state(state)
    rest.run(steps=600)
    a, b = full.get_particles(), rest.get_particles()
    for k in ("x", "v", "w", "f"):
        assert np.array_equal(a[k], b[k]), k
    assert np.array_equal(full.walls["cell"].params, rest.walls["cell"].params)


# ----------------------------------------------------------------------------------- triangles
def _closest_reference(a, b, c, p):
    """Independent construction: the projection if it falls inside (barycentric by areas), else the
    nearest of the three edges' closest points."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    q = p - ((p - a) @ n) * n
    area = lambda u, v, w: np.cross(v - u, w - u) @ n  # noqa: E731
    tot = area(a, b, c)
    lam = np.array([area(q, b, c), area(a, q, c), area(a, b, q)]) / tot
    if np.all(lam >= 0):
        return q, True
    best = None
    for u, v in ((a, b), (b, c), (c, a)):
        t = np.clip((p - u) @ (v - u) / ((v - u) @ (v - u)), 0.0, 1.0)
        e = u + t * (v - u)
        if best is None or np.linalg.norm(p - e) < np.linalg.norm(p - best):
            best = e
    return best, False


def test_triangle_closest_point_against_independent_construction():
    rng = np.random.default_rng(5)
    for _ in range(400):
        a, b, c = rng.normal(size=(3, 3))
        p = rng.normal(size=3) * 1.5
        params = np.zeros(16)
        params[0:3], params[3:6], params[6:9] = a, b - a, c - a
        gap, nx, ny, nz, cx, cy, cz, inside = triangle_contact(params, p[0], p[1], p[2], 0.1)
        ref, ref_inside = _closest_reference(a, b, c, p)
        assert np.allclose([cx, cy, cz], ref, atol=1e-12)
        assert gap == pytest.approx(np.linalg.norm(p - ref) - 0.1, abs=1e-12)
        assert np.allclose([nx, ny, nz], (ref - p) / np.linalg.norm(ref - p), atol=1e-9)
        if abs(np.linalg.norm(np.cross(ref - p, b - a))) > 1e-9:  # away from degenerate ties
            assert inside == ref_inside
        assert wall_contact(KIND_TRIANGLE, params, p[0], p[1], p[2], 0.1)[0] == gap


def _box_mesh_file(tmp_path, lo, hi):
    import meshio

    lo, hi = np.asarray(lo), np.asarray(hi)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    # faces as quads (vertex index = 4 ix + 2 iy + iz), each split into two triangles
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = [t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]
    path = tmp_path / "box.stl"
    meshio.write_points_cells(path, v, [("triangle", np.array(tris))], binary=False)
    return path


@pytest.mark.integration
def test_stl_box_gives_the_loads_of_the_six_planes(tmp_path):
    lo, hi = np.array([-6 * R, -6 * R, 0.0]), np.array([6 * R, 6 * R, 12 * R])
    rng = np.random.default_rng(2)
    # separated grains (no grain-grain contact: the runs stay comparable to rounding), thrown at the
    # faces, edges, corners and across the faces' diagonals
    # (the floor's facets share the diagonal y = x: four grains sit on it)
    c = (-4.95, -1.6, 1.6, 4.95)
    g = np.array([[x, y, 1.0 * R] for x in c for y in c]) * [R, R, 1]
    g[:, 2] = R * 1.02
    v = rng.normal(0.0, 0.02, g.shape) + 0.05 * np.sign(g) * (np.abs(g) > 4 * R)
    v[:, 2] = -0.05

    class Loads(Boundary):
        """Records, every step, the total load and the load per box face."""

        def __init__(self, faces):
            super().__init__("loads", BoundaryParams(type="probe"))
            self.faces = faces
            self.rows = []

        def after_step(self, sim):
            self.rows.append(np.concatenate([f(sim) for f in self.faces]))

    def run(mesh: bool):
        sim = _sim(gravity=(0, 0, -9.81), friction=0.3)
        sim.add_particles(g, R, velocities=v)
        if mesh:
            box = shapes.TriangleMesh.from_file(_box_mesh_file(tmp_path, lo, hi))
            sim.add_wall(box, name="box")
            # mesh faces as written (two facets each): x-lo, x-hi, y-lo, y-hi, z-lo, z-hi, the order
            # of box_planes
            faces = [lambda s, k=k: s.walls["box"].facet_loads()[2 * k : 2 * k + 2, :3].sum(axis=0)
                     for k in range(6)]  # fmt: skip
        else:
            for k, plane in enumerate(shapes.box_planes(lo, hi)):
                sim.add_wall(plane, name=f"p{k}")
            faces = [lambda s, k=k: s.walls[f"p{k}"].force for k in range(6)]
        probe = sim.add_boundary(Loads(faces))
        sim.dt = 2e-6
        sim.run(steps=3000)
        return sim, np.array(probe.rows)

    (m, lm), (p, lp) = run(True), run(False)
    assert np.count_nonzero(np.abs(lp).sum(axis=1)) > 1000  # loaded most of the time
    assert np.abs(lp[:, 0:3]).max() > 0 and np.abs(lp[:, 6:9]).max() > 0  # x and y faces touched too
    scale = np.abs(lp).max()
    assert np.allclose(lm, lp, rtol=1e-9, atol=1e-9 * scale)
    assert np.allclose(m.walls["box"].force, sum(p.walls[f"p{k}"].force for k in range(6)), atol=1e-9 * scale)
    a, b = m.get_particles(), p.get_particles()
    assert np.allclose(a["x"], b["x"], rtol=0, atol=1e-12)


def test_grain_on_a_facet_diagonal_counts_once():
    """A grain pressed on the shared diagonal of a square made of two triangles gets the load of a
    plane, not twice it."""
    sq = shapes.TriangleMesh([[-2e-3, -2e-3, 0], [2e-3, -2e-3, 0], [2e-3, 2e-3, 0], [-2e-3, 2e-3, 0]],
                             [[0, 1, 2], [0, 2, 3]])

    def settle(shape):
        sim = _sim(friction=0.0)
        sim.add_particles([[1e-4, 1e-4, R]], R)  # over the diagonal y = x
        sim.add_wall(shape, name="w")
        sim.dt = 2e-6
        sim.run(steps=20000)
        return sim

    mesh, plane = settle(sq), settle(shapes.Plane((0, 0, 0), (0, 0, 1)))
    m = RHO * 4 / 3 * math.pi * R**3
    assert mesh.walls["w"].force[2] == pytest.approx(-m * 9.81, rel=1e-3)
    assert mesh.walls["w"].force[2] == pytest.approx(plane.walls["w"].force[2], rel=1e-9)


# ----------------------------------------------------------------------------------- rigid bodies
@pytest.mark.integration
@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_dropped_rigid_ball_falls_freely_then_rests_on_fixed_grains(law):
    sim = _sim(law, gravity=(0, 0, -9.81))
    if law == "complementarity":
        # the body is solved with the grains; at this mass ratio (84:1) projected Jacobi needs far
        # more than 200 iterations per step to converge, APGD about 90 (docs/dem_c.md)
        sim.set_law("complementarity", solver="apgd")
    bed = _column(n_side=7, layers=1, spacing=2.0 * R, origin=(0, 0, R))
    sim.add_particles(bed, R, motion="fixed")
    ball_r, z0, g = 3 * R, 0.02, 9.81
    mass = 7800 * 4 / 3 * math.pi * ball_r**3
    body = RigidBody(mass=mass, gravity=(0, 0, -g), fixed_translation="xy")
    ball = sim.add_wall(shapes.Sphere((0, 0, z0), ball_r), name="ball", motion=body)
    dt = 5e-6 if law == "hertz_mindlin" else 1e-4  # 0.3 of the grains' Rayleigh time
    sim.dt = dt
    n = int(0.02 / dt)  # 20 ms: no contact yet (falls ~2 mm)
    sim.run(steps=n)
    expected = -g * dt * dt * n * (n + 1) / 2  # symplectic Euler, exact for constant gravity
    assert ball.offset[2] == pytest.approx(expected, rel=1e-9)
    assert ball.velocity[2] == pytest.approx(-g * n * dt, rel=1e-9)
    sim.run(until=0.2)  # at rest from ~0.12 s (DEM-P) and ~0.10 s (DEM-C)
    assert abs(ball.velocity[2]) < 1e-3
    assert ball.force[2] == pytest.approx(mass * g, rel=0.02)  # its weight carried by the grains
    gap_to_bed = ball.reference_point[2] - ball_r - 2 * R
    assert -0.1 * R < gap_to_bed < 0.5 * R
