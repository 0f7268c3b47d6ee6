"""Measurement files: the three accepted formats load; bad files are refused naming the line and column."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from offline.material.measurements import MeasurementError, load_measurements
from offline.material.specimen import make_plan

DATA = Path(__file__).resolve().parents[3] / "data" / "tensile"
PLAN = make_plan("auto")


def _write(tmp_path: Path, text: str, name: str = "m.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_strain_force_csv(tmp_path: Path) -> None:
    path = _write(tmp_path, "# comment\nstrain,force_N\n-0.1,-15.0\n0.0,0.0\n0.1,0.07\n0.2,0.13\n")
    m = load_measurements(path, PLAN)
    np.testing.assert_allclose(m.strain, [-0.1, 0.0, 0.1, 0.2])
    np.testing.assert_allclose(m.force, [-15.0, 0.0, 0.07, 0.13])
    assert list(m.lines) == [3, 4, 5, 6]
    assert m.specimen is None


def test_displacement_csv_uses_gauge_length(tmp_path: Path) -> None:
    # strip gauge 55 mm for tension, cylinder gauge 12 mm for compression (auto plan)
    path = _write(tmp_path, "displacement_m,force_N\n-0.0012,-15.0\n0.0055,0.07\n0.011,0.13\n")
    m = load_measurements(path, PLAN)
    np.testing.assert_allclose(m.strain, [-0.1, 0.1, 0.2])


@pytest.mark.parametrize("name", sorted(p.name for p in DATA.glob("*.csv")))
def test_real_tensile_exports_load(name: str) -> None:
    m = load_measurements(DATA / name, PLAN)
    assert m.file_format == "tensile-export"
    assert m.specimen is not None and m.specimen.area == pytest.approx(0.18e-4)
    assert m.specimen.length == pytest.approx(0.033)
    assert len(m) > 300 and np.all(np.diff(m.strain) > 0)
    # force = engineering stress (MPa) x 0.18 cm²; check one row against the file text
    row = (DATA / name).read_text().splitlines()[int(m.lines[5]) - 1].split(";")
    assert m.force[5] == pytest.approx(float(row[4]) * 1e6 * 0.18e-4)
    assert m.strain[5] == pytest.approx(float(row[3]))


BAD = {
    "empty": ("", "file", "empty"),
    "header only": ("strain,force_N\n", "line 1", "no data rows"),
    "missing column": ("strain,load\n0.1,0.07\n", "line 1", "force_N"),
    "missing strain": ("time,force_N\n0.1,0.07\n", "line 1", "strain"),
    "nan": ("strain,force_N\n0.0,0.0\n0.1,nan\n0.2,0.13\n", "line 3, column 'force_N'", "NaN"),
    "text": ("strain,force_N\n0.0,0.0\n0.1,abc\n", "line 3, column 'force_N'", "not a number"),
    "short row": ("strain,force_N\n0.0,0.0\n0.1\n", "line 3", "fields"),
    "non-monotonic": ("strain,force_N\n0.0,0.0\n0.2,0.13\n0.1,0.07\n0.3,0.18\n", "line 4, column 'strain'",
                      "monotonic"),
    "percent": ("strain,force_N\n0,0\n10,0.07\n20,0.13\n50,0.27\n", "line 5, column 'strain'", "percent"),
    "kN": ("strain,force_N\n0,0\n0.1,0.00007\n0.2,0.00013\n0.5,0.00027\n", "line 5, column 'force_N'", "kN"),
    "mN": ("strain,force_N\n0,0\n0.1,70000\n0.2,130000\n0.5,270000\n", "line 5, column 'force_N'", "mN"),
    "impossible compression": ("strain,force_N\n-1.5,-20\n-0.1,-15\n0,0\n", "line 2, column 'strain'", "-1"),
    "sign flipped": ("strain,force_N\n-0.1,15\n0,0\n0.1,-0.07\n0.2,-0.13\n", "line 2, column 'force_N'",
                     "opposite sign"),
    "displacement in mm": ("displacement_m,force_N\n0,0\n5.5,0.07\n11,0.13\n", "line 4, column 'displacement_m'",
                           "mm"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_files_refused_naming_row_and_column(tmp_path: Path, case: str) -> None:
    text, where, what = BAD[case]
    path = _write(tmp_path, text)
    with pytest.raises(MeasurementError) as info:
        load_measurements(path, PLAN)
    message = str(info.value)
    assert str(path) in message
    assert where in message, message
    assert what in message, message


def test_bad_tensile_export_row(tmp_path: Path) -> None:
    lines = (DATA / "Ecoflex_00-30.csv").read_text().splitlines()
    header = next(i for i, t in enumerate(lines) if t.startswith("Time (s)"))
    cells = lines[header + 3].split(";")
    cells[3] = "NaN"
    lines[header + 3] = ";".join(cells)
    path = _write(tmp_path, "\n".join(lines) + "\n", "export.csv")
    with pytest.raises(MeasurementError, match=f"line {header + 4}, column 'Engineering Strain'"):
        load_measurements(path, PLAN)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MeasurementError, match="not found"):
        load_measurements(tmp_path / "nope.csv", PLAN)
