"""Contract check for partitioned particle sources; plugin authors reuse it.

    from pdem.testing.source_contract import check_partitioned
    check_partitioned(MySource(params), base_dir=Path("."), seed=1, material=glass)

A partitioned source (``partitioned = True``, :mod:`pdem.sources.api`) must, without
communicating: survey what ``generate`` makes (its count, the box of its centres, its largest
radius, a sample of its centres), and for any box give at least the spheres whose centres lie in it,
each bitwise the sphere ``generate`` returns at the index it names. The check cuts the surveyed
box into ``pieces`` × ``pieces`` × ``pieces`` boxes (and a few random ones), asks for each, and
compares.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..sources.api import SURVEY_SAMPLE, Source, produce_part

__all__ = ["check_partitioned"]


def _same(a, b) -> bool:
    return a is None and b is None or (a is not None and b is not None and np.array_equal(a, b))


def check_partitioned(source: Source, *, base_dir: Path, seed: int, material, pieces: int = 3) -> None:
    """Raise AssertionError naming the first breach of the contract."""
    talk: dict = {}
    if source.collective:  # (checked serially: a one-rank communicator)
        from ..parallel.comm import SerialComm

        talk["comm"] = SerialComm()
    whole = source.generate(base_dir=Path(base_dir), seed=seed, material=material, **talk)
    n = len(whole)
    survey = source.survey(base_dir=Path(base_dir), seed=seed, material=material, **talk)
    assert survey.count == n, f"survey counts {survey.count} spheres, generate makes {n}"
    if n:
        assert np.array_equal(survey.lo, whole.positions.min(axis=0)), "survey.lo is not the centres' minimum"
        assert np.array_equal(survey.hi, whole.positions.max(axis=0)), "survey.hi is not the centres' maximum"
        assert survey.r_max == float(whole.radii.max()), "survey.r_max is not the largest radius"
        assert 0 < survey.sample.shape[0] <= SURVEY_SAMPLE, "the sample is empty or too large"
        rows = {tuple(x) for x in whole.positions}
        stray = [x for x in survey.sample if tuple(x) not in rows]
        assert not stray, f"the sample holds a centre generate does not make: {stray[0]}"
    lo, hi = survey.lo, survey.hi
    edges = [np.linspace(lo[d], hi[d], pieces + 1) for d in range(3)]
    boxes = []
    for i in range(pieces):
        for j in range(pieces):
            for k in range(pieces):
                a = np.array([edges[0][i], edges[1][j], edges[2][k]])
                b = np.array([edges[0][i + 1], edges[1][j + 1], edges[2][k + 1]])
                boxes.append((a, b))
    rng = np.random.default_rng(seed)
    for _ in range(4):
        a, b = np.sort(rng.uniform(lo, hi, (2, 3)), axis=0)
        boxes.append((a, b))
    boxes.append((np.full(3, -np.inf), np.full(3, np.inf)))
    covered = np.zeros(n, dtype=bool)
    for a, b in boxes:
        part = produce_part(source, base_dir=Path(base_dir), seed=seed, material=material, lo=a, hi=b)
        assert part.total == n, f"generate_part's total {part.total} is not generate's count {n}"
        idx = part.index
        out = part.output
        assert np.array_equal(out.positions, whole.positions[idx]), f"positions differ in box {a}..{b}"
        assert np.array_equal(out.radii, whole.radii[idx]), f"radii differ in box {a}..{b}"
        for name in ("velocities", "fixed", "rows"):
            w = getattr(whole, name)
            assert _same(getattr(out, name), None if w is None else w[idx]), f"{name} differ in box {a}..{b}"
        inside = np.flatnonzero(np.all((whole.positions >= a) & (whole.positions <= b), axis=1))
        missing = np.setdiff1d(inside, idx)
        assert not missing.size, f"box {a}..{b}: sphere {missing[0]} lies in it and was not given"
        covered[idx] = True
    assert covered.all(), "some spheres were never given"
