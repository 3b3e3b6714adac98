"""Semantically hostile decks through the real CLI.

Each case is a small, valid scene (64 spheres on a simple cubic lattice above a floor) broken in one
way a user, a typo or a tester might: absurd or non-finite values, negative sizes, contradictory
stages, missing or damaged packing files, overlapping grains, huge particle counts, bad or broken
plugins, wrong checkpoints, changes a resume does not allow. Every case runs ``pdem.cli.main`` in
this process (a run with ``--steps 5``, or ``pdem resume``), with a time limit.

Required of every case: no traceback (an exception escaping ``main`` or 'Traceback' on stderr), an
exit code of 0, 2 or 3 only, no hang (60 s), and a run refused (exit 2) leaves nothing on disk; a
run that succeeds has written its checkpoint. All 181 cases take about 10 s (kernels cached), so
they all run in the default suite. Measured: 32 run (exit 0), 145 are refused (exit 2), 4 fail
numerically (exit 3: an instability, or a stage reaching its max_time).
"""

# ruff: noqa: E501  (the table of cases reads best with one case per line)

from __future__ import annotations

import signal
import textwrap
from pathlib import Path

import pytest
from decks import TINY_LATTICE_TWO_STAGES

from pdem.cli import main

BASE = TINY_LATTICE_TWO_STAGES.replace("tiny lattice", "fuzz base")

FILE_SOURCE = '[[particles]]\nsource = "file"\nmaterial = "glass"\npath = "pack.txt"\n'
LATER_FILE_SOURCE = FILE_SOURCE + 'stage = "rest"\n'

# a third-party package with broken plugins, found by importlib.metadata on sys.path
PLUGIN_MODULE = textwrap.dedent(
    """
    from pdem.api import Boundary, BoundaryParams, Writer


    class BuildFails(Boundary):
        Params = BoundaryParams

        def build(self, sim):
            raise ZeroDivisionError("a bug in the plugin's build")


    class NoParams:
        Params = None


    class InitFails(Boundary):
        Params = BoundaryParams

        def __init__(self, name, params):
            raise KeyError("a bug in the plugin's constructor")


    class WriterFails(Writer):
        name = "fuzz_writer"

        def __init__(self, directory, **kwargs):
            raise ValueError("a bug in the writer's constructor")
    """
)
ENTRY_POINTS = textwrap.dedent(
    """
    [pdem.boundaries]
    fuzz_build_fails = pdem_fuzz_plugins:BuildFails
    fuzz_no_params = pdem_fuzz_plugins:NoParams
    fuzz_init_fails = pdem_fuzz_plugins:InitFails
    fuzz_missing_module = pdem_fuzz_missing:Anything

    [pdem.writers]
    fuzz_writer = pdem_fuzz_plugins:WriterFails
    """
)


def _packing(rows: list[tuple[float, float, float, float]]) -> str:
    return "x y z diameter\n" + "".join(" ".join(repr(v) for v in r) + "\n" for r in rows)


GOOD_PACK = _packing([(0.01, 0.0, 0.002, 0.001), (0.013, 0.0, 0.002, 0.001)])


def S(*sets: str) -> dict:
    return {"sets": list(sets)}


def R(old: str, new: str, **kw) -> dict:
    return {"replace": (old, new), **kw}


