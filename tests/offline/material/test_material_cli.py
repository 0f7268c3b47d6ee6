"""``likeness offline uniaxial`` and ``likeness offline fit-material`` end to end (in-process CLI)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from likeness.cli import main
from offline.material.closed_form import uniaxial_nominal_stress
from offline.material.models import MaterialParams

DATA = Path(__file__).resolve().parents[3] / "data" / "tensile"


def _read_curve(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    return lines, np.array([[float(v) for v in row.split(",")] for row in lines[1:]])


def test_uniaxial_writes_exact_header_and_fem_forces(tmp_path: Path) -> None:
    out = tmp_path / "curve.csv"
    rc = main(["offline", "uniaxial", "--material", "neo_hookean", "--E", "78000", "--nu", "0.47",
               "--strain=-0.2:0.5:8", "--grips", "frictionless", "--out", str(out)])
    assert rc == 0
    lines, data = _read_curve(out)
    assert lines[0] == "strain,force_N"
    np.testing.assert_allclose(data[:, 0], np.linspace(-0.2, 0.5, 8), atol=1e-12)
    eps = data[:, 0]
    area = np.where(eps < 0, np.pi * 0.025**2, 0.005 * 0.002)  # auto: cylinder compression, strip tension
    expected = uniaxial_nominal_stress(MaterialParams("neo_hookean", 78_000.0, 0.47), 1.0 + eps)[0] * area
    moved = np.abs(eps) > 1e-12
    np.testing.assert_allclose(data[moved, 1], expected[moved], rtol=0.005)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic write leaves no temp file


def test_uniaxial_clamped_strip_is_stiffer(tmp_path: Path) -> None:
    free, clamped = tmp_path / "free.csv", tmp_path / "clamped.csv"
    common = ["offline", "uniaxial", "--strain", "0.25,0.5", "--specimen", "strip"]
    assert main([*common, "--out", str(free)]) == 0
    assert main([*common, "--grips", "clamped", "--out", str(clamped)]) == 0
    f = _read_curve(free)[1][:, 1]
    c = _read_curve(clamped)[1][:, 1]
    assert np.all(c > f * 1.005)


def test_uniaxial_user_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x.csv"
    assert main(["offline", "uniaxial", "--solver", "closed-form", "--grips", "clamped", "--out", str(out)]) == 2
    assert "frictionless" in capsys.readouterr().err
    assert main(["offline", "uniaxial", "--strain", "0:50:3", "--out", str(out)]) == 2
    assert "percent" in capsys.readouterr().err
    assert main(["offline", "uniaxial", "--c01", "100", "--out", str(out)]) == 2
    assert "--c01" in capsys.readouterr().err
    assert not out.exists()


def test_fit_material_round_trip_from_uniaxial_curve(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    curve, fit = tmp_path / "curve.csv", tmp_path / "fit.json"
    assert main(["offline", "uniaxial", "--E", "90000", "--nu", "0.44", "--strain=-0.2:0.5:8",
                 "--out", str(curve)]) == 0
    assert main(["offline", "fit-material", str(curve), "--method", "lsq", "--out", str(fit)]) == 0
    result = json.loads(fit.read_text())
    assert abs(result["E_Pa"] / 90_000.0 - 1.0) < 1e-4
    assert abs(result["nu"] - 0.44) < 1e-3
    assert result["relative_rms_force_error"] < 1e-5
    assert "closed form" in result["forward_model"]
    assert "chosen lsq" in capsys.readouterr().out


def test_fit_material_real_silicone_with_plot(tmp_path: Path) -> None:
    fit, png = tmp_path / "fit.json", tmp_path / "fit.png"
    rc = main(["offline", "fit-material", str(DATA / "Dragon_Skin_10_MEDIUM.csv"), "--method", "both",
               "--strain-range", "0:0.5", "--plot", str(png), "--out", str(fit)])
    assert rc == 0
    result = json.loads(fit.read_text())
    # README orientation: E ≈ 139 kPa (incompressible neo-Hookean least squares over 0-50 %)
    assert 110_000.0 < result["E_Pa"] < 170_000.0
    assert result["file_format"] == "tensile-export"
    assert result["samples_used"] < result["samples_in_file"]
    assert {r["method"] for r in result["runs"]} == {"anneal", "lsq"}
    assert result["rms_force_error_N"] > 0.0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_fit_material_bad_file_names_row(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("strain,force_N\n0.0,0.0\n0.1,0.07\n0.2,nan\n0.3,0.18\n")
    assert main(["offline", "fit-material", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "line 4" in err and "force_N" in err


def test_joint_fit_file_feeds_the_head_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Strip + cylinder files fitted jointly; the result file is the head's [skin_material] (one vocabulary)."""
    from models.errors import SpecError
    from models.headspec import load_head
    from offline.dataset.fem_problem import FemSpec, material_fields

    tension, compression, fit = tmp_path / "t.csv", tmp_path / "c.csv", tmp_path / "fit.json"
    assert main(["offline", "uniaxial", "--material", "mooney_rivlin", "--E", "70000", "--nu", "0.46", "--c01",
                 "5000", "--strain=0.05:0.5:8", "--specimen", "strip", "--out", str(tension)]) == 0
    assert main(["offline", "uniaxial", "--material", "mooney_rivlin", "--E", "70000", "--nu", "0.46", "--c01",
                 "5000", "--strain=-0.2:-0.02:6", "--specimen", "cylinder", "--out", str(compression)]) == 0
    capsys.readouterr()
    assert main(["offline", "fit-material", str(tension), str(compression), "--model", "mooney_rivlin",
                 "--method", "lsq", "--out", str(fit)]) == 0
    out = capsys.readouterr().out
    assert "joint fit of 2 files" in out and "nu is identified by these tension and compression data" in out
    doc = json.loads(fit.read_text())
    assert doc["format"] == "likeness-material-fit" and doc["model"] == "mooney_rivlin"
    assert doc["measurements_files"] == [str(tension), str(compression)]
    assert doc["identifiability"]["parameters"]["nu"]["identified"]
    assert abs(doc["nu"] - 0.46) < 1e-3 and abs(doc["params"]["c01"] / 5000.0 - 1) < 1e-2
    head_src = (Path(__file__).resolve().parents[3] / "heads" / "sample" / "head.toml").read_text()
    head_src = head_src.replace('predictor = "predictor.onnx"\n', "").replace('linkmap = "linkmap.json"\n', "")
    import re

    head_src = re.sub(r"\[skin_material\][^\[]*", "", head_src)
    (tmp_path / "head.toml").write_text(head_src + '\n[skin_material]\nfit = "fit.json"\nnote = "test"\n')
    mat = load_head(tmp_path / "head.toml").skin_material()
    assert mat.model == "mooney_rivlin" and mat.shape["c01"] > 0
    assert abs(mat.E - doc["E_Pa"]) <= 1e-9 * doc["E_Pa"]
    assert "fit.json" in mat.source and str(tension) in mat.source
    spec = FemSpec(config="x", mesh="y", linkmap="z", **material_fields(mat))
    assert spec.describe()["material"]["model"] == "mooney_rivlin" and "fit.json" in spec.material_source
    (tmp_path / "head.toml").write_text(head_src + '\n[skin_material]\nfit = "fit.json"\nE = 1.0\n')
    with pytest.raises(SpecError, match=r"skin_material\.E: give either fit"):
        load_head(tmp_path / "head.toml")
