"""tools/mohr_coulomb.py: the fits recover a known envelope (closed form), and the tool reads run
outputs of both tests (summary.json + series CSVs as pdem writes them)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from pdem.io.series import SeriesWriter

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import mohr_coulomb as mc  # noqa: E402


def _sigma1(s3: float, phi_deg: float, c: float) -> float:
    """Major stress at failure on the envelope τ = c + σ tan φ (closed form)."""
    sp, cp = math.sin(math.radians(phi_deg)), math.cos(math.radians(phi_deg))
    return s3 * (1 + sp) / (1 - sp) + 2 * c * cp / (1 - sp)


@pytest.mark.parametrize("phi, c", [(22.0, 0.0), (31.5, 1500.0)])
def test_triaxial_envelope_recovers_phi_and_c(phi, c):
    pairs = [(_sigma1(s3, phi, c), s3) for s3 in (5e4, 1e5, 2e5)]
    fit = mc.fit_triaxial(pairs)
    assert fit["phi_deg"] == pytest.approx(phi, abs=1e-9)
    assert fit["cohesion_pa"] == pytest.approx(c, abs=1e-6)
    assert fit["r2"] == pytest.approx(1.0, abs=1e-12)


def test_shear_envelope_and_r2_of_noisy_points():
    sigma = np.array([3100.0, 6400.0, 12500.0, 24200.0])
    tau = 0.45 * sigma + 100.0
    fit = mc.fit_shear(sigma, tau)
    assert fit["phi_deg"] == pytest.approx(math.degrees(math.atan(0.45)), abs=1e-9)
    assert fit["cohesion_pa"] == pytest.approx(100.0, abs=1e-6)
    noisy = mc.fit_shear(sigma, tau * np.array([1.1, 0.9, 1.1, 0.9]))
    assert noisy["r2"] < 0.999  # the R² does fall when the points leave the line


def _write_series(path: Path, rows: list[dict]) -> None:
    w = SeriesWriter(path, list(rows[0]))
    for r in rows:
        w.append(r)
    w.close()


def test_reads_triaxial_and_shear_outputs(tmp_path):
    phi = 24.0
    outs = []
    for s3 in (5e4, 1e5, 2e5):
        out = tmp_path / f"tx{int(s3)}"
        out.mkdir()
        ea = np.linspace(0.001, 0.2, 50)
        q_peak = _sigma1(s3, phi, 0.0) - s3
        q = q_peak * np.minimum(ea / 0.02, 1.0) * np.where(ea > 0.1, 1 - 0.5 * (ea - 0.1), 1.0)
        _write_series(out / "series_shear.csv", [
            {"time": k, "step": k, "cell.eps_a": e, "cell.q": qq, "cell.sigma3": s3, "cell.eps_v": -e / 10}
            for k, (e, qq) in enumerate(zip(ea, q, strict=True))
        ])  # fmt: skip
        (out / "summary.json").write_text(json.dumps({"results": {"cell": {"q_peak": float(q.max())}}}))
        outs.append(out)
    for sn in (3100.0, 6400.0):
        out = tmp_path / f"ds{int(sn)}"
        out.mkdir()
        u = np.linspace(1e-4, 0.01, 20)
        _write_series(out / "series_shear.csv", [
            {"time": k, "step": k, "box.displacement": x, "box.ratio": 0.5, "box.normal_stress": sn,
             "box.dilation": 1e-4} for k, x in enumerate(u)
        ])  # fmt: skip
        res = {"peak_ratio": 0.55, "residual_ratio": 0.45, "peak_displacement": 0.004, "max_dilation": 2e-4}
        (out / "summary.json").write_text(json.dumps({"results": {"box": res}}))
        outs.append(out)
    prefix = tmp_path / "mc"
    assert mc.main([*map(str, outs), "--out", str(prefix)]) == 0
    data = json.loads(Path(f"{prefix}.json").read_text())
    assert data["fits"]["triaxial"]["peak"]["phi_deg"] == pytest.approx(phi, abs=1e-6)
    assert data["fits"]["direct_shear"]["peak"]["phi_deg"] == pytest.approx(math.degrees(math.atan(0.55)))
    assert data["fits"]["direct_shear"]["residual"]["cohesion_pa"] == pytest.approx(0.0, abs=1e-6)
    assert Path(f"{prefix}.png").stat().st_size > 10_000
    assert len(Path(f"{prefix}.csv").read_text().splitlines()) == 6


def test_runs_at_one_stress_get_their_mean_angle_not_an_envelope(tmp_path, capsys):
    """Seeds at one cell pressure: a line through (nearly) equal abscissae is noise (it gave φ = 90°
    and c = −1.9e12 Pa on two real 100 kPa runs); the tool reports the runs' own angles instead."""
    outs, phis = [], (21.0, 23.0, 22.0)
    for k, phi in enumerate(phis):
        out = tmp_path / f"seed{k}"
        out.mkdir()
        s3 = 1e5 * (1.0 + 1e-4 * k)  # realised pressures differ in the last digits
        ea = np.linspace(0.001, 0.2, 50)
        q = (_sigma1(s3, phi, 0.0) - s3) * np.minimum(ea / 0.02, 1.0)
        _write_series(out / "series_shear.csv", [
            {"time": i, "step": i, "cell.eps_a": e, "cell.q": qq, "cell.sigma3": s3, "cell.eps_v": 0.0}
            for i, (e, qq) in enumerate(zip(ea, q, strict=True))
        ])  # fmt: skip
        (out / "summary.json").write_text(json.dumps({"results": {"cell": {"q_peak": float(q.max())}}}))
        outs.append(out)
    prefix = tmp_path / "mc"
    assert mc.main([*map(str, outs), "--out", str(prefix)]) == 0
    fits = json.loads(Path(f"{prefix}.json").read_text())["fits"]["triaxial"]
    assert set(fits) == {"one_stress"}
    peak = fits["one_stress"]["peak"]
    assert peak["runs"] == 3
    assert peak["phi_deg_mean"] == pytest.approx(np.mean(phis), abs=1e-3)
    assert peak["phi_deg_std"] == pytest.approx(np.std(phis, ddof=1), abs=1e-3)
    assert "no envelope" in capsys.readouterr().out
    assert Path(f"{prefix}.png").stat().st_size > 10_000