# name -> case: "sets" (--set texts), "replace" (old, new) in BASE, "text" (whole deck), "append" (text
# added to BASE), "files" (name -> str or bytes), "cmd" ("run", "check", "resume"), "args" (extra)
CASES: dict[str, dict] = {
    # ---- [run]
    "dt 1e-300 with a timed stage": S("run.dt=1e-300", "stages.drop.end={time = 1.0}"),
    "dt above the stability limit": S("run.dt=1e-2"),
    "dt negative": S("run.dt=-1e-6"),
    "dt nan": S("run.dt=nan"),
    "dt inf": S("run.dt=inf"),
    "dt as a string": S('run.dt="2e-6"'),
    "dt huge with force_dt": S("run.dt=1e-3", "run.force_dt=true"),
    "gravity enormous": S("run.gravity=[0, 0, -1e30]"),
    "gravity nan": S("run.gravity=[nan, 0, 0]"),
    "gravity two components": S("run.gravity=[0, -9.81]"),
    "skin negative": S("run.skin=-1e-3"),
    "skin enormous": S("run.skin=1e3"),
    "skin tiny": S("run.skin=1e-300"),
    "max_overlap zero": S("run.max_overlap=0.0"),
    "max_overlap one": S("run.max_overlap=1.0"),
    "seed negative": S("run.seed=-1"),
    "seed huge": S("run.seed=9223372036854775807"),
    "decomposition zero": S("run.decomposition=[0, 0, 0]"),
    "decomposition for 8 ranks on 1": S("run.decomposition=[2, 2, 2]"),
    "balance_threshold 1": S("run.balance_threshold=1.0"),
    "max_particles below the deck": S("run.max_particles=10"),
    "max_particles zero": S("run.max_particles=0"),
    "max_particles above the id range": S("run.max_particles=4294967296"),
    "unknown run key": S("run.timestep=1e-6"),
    # ---- materials
    "density zero": S("materials.glass.density=0.0"),
    "density enormous": S("materials.glass.density=1e300"),
    "density nan": S("materials.glass.density=nan"),
    "Young's modulus tiny": S("materials.glass.youngs_modulus=1e-300"),
    "Young's modulus enormous": S("materials.glass.youngs_modulus=1e300"),
    "Poisson ratio -1": S("materials.glass.poisson_ratio=-1.0"),
    "Poisson ratio 0.5": S("materials.glass.poisson_ratio=0.5"),
    "restitution zero": S("materials.glass.restitution=0.0"),
    "restitution one": S("materials.glass.restitution=1.0"),
    "restitution negative": S("materials.glass.restitution=-0.1"),
    "friction enormous": S("materials.glass.friction=1e300"),
    "rolling friction enormous": S("materials.glass.rolling_friction=1e10"),
    "no materials": R("[materials.glass]\ndensity = 2500.0\nyoungs_modulus = 5e7\npoisson_ratio = 0.3\n"
                      "restitution = 0.5\nfriction = 0.5\n", ""),
    "material pair unknown": {"append": '[[material_pairs]]\nmaterials = ["glass", "sand"]\nfriction = 0.1\n'},
    "material pair without values": {"append": '[[material_pairs]]\nmaterials = ["glass", "glass"]\n'},
    "material pair twice": {"append": '[[material_pairs]]\nmaterials = ["glass", "glass"]\nfriction = 0.1\n'
                            '[[material_pairs]]\nmaterials = ["glass", "glass"]\nfriction = 0.2\n'},
    # ---- lattice source
    "radius zero": S("particles.0.radius=0.0"),
    "radius negative": S("particles.0.radius=-0.5e-3"),
    "radius nan": S("particles.0.radius=nan"),
    "radius larger than the region": S("particles.0.radius=1.0"),
    "spacing below the diameter": S("particles.0.spacing=0.5e-3"),
    "spacing enormous": S("particles.0.spacing=1e3"),
    "region inverted": S("particles.0.region.hi=[-0.004, 0.004, 0.004]"),
    "region degenerate": S("particles.0.region.hi=[0.0, 0.004, 0.004]"),
    "region cylinder negative radius": S("particles.0.region={type = 'cylinder', base_center = [0, 0, 0], "
                                         "radius = -1.0, height = 0.004}"),
    "region unknown type": S("particles.0.region={type = 'sphere', radius = 1.0}"),
    "lattice of 1e9 spheres": S("particles.0.radius=5e-6", "particles.0.region.hi=[0.01, 0.01, 0.02]"),
    "hex2d of 1e12 spheres": S("particles.0={source = 'lattice', lattice = 'hex2d', material = 'glass', "
                               "radius = 1e-3, n_cols = 1000000, n_rows = 1000000}"),
    "hex2d with a region": S("particles.0.lattice='hex2d'"),
    "unknown lattice": S("particles.0.lattice='bcc'"),
    "unknown source": S("particles.0.source='cloud'"),
    "source of unknown stage": S("particles.0.stage='later'"),
    "source material unknown": S("particles.0.material='sand'"),
    "velocity enormous": S("particles.0.velocity=[1e300, 0, 0]"),
    "velocity nan": S("particles.0.velocity=[nan, 0, 0]"),
    "motion unknown": S("particles.0.motion='flying'"),
    "motion prescribed": S("particles.0.motion='prescribed'", "particles.0.velocity=[0, 0, 1.0]"),
    "motion fixed": S("particles.0.motion='fixed'"),
    # ---- random fill and pluviation
    "random fill n zero": S("particles.0={source = 'random_fill', material = 'glass', n = 0, "
                            "sizes = {type = 'single', radius = 1e-4}, region = {type = 'box', lo = [0, 0, 0], "
                            "hi = [0.004, 0.004, 0.004]}}"),
    "random fill n 1e12": S("particles.0={source = 'random_fill', material = 'glass', n = 1000000000000, "
                            "sizes = {type = 'single', radius = 1e-3}, region = {type = 'box', "
                            "lo = [-1e3, -1e3, 1], hi = [1e3, 1e3, 1e3]}}"),
    "random fill too dense": S("particles.0={source = 'random_fill', material = 'glass', n = 5000, "
                               "sizes = {type = 'single', radius = 1e-4}, region = {type = 'box', "
                               "lo = [0, 0, 0], hi = [0.004, 0.004, 0.004]}}"),
    "random fill that jams": S("particles.0={source = 'random_fill', material = 'glass', "
                               "volume_fraction = 0.49, sizes = {type = 'single', radius = 2e-4}, "
                               "region = {type = 'box', lo = [0, 0, 0], hi = [0.004, 0.004, 0.004]}}"),
    "random fill n and volume fraction": S("particles.0={source = 'random_fill', material = 'glass', n = 10, "
                                           "volume_fraction = 0.1, sizes = {type = 'single', radius = 1e-4}, "
                                           "region = {type = 'box', lo = [0, 0, 0], hi = [0.004, 0.004, 0.004]}}"),
    "sizes r_min above r_max": S("particles.0={source = 'random_fill', material = 'glass', n = 10, "
                                 "sizes = {type = 'uniform', r_min = 2e-4, r_max = 1e-4}, "
                                 "region = {type = 'box', lo = [0, 0, 0], hi = [0.004, 0.004, 0.004]}}"),
    "sizes normal reaching below zero": S("particles.0={source = 'random_fill', material = 'glass', n = 10, "
                                          "sizes = {type = 'normal', mean = 1e-4, std = 1e-4}, "
                                          "region = {type = 'box', lo = [0, 0, 0], hi = [0.004, 0.004, 0.004]}}"),
    "sizes table not summing to one": S("particles.0={source = 'random_fill', material = 'glass', n = 10, "
                                        "sizes = {type = 'table', radii = [1e-4, 2e-4], mass_fractions = "
                                        "[0.5, 0.6]}, region = {type = 'box', lo = [0, 0, 0], "
                                        "hi = [0.004, 0.004, 0.004]}}"),
    "sizes table with a zero radius": S("particles.0={source = 'random_fill', material = 'glass', n = 10, "
                                        "sizes = {type = 'table', radii = [0.0, 2e-4], mass_fractions = "
                                        "[0.5, 0.5]}, region = {type = 'box', lo = [0, 0, 0], "
                                        "hi = [0.004, 0.004, 0.004]}}"),
    "pluviate n 1e12": S("particles.0={source = 'pluviate', material = 'glass', n = 1000000000000, "
                         "sizes = {type = 'single', radius = 1e-3}, region = {type = 'box', lo = [0, 0, 0], "
                         "hi = [1, 1, 1]}}"),
    "pluviate fill fraction 0.9": S("particles.0={source = 'pluviate', material = 'glass', n = 10, "
                                    "fill_fraction = 0.9, sizes = {type = 'single', radius = 1e-3}, "
                                    "region = {type = 'box', lo = [0, 0, 0], hi = [0.01, 0.01, 0.01]}}"),
    # ---- packing files
    "file missing": {"append": FILE_SOURCE},
    "file empty": {"append": FILE_SOURCE, "files": {"pack.txt": ""}},
    "file header only": {"append": FILE_SOURCE, "files": {"pack.txt": "x y z diameter\n"}},
    "file binary garbage": {"append": FILE_SOURCE, "files": {"pack.txt": bytes(range(256)) * 4}},
    "file with nan": {"append": FILE_SOURCE, "files": {"pack.txt": "0.01 0 0.002 nan\n"}},
    "file with inf": {"append": FILE_SOURCE, "files": {"pack.txt": "inf 0 0.002 0.001\n"}},
    "file with a negative diameter": {"append": FILE_SOURCE, "files": {"pack.txt": "0.01 0 0.002 -0.001\n"}},
    "file with three columns": {"append": FILE_SOURCE, "files": {"pack.txt": "0.01 0 0.002\n"}},
    "file with overlapping grains": {"append": FILE_SOURCE, "files": {
        "pack.txt": _packing([(0.01, 0.0, 0.002, 0.001), (0.0101, 0.0, 0.002, 0.001)])}},
    "file grain below the floor": {"append": FILE_SOURCE, "files": {"pack.txt": _packing([(0.01, 0.0, -0.01, 0.001)])}},
    "file grain overlapping the lattice": {"append": FILE_SOURCE, "files": {
        "pack.txt": _packing([(0.0005, 0.0005, 0.0005, 0.001)])}},
    "file grain very far away": {"append": FILE_SOURCE, "files": {"pack.txt": _packing([(1e10, 0.0, 0.002, 0.001)])}},
    "file grain enormous": {"append": FILE_SOURCE, "files": {"pack.txt": _packing([(0.0, 0.0, 1e9, 2e9)])}},
    "file coordinates 1e300": {"append": FILE_SOURCE, "files": {"pack.txt": _packing([(1e300, 0.0, 0.002, 0.001)])}},
    "file h5 that is text": {"append": FILE_SOURCE.replace("pack.txt", "pack.h5"), "files": {"pack.h5": "x y z d\n"}},
    "file is a directory": {"append": FILE_SOURCE.replace("pack.txt", "."), "files": {}},
    "file of a later stage with nan": {"append": LATER_FILE_SOURCE, "files": {"pack.txt": "0.01 0 0.002 nan\n"}},
    "file of a later stage, fine": {"append": LATER_FILE_SOURCE, "files": {"pack.txt": GOOD_PACK}},
    "file with an unknown header": {"append": FILE_SOURCE, "files": {"pack.txt": "x y z colour\n0 0 0 1\n"}},
    # ---- boundaries
    "boundary unknown type": S("boundaries.floor.type='floor'"),
    "plane normal zero": S("boundaries.floor.normal=[0, 0, 0]"),
    "plane normal nan": S("boundaries.floor.normal=[nan, 0, 1]"),
    "plane through the grains": S("boundaries.floor.point=[0, 0, 0.002]"),
    "plane facing away": S("boundaries.floor.normal=[0, 0, -1]"),
    "wall material unknown": S("boundaries.floor.material='steel'"),
    "wall stages unknown": S("boundaries.floor.stages=['later']"),
    "wall moving at 1e300 m/s": S("boundaries.floor.motion={type = 'constant_velocity', velocity = [0, 0, 1e300]}"),
    "wall motion unknown": S("boundaries.floor.motion={type = 'spiral'}"),
    "boundary name with a space": {"append": '[boundaries."my wall"]\ntype = "plane"\nmaterial = "glass"\n'
                                   'point = [0, 0, -1]\nnormal = [0, 0, 1]\n'},
    "box inverted": {"append": '[boundaries.box]\ntype = "box"\nmaterial = "glass"\nlo = [1, 1, 1]\nhi = [0, 0, 0]\n'},
    "box unknown face": {"append": '[boundaries.box]\ntype = "box"\nmaterial = "glass"\nlo = [-1, -1, -1]\n'
                         'hi = [1, 1, 1]\nopen_faces = ["top"]\n'},
    "hopper top below orifice": {"append": '[boundaries.h]\ntype = "hopper"\nmaterial = "glass"\n'
                                 'orifice_center = [0, 0, -0.1]\norifice_diameter = 0.02\nhalf_angle_deg = 30.0\n'
                                 'top_diameter = 0.01\nbarrel_height = 0.0\nopen_at_stage = "rest"\n'
                                 'outflow_depth = 0.01\n'},
    "hopper opening at an unknown stage": {"append": '[boundaries.h]\ntype = "hopper"\nmaterial = "glass"\n'
                                           'orifice_center = [0, 0, -0.1]\norifice_diameter = 0.002\n'
                                           'half_angle_deg = 30.0\ntop_diameter = 0.01\nbarrel_height = 0.0\n'
                                           'open_at_stage = "later"\noutflow_depth = 0.01\n'},
    "outflow above everything": {"append": '[boundaries.sink]\ntype = "outflow"\npoint = [0, 0, 1]\n'
                                 'normal = [0, 0, 1]\n'},
    "cylinder negative radius": {"append": '[boundaries.c]\ntype = "cylinder"\nmaterial = "glass"\n'
                                 'point = [0, 0, 0]\naxis = [0, 0, 1]\nradius = -1.0\n'},
    # ---- stages
    "no stages": R('[[stages]]\nname = "drop"\n[stages.end]\nsteps = 20\n[[stages]]\nname = "rest"\n'
                   '[stages.end]\nsteps = 20\n', ""),
    "stage without end": S("stages.drop.end={}"),
    "only max_time": S("stages.drop.end={max_time = 1.0}"),
    "time negative": S("stages.drop.end={time = -1.0}"),
    "steps zero": S("stages.drop.end={steps = 0}"),
    "steps 1e12": S("stages.drop.end={steps = 1000000000000}"),
    "max_time below time": S("stages.drop.end={time = 1e-3, max_time = 1e-5}"),
    "max_time reached": S("stages.drop.end={time = 1e-3, kinetic_energy_below = 1e-30, max_time = 4e-6}"),
    "kinetic energy below 1e300": S("stages.drop.end={kinetic_energy_below = 1e300, check_every = 5}"),
    "quantity of an unknown key": S("stages.drop.end={quantity = 'floor.nothing', above = 1.0}"),
    "quantity of an unknown boundary": S("stages.drop.end={quantity = 'lid.fz', above = 1.0}"),
    "quantity with above and below": S("stages.drop.end={quantity = 'floor.fz', above = 1.0, below = 0.0}"),
    "quantity without a dot": S("stages.drop.end={quantity = 'floor', above = 1.0}"),
    "quantity that never ends": S("stages.drop.end={quantity = 'floor.fz', above = 1e300, check_every = 1}"),
    "check_every zero": S("stages.drop.end={steps = 10, check_every = 0}"),
    "duplicate stage names": S("stages.1.name='drop'"),
    "stage name with a dot": S("stages.1.name='re.st'"),
    "stage dt above the limit": S("stages.rest.dt=1e-2"),
    "stage dt 1e-300 by steps": S("stages.rest.dt=1e-300"),
    "stage dt 1e-300 by time": S("stages.rest.dt=1e-300", "stages.rest.end={time = 1.0}"),
    "stage snapshots every 1e-300 s": S("stages.drop.output={every_time = 1e-300}"),
    "stage snapshots every 0 steps": S("stages.drop.output={every_steps = 0}"),
    "stage output both cadences": S("stages.drop.output={every_steps = 1, every_time = 1e-5}"),
    # ---- output
    "unknown format": S("output.formats=['netcdf']"),
    "broken writer plugin": S("output.formats=['fuzz_writer']"),
    "no formats": S("output.formats=[]"),
    "vtk only": S("output.formats=['vtk']"),
    "format twice": S("output.formats=['hdf5', 'hdf5']"),
    "no fields": S("output.fields=[]"),
    "unknown field": S("output.fields=['x', 'colour']"),
    "per rank on one rank": S("output.parallel='per_rank'"),
    "series every 1e18 steps": S("output.series_every_steps=1000000000000000000"),
    "checkpoint every step": S("output.checkpoint_every_steps=1"),
    "output directory /dev/null": {"sets": ["output.directory='/dev/null'"], "no_output_arg": True},
    "output directory empty string": {"sets": ["output.directory=''"], "no_output_arg": True},
    # ---- domain
    "periodic inverted box": S("domain.periodic=['x']", "domain.lo=[1, 0, 0]", "domain.hi=[0, 1, 1]"),
    "periodic box too small": S("domain.periodic=['x']", "domain.lo=[0, 0, 0]", "domain.hi=[0.001, 1, 1]"),
    "periodic unknown axis": S("domain.periodic=['w']", "domain.lo=[0, 0, 0]", "domain.hi=[1, 1, 1]"),
    "periodic along the floor normal": S("domain.periodic=['z']", "domain.lo=[-1, -1, -1]", "domain.hi=[1, 1, 1]"),
    "periodic without a box": S("domain.periodic=['x']"),
    # ---- contact law
    "unknown law": S("contact.law='hertz'"),
    "unknown law parameter": S("contact.clamp_normall=true"),
    "coefficients without kn": S("contact.parameterisation='coefficients'"),
    "coefficients negative": S("contact.parameterisation='coefficients'", "contact.kn=-1.0", "contact.kt=1.0",
                               "contact.cn=0.0", "contact.ct=0.0"),
    "complementarity tolerance negative": S("contact.law='complementarity'", "contact.tolerance=-1.0"),
    "complementarity with APGD": S("contact.law='complementarity'", "contact.solver='apgd'", "run.dt=1e-4"),
    "plugin law": S("contact.law='linear_spring'"),
    # ---- plugins
    "boundary plugin whose build fails": {"append": '[boundaries.bad]\ntype = "fuzz_build_fails"\n'},
    "boundary plugin without Params": {"append": '[boundaries.bad]\ntype = "fuzz_no_params"\n'},
    "boundary plugin whose constructor fails": {"append": '[boundaries.bad]\ntype = "fuzz_init_fails"\n'},
    "boundary plugin that does not import": {"append": '[boundaries.bad]\ntype = "fuzz_missing_module"\n'},
    # ---- the deck file itself
    "deck is not TOML": {"text": "this is [not toml"},
    "deck is binary": {"text": bytes(range(256))},
    "deck is empty": {"text": ""},
    "deck is a directory": {"deck_is_dir": True},
    "deck missing": {"deck_missing": True},
    "title 50 MB": {"replace": ('title = "fuzz base"', 'title = "' + "x" * 50_000_000 + '"')},
    "title with control characters": {"replace": ('title = "fuzz base"', 'title = "a\\u0001b\\u001fc"')},
    "malformed --set": S("run.dt"),
    "--set of a scalar as a table": S("run.dt.x=1"),
    "--set index far out of range": S("stages.7.name='x'"),
    # ---- resume
    "resume a text file": {"cmd": "resume", "checkpoint": "deck"},
    "resume a missing file": {"cmd": "resume", "checkpoint": "missing"},
    "resume a directory": {"cmd": "resume", "checkpoint": "dir"},
    "resume changing a material": {"cmd": "resume", "args": ["--set", "materials.glass.density=1.0"]},
    "resume changing gravity": {"cmd": "resume", "args": ["--set", "run.gravity=[0, 0, 0]"]},
    "resume changing the particles": {"cmd": "resume", "args": ["--set", "particles.0.radius=1e-4"]},
    "resume dt above the limit": {"cmd": "resume", "args": ["--set", "run.dt=1.0"]},
    "resume steps before the checkpoint": {"cmd": "resume", "args": ["--steps", "5"]},
    "resume renaming the current stage": {"cmd": "resume", "args": ["--set", "stages.0.name='fall'"]},
    "resume adding a stage": {"cmd": "resume", "args": ["--set", "stages.2.name='more'",
                                                        "--set", "stages.2.end.steps=5"]},
    "resume changing the end": {"cmd": "resume", "args": ["--set", "stages.drop.end.steps=15"]},
    "resume to /dev/null": {"cmd": "resume", "args": ["--output", "/dev/null"]},
}  # fmt: skip


