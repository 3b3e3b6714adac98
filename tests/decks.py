"""Small decks the tests share."""

# 64 spheres on a simple cubic lattice above a floor, 20 steps (~0.2 s once the kernels are cached)
TINY_LATTICE = """\
title = "tiny lattice"
[run]
gravity = [0.0, 0.0, -9.81]
dt = 2e-6
[materials.glass]
density = 2500.0
youngs_modulus = 5e7
poisson_ratio = 0.3
restitution = 0.5
friction = 0.5
[[particles]]
source = "lattice"
lattice = "sc"
material = "glass"
radius = 0.5e-3
region = { type = "box", lo = [0.0, 0.0, 0.0], hi = [0.004, 0.004, 0.004] }
[boundaries.floor]
type = "plane"
material = "glass"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
[[stages]]
name = "drop"
[stages.end]
steps = 20
[output]
every_steps = 10
series_every_steps = 10
"""

# the same with a second stage of 20 steps
TINY_LATTICE_TWO_STAGES = TINY_LATTICE.replace(
    "[output]", '[[stages]]\nname = "rest"\n[stages.end]\nsteps = 20\n[output]'
)

# inputs/hopper.toml's DEM-C tables replaced by the engine's plain settings (Jacobi capped at 100 at
# the automatic step, one solver for both stages): tests of solver paths on the hopper set their own
# solver keys on top, which the deck's discharge table would otherwise override
HOPPER_PLAIN_DEM_C = [
    'contact.complementarity={solver="jacobi", tolerance=1.0e-4, max_iterations=100}',
    "stages.discharge.contact={}",
]

# inputs/hopper.toml shortened: 300 beads, 0.03 s of fill, discharge until 0.3 g has left (~6,600
# steps, ~2 s), snapshots every 0.02 s and a checkpoint every 1,000 steps
SHORT_HOPPER_SETS = [
    "particles.0.n=300",
    "particles.0.region.height=0.008",
    "stages.fill.end.time=0.03",
    "stages.fill.end.kinetic_energy_below=1e-12",
    "output.every_time=0.02",
    "boundaries.hopper.outflow_depth=0.004",
    "stages.discharge.end.above=0.0003",
    "output.checkpoint_every_steps=1000",
]

# tests/data/triaxial_small.toml with its 300 beads read from the shared packing
# (tests/data/make_triaxial_small_packing.py) instead of poured again: ``--set`` arguments
TRIAXIAL_SMALL_PACKED = [
    "--set",
    "particles.0={source = 'file', material = 'glass', path = 'triaxial_small_packing.txt'}",
]


def settling_bed(top: float, steps: int, output: str, seed: int = 3, friction: float = 0.4) -> str:
    """600 glass grains (radii 0.45–0.55 mm) filled at random below ``top`` [m] in a 20 × 20 × 40 mm
    rigid box, falling under gravity for ``steps`` steps of 2e-5 s; ``output``: the deck's
    ``[output]`` section (its lines after the header)."""
    return f"""\
title = "a settling bed"
[run]
gravity = [0.0, 0.0, -9.81]
seed = {seed}
dt = 2e-5
[contact]
law = "hertz_mindlin"
[materials.glass]
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.3
restitution = 0.5
friction = {friction}
[materials.wall]
rigid = true
friction = 0.3
[[particles]]
source = "random_fill"
material = "glass"
region = {{ type = "box", lo = [0.0, 0.0, 0.0], hi = [0.02, 0.02, {top}] }}
sizes = {{ type = "uniform", r_min = 0.00045, r_max = 0.00055 }}
n = 600
[boundaries.box]
type = "box"
material = "wall"
lo = [0.0, 0.0, 0.0]
hi = [0.02, 0.02, 0.04]
[[stages]]
name = "settle"
[stages.end]
steps = {steps}
[output]
{output.strip()}
"""

