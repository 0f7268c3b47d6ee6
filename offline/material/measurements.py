"""Measured uniaxial force–strain data: loading, unit sanity checks and validation with row-level errors.

Accepted files:

- ``strain,force_N`` CSV (our own format, e.g. written by ``likeness offline uniaxial``); nominal strain as a
  fraction, force in newtons. Extra columns are ignored; lines starting with ``#`` are comments.
- ``displacement_m,force_N`` CSV: grip displacement in metres, converted to nominal strain with the gauge length
  of the specimen given on the command line.
- The tensile-test exports of the Soft Robotics Materials Database (``;``-separated ``PARAMETER;INFO`` header
  block, then ``Time (s);True Strain;True Stress (MPa);Engineering Strain;Engineering Stress (MPa)``): the
  engineering strain and stress are used, the stress turned into force with the cross-section from the header,
  and the specimen (a strip) is taken from the header.

Every refusal names the file, the line and the column: empty files, missing columns, non-numbers/NaN/inf,
strain that is not monotonic, strain that looks like percent, forces whose magnitude implies an implausible
stiffness (kN or mN given as N).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from models.errors import SpecError
from offline.material.specimen import PointPlan, Specimen, SpecimenPlan

MAX_STRAIN_FRACTION = 10.0
"""Largest nominal strain accepted in our CSV formats (1000 %); larger values are taken for percent."""

SECANT_MODULUS_RANGE = (100.0, 1.0e9)
"""Plausible secant modulus (Pa) implied by force / (area · strain); outside it the force unit is wrong."""


class MeasurementError(SpecError):
    """A measurement file that cannot be used; ``line`` (1-based, or None) and ``column`` name the culprit."""

    def __init__(self, source: str, message: str, *, line: int | None = None, column: str | None = None,
                 value: object = None) -> None:
        where = []
        if line is not None:
            where.append(f"line {line}")
        if column is not None:
            where.append(f"column {column!r}")
        key = ", ".join(where) if where else "file"
        if value is None:
            super().__init__(source, key, message)
        else:
            super().__init__(source, key, message, value)
        self.line = line
        self.column = column


@dataclass(frozen=True)
class Measurement:
    """Measured samples: nominal ``strain`` (fraction) and axial ``force`` (N), with provenance.

    ``lines`` holds the 1-based file line of each sample; ``specimen`` is set when the file itself defines the
    specimen (real tensile exports), else None (the caller's specimen plan applies).
    """

    strain: np.ndarray
    force: np.ndarray
    lines: np.ndarray
    source: str
    file_format: str
    specimen: Specimen | None = None
    info: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.strain.shape[0])

    def select(self, lo: float, hi: float) -> Measurement:
        """The samples with lo ≤ strain ≤ hi (a new Measurement)."""
        keep = (self.strain >= lo) & (self.strain <= hi)
        return Measurement(self.strain[keep], self.force[keep], self.lines[keep], self.source, self.file_format,
                           self.specimen, dict(self.info))


def _number(text: str, source: str, line: int, column: str) -> float:
    try:
        value = float(text.strip())
    except ValueError:
        raise MeasurementError(source, "not a number", line=line, column=column, value=text) from None
    if not math.isfinite(value):
        raise MeasurementError(source, "value must be finite (NaN/inf refused)", line=line, column=column,
                               value=text)
    return value


def _check_monotonic(strain: np.ndarray, lines: np.ndarray, source: str, column: str) -> None:
    if strain.size < 2:
        return
    direction = 1.0 if strain[-1] >= strain[0] else -1.0
    steps = np.diff(strain) * direction
    bad = np.flatnonzero(steps <= 0.0)
    if bad.size:
        k = int(bad[0]) + 1
        raise MeasurementError(
            source,
            f"{column} must be strictly monotonic (one loading branch); previous value {float(strain[k - 1])!r} "
            f"on line {int(lines[k - 1])}",
            line=int(lines[k]), column=column, value=float(strain[k]))


def _check_units(strain: np.ndarray, force: np.ndarray, lines: np.ndarray, area: np.ndarray, source: str,
                 strain_column: str, check_percent: bool) -> None:
    if check_percent:
        k = int(np.argmax(np.abs(strain)))
        if strain[k] > MAX_STRAIN_FRACTION:
            raise MeasurementError(
                source, f"strain above {MAX_STRAIN_FRACTION:g} ({MAX_STRAIN_FRACTION * 100:g} %) looks like percent;"
                " give nominal strain as a fraction (0.5 for 50 %)", line=int(lines[k]), column=strain_column,
                value=float(strain[k]))
    k = int(np.argmin(strain))
    if strain[k] <= -1.0:
        raise MeasurementError(
            source, "nominal strain at or below -1 is impossible (zero length); percent given as a fraction?",
            line=int(lines[k]), column=strain_column, value=float(strain[k]))
    strained = np.abs(strain) >= 0.01
    opposite = strained & (np.sign(force) == -np.sign(strain))
    if strained.any() and opposite.sum() > 0.5 * strained.sum():
        k = int(np.flatnonzero(opposite)[0])
        raise MeasurementError(
            source, f"force has the opposite sign of the strain in {int(opposite.sum())} of {int(strained.sum())} "
            "strained rows: tension must be positive, compression negative", line=int(lines[k]), column="force_N",
            value=float(force[k]))
    if strained.sum() >= 1:
        secant = np.abs(force[strained]) / (area[strained] * np.abs(strain[strained]))
        modulus = float(np.median(secant))
        idx = np.flatnonzero(strained)
        k = int(idx[np.argmax(np.abs(force[strained]))])
        lo, hi = SECANT_MODULUS_RANGE
        if modulus < lo:
            raise MeasurementError(
                source, f"forces imply a secant modulus of only {modulus:.3g} Pa over a {area[k] * 1e6:.4g} mm² "
                "section: force given in kN (or strain in percent)? force_N must be newtons",
                line=int(lines[k]), column="force_N", value=float(force[k]))
        if modulus > hi:
            raise MeasurementError(
                source, f"forces imply a secant modulus of {modulus:.3g} Pa over a {area[k] * 1e6:.4g} mm² "
                "section, far stiffer than any skin silicone: force given in mN (or wrong specimen)? "
                "force_N must be newtons", line=int(lines[k]), column="force_N", value=float(force[k]))


def _read_text(path: Path) -> str:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise MeasurementError(str(path), "file not found") from None
    except UnicodeDecodeError as exc:
        raise MeasurementError(str(path), f"not a UTF-8 text file ({exc.reason})") from None
    if not text.strip():
        raise MeasurementError(str(path), "file is empty: expected a header line and data rows")
    return text


def _is_tensile_export(text: str) -> bool:
    for raw in text.splitlines():
        if raw.strip():
            return raw.split(";")[0].strip().upper() == "PARAMETER" or raw.startswith("Time (s);")
    return False


def _load_tensile_export(text: str, source: str) -> Measurement:
    info: dict[str, str] = {}
    header_line = None
    lines_list = text.splitlines()
    for n, raw in enumerate(lines_list, start=1):
        cells = [c.strip() for c in raw.split(";")]
        if cells[0] == "Time (s)":
            header_line = n
            header = cells
            break
        if cells[0] and cells[0].upper() != "PARAMETER" and len(cells) > 1:
            info[cells[0]] = cells[1]
    if header_line is None:
        raise MeasurementError(source, "no data header row starting with 'Time (s)' after the PARAMETER block")
    need = ("Engineering Strain", "Engineering Stress (MPa)")
    for col in need:
        if col not in header:
            raise MeasurementError(source, f"missing column {col!r}; found {', '.join(c for c in header if c)}",
                                   line=header_line)
    i_eps, i_sig = header.index(need[0]), header.index(need[1])

    def dim_mm(key: str) -> float:
        if key not in info:
            raise MeasurementError(source, f"header block lacks {key!r} (needed for the specimen)")
        value = _number(info[key], source, _line_of(lines_list, key), key)
        if value <= 0:
            raise MeasurementError(source, "must be positive", line=_line_of(lines_list, key), column=key,
                                   value=value)
        return value * 1e-3

    length = dim_mm("Specimen Length (mm)")
    width = dim_mm("Specimen Width (mm)")
    thickness = dim_mm("Specimen Thickness (mm)")
    area = width * thickness
    key = "Specimen Cross-section (cm^2)"
    if key in info:
        area = _number(info[key], source, _line_of(lines_list, key), key) * 1e-4
        if area <= 0:
            raise MeasurementError(source, "must be positive", line=_line_of(lines_list, key), column=key)
    specimen = Specimen("strip", length, width, thickness, area_override=area)
    strain, stress, rows = [], [], []
    for n in range(header_line + 1, len(lines_list) + 1):
        raw = lines_list[n - 1]
        if not raw.strip() or not raw.replace(";", "").strip():
            continue
        cells = raw.split(";")
        if len(cells) <= max(i_eps, i_sig):
            raise MeasurementError(source, f"row has {len(cells)} fields, expected {len(header)}", line=n)
        strain.append(_number(cells[i_eps], source, n, need[0]))
        stress.append(_number(cells[i_sig], source, n, need[1]))
        rows.append(n)
    if not rows:
        raise MeasurementError(source, "no data rows after the header", line=header_line)
    eps = np.array(strain)
    lines = np.array(rows, dtype=np.int64)
    force = np.array(stress) * 1e6 * area
    _check_monotonic(eps, lines, source, need[0])
    _check_units(eps, force, lines, np.full(eps.shape, area), source, need[0], check_percent=False)
    return Measurement(eps, force, lines, source, "tensile-export", specimen, info)


def _line_of(lines: list[str], key: str) -> int:
    for n, raw in enumerate(lines, start=1):
        if raw.split(";")[0].strip() == key:
            return n
    return 0


def _load_csv(text: str, source: str, plan: SpecimenPlan) -> Measurement:
    rows = [(n, raw) for n, raw in enumerate(text.splitlines(), start=1)
            if raw.strip() and not raw.lstrip().startswith("#")]
    if not rows:
        raise MeasurementError(source, "file has only comments: expected a header line and data rows")
    header_line, header_raw = rows[0]
    header = [c.strip() for c in next(csv.reader(io.StringIO(header_raw)))]
    if "force_N" not in header:
        raise MeasurementError(source, "missing column 'force_N' (expected header 'strain,force_N' or "
                               f"'displacement_m,force_N'); found {', '.join(header)}", line=header_line)
    if "strain" in header:
        x_col = "strain"
    elif "displacement_m" in header:
        x_col = "displacement_m"
    else:
        raise MeasurementError(source, "missing column 'strain' or 'displacement_m' (expected header "
                               f"'strain,force_N' or 'displacement_m,force_N'); found {', '.join(header)}",
                               line=header_line)
    ix, iforce = header.index(x_col), header.index("force_N")
    xs, fs, ns = [], [], []
    for n, raw in rows[1:]:
        cells = next(csv.reader(io.StringIO(raw)))
        if len(cells) != len(header):
            raise MeasurementError(source, f"row has {len(cells)} fields, header has {len(header)}", line=n)
        xs.append(_number(cells[ix], source, n, x_col))
        fs.append(_number(cells[iforce], source, n, "force_N"))
        ns.append(n)
    if not ns:
        raise MeasurementError(source, "no data rows after the header", line=header_line)
    x = np.array(xs)
    lines = np.array(ns, dtype=np.int64)
    force = np.array(fs)
    _check_monotonic(x, lines, source, x_col)
    if x_col == "displacement_m":
        gauge = plan.gauge_per_point(x)
        k = int(np.argmax(np.abs(x)))
        if abs(x[k]) > MAX_STRAIN_FRACTION * gauge[k]:
            raise MeasurementError(source, f"displacement exceeds {MAX_STRAIN_FRACTION:g}× the "
                                   f"{gauge[k] * 1e3:g} mm gauge length: given in mm instead of metres?",
                                   line=int(lines[k]), column=x_col, value=float(x[k]))
        strain = x / gauge
    else:
        strain = x
    _check_units(strain, force, lines, plan.area_per_point(strain), source, x_col, check_percent=True)
    return Measurement(strain, force, lines, source, x_col + ",force_N")


def load_measurements(path: str | Path, plan: SpecimenPlan) -> Measurement:
    """Load and validate a measurement file; ``plan`` supplies specimens for the CSV formats.

    Raises :class:`MeasurementError` (a ValueError) naming the file, line and column of the first problem.
    """
    p = Path(path)
    text = _read_text(p)
    if _is_tensile_export(text):
        return _load_tensile_export(text, str(p))
    return _load_csv(text, str(p), plan)


def combine_measurements(measurements: Sequence[Measurement], plan: SpecimenPlan) -> tuple[Measurement, PointPlan]:
    """Join several files for one fit: every sample keeps its own specimen (its file's, else ``plan``'s by sign).

    The fit then scales residuals per specimen, so a compression cylinder's large forces do not drown a strip's.
    """
    if not measurements:
        raise ValueError("no measurements to combine")
    specimens: list[Specimen] = []
    labels: list[str] = []
    index_parts = []
    for meas in measurements:
        if meas.specimen is not None:
            groups = [(meas.specimen, np.ones(len(meas), dtype=bool), meas.source)]
        else:
            neg = meas.strain < 0
            groups = [(plan.compression, neg, f"{meas.source} (compression)"),
                      (plan.tension, ~neg, f"{meas.source} (tension)")]
        idx = np.full(len(meas), -1, dtype=np.int64)
        for spec, mask, label in groups:
            if not mask.any():
                continue
            specimens.append(spec)
            labels.append(label)
            idx[mask] = len(specimens) - 1
        index_parts.append(idx)
    joined = Measurement(
        np.concatenate([m.strain for m in measurements]), np.concatenate([m.force for m in measurements]),
        np.concatenate([m.lines for m in measurements]), " + ".join(m.source for m in measurements), "joint",
        None, {"files": ", ".join(m.source for m in measurements)})
    return joined, PointPlan(tuple(specimens), np.concatenate(index_parts), tuple(labels))
