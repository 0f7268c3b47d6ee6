"""Skin thickness designed on a redesigned head (``likeness offline clone --design-mechanism --design-thickness``).

The layout design (:mod:`offline.design.mechanism_design_job`) moves the mechanism with the skin as it is; this stage
then designs the skin's thickness, with actuation, on the redesigned head: the face cloning of
:mod:`offline.design.clone_job` runs on ``DIR/head/head.toml`` (its new mechanism's link map and attachment sets)
into ``DIR/thickness/``, and the optimized skin replaces ``DIR/head/skin/`` (outer surface and attachments are the
design's fixed side, so the head's link map and face units stay valid). The two designs run one after the other
(block coordinates: layout with actuation, then thickness with actuation on the new layout). The mold of the head's
new skin goes to ``DIR/mold/``, and ``DIR/report.json`` gains a ``thickness`` section.

Resuming: the clone keeps its own checkpoint in ``DIR/thickness/``; the layout job writes ``DIR/head/`` again on
every run (its own skin included), so the optimized skin is installed again each time.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from models.atomic import atomic_path

from .clone import CloneSettings

Progress = Callable[[str], None]

#: Files of the clone's optimized skin folder that replace the head folder's.
SKIN_FILES = ("skin.vtu", "face_units.npz", "mesh_report.json", "README.md")


def design_thickness_on_head(out: str | Path, targets: Mapping[str, Any], settings: CloneSettings, *,
                             targets_file: str | None, backend: str = "auto", resume: bool = True,
                             progress: Progress = print) -> dict[str, Any]:
    """Design thickness and actuation on the head folder ``out/head`` (written by the layout design) for the same
    ``targets``, install the optimized skin there and add the ``thickness`` section to ``out/report.json``; returns
    that section."""
    from models.errors import SpecError

    from .clone_job import load_clone_problem, run_clone

    out = Path(out)
    head_cfg = out / "head" / "head.toml"
    if not head_cfg.is_file():
        raise SpecError(str(head_cfg), "head folder", "missing: the layout design writes it before thickness")
    work = out / "thickness"
    mesh = None
    if settings.layers:
        from .layered import layered_skin_folder

        mesh = str(work / "design_mesh")
        layered_skin_folder(out / "head" / "skin", mesh, layers=settings.layers)
    face, _ = load_clone_problem(str(head_cfg), mesh, targets_file, backend=backend,
                                 element_order=settings.element_order)
    progress(f"[thickness] on the redesigned head ({head_cfg}): {len(targets)} targets, "
             f"{settings.n_samples} thickness samples, up to {settings.max_outer} outer iterations")
    clone = run_clone(face, targets, work, settings, config=head_cfg, targets_file=targets_file, resume=resume,
                      progress=progress)
    install_skin(work / "skin", out / "head" / "skin")
    section = thickness_section(clone)
    _add_to_report(out / "report.json", section)
    progress(f"[thickness] optimized skin installed in {out / 'head' / 'skin'}")
    return section


def install_skin(src: Path, dst: Path) -> None:
    """Replace the head folder's skin files by the optimized skin's (each file written atomically)."""
    dst.mkdir(parents=True, exist_ok=True)
    for name in SKIN_FILES:
        if (src / name).is_file():
            with atomic_path(dst / name, suffix=Path(name).suffix) as tmp:
                shutil.copyfile(src / name, tmp)


def thickness_section(clone: Mapping[str, Any]) -> dict[str, Any]:
    """The layout report's ``thickness`` section: the clone's figures on the redesigned head."""
    sm = clone["summary"]
    keep = ("surface_mean_m", "surface_max_m")
    return {
        "report": "thickness/report.json",
        "before": {k: sm["before"][k] for k in keep},  # uniform skin, actuation optimized on the new layout
        "after": {k: sm["after"][k] for k in keep},  # thickness and actuation optimized
        "strain_after": sm["strain_after"],
        "thickness_change": sm["thickness_change"],
        "regions": sm["regions"],
        "per_target": [{"name": r["name"], **{stage: {k: r[stage][k] for k in (*keep, "strain")}
                                              for stage in ("before", "after")}} for r in clone["targets"]],
        "outer_iterations": clone["outer_iterations"],
        "seconds": clone["seconds"],
        "skin": "head/skin/ (the optimized skin, installed)",
        "mold": "mold/",
    }


def _add_to_report(path: Path, section: dict[str, Any]) -> None:
    """The section into ``report.json``, and its lines at the end of ``report.md`` (both written again by the layout
    job on every run, so added once)."""
    report = json.loads(path.read_text())
    report["thickness"] = section
    with atomic_path(path, suffix=".json") as tmp:
        Path(tmp).write_text(json.dumps(report, indent=1, default=float))
    md = path.with_name("report.md")
    if md.is_file():
        mm = 1e3
        dh = section["thickness_change"]
        lines = ["", "## Thickness on the redesigned head", "",
                 "The skin's thickness designed with actuation on the new layout (`thickness/report.json`); the "
                 "optimized skin is the head folder's (`head/skin/`), its mold in `mold/`.", "",
                 "| target | uniform skin: mean / max (mm) | optimized skin: mean / max (mm) |", "|---|---|---|"]
        for r in section["per_target"]:
            b, a = r["before"], r["after"]
            lines.append(f"| {r['name']} | {b['surface_mean_m'] * mm:.2f} / {b['surface_max_m'] * mm:.2f} | "
                         f"{a['surface_mean_m'] * mm:.2f} / {a['surface_max_m'] * mm:.2f} |")
        b, a = section["before"], section["after"]
        lines += ["", f"All targets: mean {b['surface_mean_m'] * mm:.2f} → {a['surface_mean_m'] * mm:.2f} mm, max "
                      f"{b['surface_max_m'] * mm:.2f} → {a['surface_max_m'] * mm:.2f} mm; thickness change |Δh| "
                      f"mean {dh['abs_mean_mm']:.2f} mm, max {dh['abs_max_mm']:.2f} mm "
                      f"({section['outer_iterations']} outer iterations, {section['seconds']:.0f} s).", ""]
        with atomic_path(md, suffix=".md") as tmp:
            Path(tmp).write_text(md.read_text() + "\n".join(lines))