def test_friction_study_skips_finished_runs_and_fits(tmp_path, capsys):
    import friction_study as fs

    deck = ROOT / "inputs" / "examples" / "direct_shear_small.toml"
    assert fs.main(["direct_shear", str(deck), "--dry-run", "--stress", "3100", "6400", "--ranks", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and "-n 2" in lines[0]
    assert "boundaries.box.normal_stress=3100.0" in lines[0]
    assert "boundaries.box.normal_stress=6400.0" in lines[1]
    # finished runs (a study record with the same overrides) are kept, not run again; then the fit is made
    from pdem.study.launch import RECORD, RunRecord

    for sn, ratio in ((3100.0, 0.5), (6400.0, 0.5)):
        out = tmp_path / f"{sn:g}"
        out.mkdir()
        _write_series(out / "series_shear.csv", [
            {"time": k, "step": k, "box.displacement": 1e-3 * (k + 1), "box.ratio": ratio,
             "box.normal_stress": sn, "box.dilation": 0.0} for k in range(5)
        ])  # fmt: skip
        res = {"peak_ratio": ratio, "residual_ratio": ratio, "peak_displacement": 0.004, "max_dilation": 0.0}
        (out / "summary.json").write_text(json.dumps({"results": {"box": res}}))
        record = RunRecord([f"boundaries.box.normal_stress={sn!r}"], [], 0, "ok", 1.0)
        (out / RECORD).write_text(record.to_json())
    code = fs.main(["direct_shear", str(deck), "--stress", "3100", "6400", "--out", str(tmp_path)])
    assert code == 0
    fit = json.loads((tmp_path / "mohr_coulomb.json").read_text())["fits"]["direct_shear"]["peak"]
    assert fit["phi_deg"] == pytest.approx(math.degrees(math.atan(0.5)))
    # constant stiffness number: E scales with the stress (the deck's E at the deck's stress)
    tri = ROOT / "inputs" / "triaxial.toml"
    args = ["triaxial", str(tri), "--dry-run", "--stress", "5e4", "2e5", "--constant-stiffness", "glass"]
    capsys.readouterr()
    assert fs.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "materials.glass.youngs_modulus=50000000.0" in lines[0]
    assert "materials.glass.youngs_modulus=200000000.0" in lines[1]
    with pytest.raises(SystemExit, match="shear_box"):
        fs.main(["direct_shear", str(ROOT / "inputs" / "triaxial.toml"), "--dry-run"])


def test_moving_average_is_the_window_mean():
    x = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    y = np.array([1.0, 3.0, np.nan, 5.0, 7.0])
    assert np.allclose(mc.moving_average(x, y, 2.0), [2.0, 2.0, 4.0, 6.0, 6.0])
    assert np.array_equal(mc.moving_average(x, y, 0.0)[[0, 1, 3, 4]], y[[0, 1, 3, 4]])


@pytest.mark.parametrize("rows", [80, 2000])
def test_smoothed_peak_of_a_noisy_shear_curve(tmp_path, rows):
    """A curve rising to 0.6 at 2 mm and falling to 0.5, with ±0.1 noise on every row: the largest
    row reads the noise (and grows with the number of rows); averaged over 0.5 mm, the peak is the
    curve's within the noise's residue, at the right displacement."""
    rng = np.random.default_rng(7)
    u = np.linspace(1e-5, 0.004, rows)
    true = np.where(u < 0.002, 0.6 * u / 0.002, 0.6 - 50.0 * (u - 0.002))
    noisy = true + rng.uniform(-0.1, 0.1, rows)
    out = tmp_path / "ds"
    out.mkdir()
    _write_series(out / "series_shear.csv", [
        {"time": k, "step": k, "box.displacement": x, "box.ratio": r, "box.plane_ratio": r,
         "box.normal_stress": 3100.0, "box.dilation": 0.0}
        for k, (x, r) in enumerate(zip(u, noisy, strict=True))
    ])  # fmt: skip
    res = {"peak_ratio": float(noisy.max()), "residual_ratio": 0.5,
           "peak_displacement": float(u[noisy.argmax()]), "max_dilation": 0.0,
           "peak_plane_ratio": float(noisy.max()), "residual_plane_ratio": 0.5,
           "plane_normal_stress_mean": 3100.0}  # fmt: skip
    (out / "summary.json").write_text(json.dumps({"results": {"box": res}}))
    raw = mc.read_run(out, 0.2)
    smooth = mc.read_run(out, 0.2, smooth=5e-4)
    assert raw["peak_ratio"] > 0.6 + 0.05  # the noise's excursion
    # the window's mean of the true curve at its apex is 0.6 − 0.0094 (the slopes average down)
    assert smooth["peak_ratio"] == pytest.approx(0.59, abs=0.03 if rows == 80 else 0.01)
    assert smooth["u_peak"] == pytest.approx(0.002, abs=3e-4)
    assert smooth["peak_ratio_applied"] == pytest.approx(smooth["peak_ratio"], abs=1e-12)
