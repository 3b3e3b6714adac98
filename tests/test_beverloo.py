"""tools/beverloo.py: the fit of W = A (D − k d)^b recovers known parameters from exact data, and its
standard errors cover the scatter of noisy data."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import beverloo  # noqa: E402

D_OVER_d = np.array([5.0, 6.5, 8.0, 10.0, 12.0])


@pytest.mark.parametrize(("A", "k", "b"), [(30.0, 1.5, 2.5), (5.0, 2.2, 2.8), (80.0, 0.8, 2.3)])
def test_exact_data_give_the_parameters_back(A, k, b):
    d = 0.002
    D = D_OVER_d * d
    W = A * (D - k * d) ** b
    f = beverloo.fit(D, W, d)
    assert f["b"] == pytest.approx(b, abs=1e-5)
    assert f["k"] == pytest.approx(k, abs=1e-4)
    assert f["A"] == pytest.approx(A, rel=1e-3)
    fixed = beverloo.fit(D, A * (D - k * d) ** 2.5, d, exponent=2.5)
    assert fixed["b"] == 2.5 and fixed["k"] == pytest.approx(k, abs=1e-4)


@pytest.mark.integration
def test_standard_errors_cover_noisy_data():
    """Over 100 noisy data sets (2 % scatter), |b − 2.5| stays within 2 standard errors in about 95 %
    of them (at least 80 %: five points and three parameters make the error itself uncertain)."""
    d, A, k, b = 0.002, 30.0, 1.5, 2.5
    D = np.repeat(D_OVER_d, 2) * d
    rng = np.random.default_rng(7)
    inside = 0
    for _ in range(100):
        W = A * (D - k * d) ** b * np.exp(rng.normal(0.0, 0.02, D.shape))
        f = beverloo.fit(D, W, d)
        inside += abs(f["b"] - b) <= 2 * f["b_err"]
    assert inside >= 80


def test_too_few_points_is_an_error():
    with pytest.raises(ValueError):
        beverloo.fit(np.array([0.01, 0.02]), np.array([1.0, 2.0]), 0.002)