class Hang(Exception):
    """A case ran longer than its time limit."""


# a case runs 5 steps in seconds once compiled; the limit catches a hang, with room for a first
# compilation of the method's kernels on a loaded machine with an empty numba cache (~1 min)
LIMIT_S = 300


def _alarm(signum, frame):
    raise Hang(f"the case did not finish within {LIMIT_S} s")


@pytest.fixture
def plugins(tmp_path_factory, monkeypatch):
    """The broken plugins as an installed distribution on sys.path."""
    site = tmp_path_factory.mktemp("fuzz_site")
    (site / "pdem_fuzz_plugins.py").write_text(PLUGIN_MODULE)
    info = site / "pdem_fuzz_plugins-0.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: pdem-fuzz-plugins\nVersion: 0.0\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    monkeypatch.syspath_prepend(str(site))
    return site


def tree(directory: Path) -> list[str]:
    return sorted(str(p.relative_to(directory)) for p in directory.rglob("*"))


def run_case(name: str, case: dict, tmp: Path, capsys) -> tuple[int, str]:
    deck = tmp / "deck.toml"
    text = case.get("text", BASE)
    if "replace" in case:
        old, new = case["replace"]
        assert old in text, name
        text = text.replace(old, new)
    text = text + case.get("append", "") if isinstance(text, str) else text
    if case.get("deck_is_dir"):
        deck.mkdir()
    elif not case.get("deck_missing"):
        deck.write_bytes(text.encode() if isinstance(text, str) else text)
    for fname, content in case.get("files", {}).items():
        (tmp / fname).write_bytes(content.encode() if isinstance(content, str) else content)
    sets = [a for s in case.get("sets", []) for a in ("--set", s)]
    out = tmp / "out"
    cmd = case.get("cmd", "run")
    if cmd == "resume":
        good = tmp / "good.toml"
        good.write_text(BASE)
        assert main([str(good), "--output", str(tmp / "prev"), "--steps", "10", "--quiet"]) == 0
        ckpt = {
            "deck": good,
            "missing": tmp / "missing.h5",
            "dir": tmp / "prev",
        }.get(case.get("checkpoint"), tmp / "prev" / "checkpoints" / "latest.h5")
        capsys.readouterr()
        args = ["resume", str(ckpt), "--quiet", *case.get("args", [])]
    elif cmd == "check":
        args = ["check", str(deck), *sets]
    else:
        args = [str(deck), *sets, "--steps", "5", "--quiet"]
        if not case.get("no_output_arg"):
            args += ["--output", str(out)]
    before = tree(tmp)
    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(LIMIT_S)
    try:
        code = main(args)
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    finally:
        signal.alarm(0)
    err = capsys.readouterr().err
    assert "Traceback" not in err, (name, err)
    assert code in (0, 2, 3), (name, code, err[-2000:])
    if code == 2:
        assert tree(tmp) == before, (name, "a refused run left files", sorted(set(tree(tmp)) - set(before)))
    if code == 0 and cmd == "run" and not case.get("no_output_arg"):
        assert (out / "checkpoints" / "latest.h5").exists(), name
    return code, err


# the 50 MB deck is parsed and run in full (10 s on 2 cores): an integration run
@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.integration) if n == "title 50 MB" else n for n in CASES]
)
def test_hostile_deck(name, tmp_path, capsys, plugins, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run_case(name, CASES[name], tmp_path, capsys)


def test_there_are_more_than_100_cases():
    assert len(CASES) >= 100
