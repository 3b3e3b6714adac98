"""Writes triaxial_small_packing.txt: 300 glass beads poured into the small triaxial cell's mould.

The tests share this packing instead of pouring it again (a pour of 300 beads takes ~33,000 steps).
It is ``pdem.sources.pluviate`` with the arguments below, written with ``write_spheres_text``
(17 significant digits: it reads back bit for bit). Run ``python tests/data/make_triaxial_small_packing.py``
to make it again after a change to the pour or to the contact kernels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import pdem
from pdem.sources import CylinderRegion, Uniform, pluviate
from pdem.sources.files import read_spheres, write_spheres_text

PATH = Path(__file__).with_name("triaxial_small_packing.txt")
MATERIAL = dict(density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3, friction=0.3)


def pour() -> tuple[np.ndarray, np.ndarray]:
    mat = pdem.Material("glass", **MATERIAL)
    return pluviate(CylinderRegion((0, 0, 0), 3.5e-3, 0.03), Uniform(0.45e-3, 0.55e-3), 300, mat, seed=5)


if __name__ == "__main__":
    x, r = pour()
    write_spheres_text(PATH, x, r)
    back = read_spheres(PATH)
    assert np.array_equal(back["positions"], x) and np.array_equal(back["radii"], r)
    print(f"wrote {PATH} ({len(r)} spheres)")
