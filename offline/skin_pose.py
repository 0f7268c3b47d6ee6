"""One quasi-static pose of the skin with the links moved rigidly (what ``likeness offline simulate`` runs).

The skull node set is fixed; every link node set of the mesh follows a rigid 4x4 transform (identity for links not
given). Transforms come from a JSON file, from compact motions ``NAME=tx,ty,tz,rx,ry,rz`` (mm and degrees, rotation
R = Rz Ry Rx about the node set's rest centroid, then translation), or from actuator values through a fitted link
map. Errors in these inputs are :class:`models.errors.UsageError` naming the option they came from.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from models.errors import UsageError
from models.headspec import load_head
from models.material import SkinMaterial

if TYPE_CHECKING:
    from offline.fem import TetMesh

#: The bundled sample head's config.
SAMPLE_HEAD = Path(__file__).resolve().parents[1] / "heads" / "sample" / "head.toml"
BACKENDS = ("auto", "cholmod", "pardiso", "superlu")


def parse_link_spec(text: str) -> tuple[str, list[float]]:
    """Parse ``NAME=tx,ty,tz,rx,ry,rz`` (mm, deg) into (name, six floats); raises ValueError naming the problem."""
    name, sep, values = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise ValueError(f"--link {text!r}: expected NAME=tx,ty,tz,rx,ry,rz")
    try:
        nums = [float(v) for v in values.split(",")]
    except ValueError as exc:
        raise ValueError(f"--link {text!r}: values must be numbers") from exc
    if len(nums) != 6 or not all(math.isfinite(v) for v in nums):
        raise ValueError(f"--link {text!r}: expected 6 finite numbers (tx,ty,tz mm, rx,ry,rz deg), got {len(nums)}")
    return name, nums


def compact_transform(centroid: Sequence[float] | np.ndarray, motion: Sequence[float] | np.ndarray) -> np.ndarray:
    """4x4 transform for a compact motion (tx,ty,tz in mm, rx,ry,rz in deg; R = Rz Ry Rx about ``centroid``)."""
    tx, ty, tz, rx, ry, rz = motion
    ax, ay, az = np.radians([rx, ry, rz])
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    R = Rz @ Ry @ Rx
    c = np.asarray(centroid, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + np.array([tx, ty, tz]) * 1e-3
    return T


def load_links_json(path: str, centroids: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Transforms from a links JSON file; each value a 4x4 matrix or a compact 6-vector (mm, deg)."""
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise UsageError(f"--links {path}: cannot read: {exc}") from exc
    except ValueError as exc:
        raise UsageError(f"--links {path}: invalid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise UsageError(f"--links {path}: expected a JSON object of link name -> transform")
    out = {}
    for name, value in data.items():
        if name not in centroids:
            raise UsageError(f"--links {path}: key {name!r}: not a link node set of the mesh "
                             f"(have {sorted(centroids)})")
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise UsageError(f"--links {path}: key {name!r}: not numeric: {value!r}") from exc
        if arr.shape == (6,):
            arr = compact_transform(centroids[name], arr)
        elif arr.shape != (4, 4):
            raise UsageError(f"--links {path}: key {name!r}: expected a 4x4 matrix or 6 numbers, "
                             f"got shape {arr.shape}")
        if not np.isfinite(arr).all() or not np.allclose(arr[3], [0, 0, 0, 1]):
            raise UsageError(f"--links {path}: key {name!r}: last row must be [0, 0, 0, 1] and values finite")
        R = arr[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise UsageError(f"--links {path}: key {name!r}: the 3x3 part is not a rotation")
        out[name] = arr
    return out


def link_motions(specs: Sequence[str], centroids: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Transforms from compact ``NAME=tx,ty,tz,rx,ry,rz`` motions of the mesh's link node sets."""
    transforms = {}
    for spec in specs:
        try:
            name, motion = parse_link_spec(spec)
        except ValueError as exc:
            raise UsageError(str(exc)) from exc
        if name not in centroids:
            raise UsageError(f"--link {spec!r}: {name!r} is not a link node set of the mesh "
                             f"(have {sorted(centroids)})")
        transforms[name] = compact_transform(centroids[name], motion)
    return transforms


def skin_material(head_path: str | Path | None, model: str | None = None, E: float | None = None,
                  nu: float | None = None) -> SkinMaterial:
    """The material to simulate: the head's ``[skin_material]`` (else E = 78 kPa, nu = 0.47, neo-Hookean), with
    ``model``, ``E`` and ``nu`` (when given) overriding its fields."""
    head_path = head_path or str(SAMPLE_HEAD)
    base = load_head(head_path).skin_material()
    if base is None:
        base = SkinMaterial("neo_hookean", 78_000.0, 0.47, source=f"FEM default ({head_path} has no [skin_material])")
    changes: dict[str, Any] = {k: v for k, v in (("model", model), ("E", E), ("nu", nu)) if v is not None}
    if not changes:
        return base
    if "model" in changes and changes["model"] != base.model:
        changes["shape"] = {}
    try:
        return dataclasses.replace(base, **changes, source=base.source + f"; overridden on the command line: "
                                   f"{', '.join(f'{k}={v}' for k, v in changes.items() if k != 'shape')}")
    except ValueError as exc:
        raise UsageError(f"--material/--E/--nu: {exc}") from exc


def actuator_transforms(head_path: str | Path, linkmap: str | None, actuators: Sequence[str],
                        link_names: set[str]) -> dict[str, np.ndarray]:
    """Link transforms from ``NAME=VALUE`` actuator values (config units of the head: deg or mm) through the link
    map (the head's ``[paths] linkmap`` unless ``linkmap`` is given)."""
    from models.errors import SpecError
    from models.linkmap import LinkMap

    try:
        head = load_head(head_path)
    except (OSError, SpecError) as exc:
        raise UsageError(f"--head {head_path}: {exc}") from exc
    linkmap = linkmap or head.path("linkmap")
    if linkmap is None:
        raise UsageError("--actuators needs --linkmap FILE (the head config names none)")
    values = {}
    for item in actuators:
        name, sep, val = item.partition("=")
        name = name.strip()
        try:
            number = float(val)
        except ValueError:
            number = math.nan
        if not sep or not name or not math.isfinite(number):
            raise UsageError(f"--actuators {item!r}: expected NAME=VALUE with a finite number")
        if name not in head.actuator_names:
            raise UsageError(f"--actuators {item!r}: {name!r} is not an actuator of {head_path} "
                             f"(have {', '.join(head.actuator_names)})")
        spec = head.actuator(name)
        si = spec.from_config_units(number)
        if not spec.min - 1e-12 <= si <= spec.max + 1e-12:
            raise UsageError(f"--actuators {item!r}: outside [{spec.to_config_units(spec.min):g}, "
                             f"{spec.to_config_units(spec.max):g}] {spec.unit}")
        values[name] = si
    try:
        transforms = LinkMap.load(linkmap).transforms(values)
    except (OSError, ValueError, KeyError) as exc:
        raise UsageError(f"--linkmap {linkmap}: {exc}") from exc
    return {k: v for k, v in transforms.items() if k in link_names}


@dataclass(frozen=True)
class PoseSettings:
    """How to pose the skin: the mesh, one source of link motions (``links_json``, ``link_specs`` or
    ``actuators`` with ``linkmap``/``head``), the material overrides and the Newton solver's settings."""

    mesh: str
    out: str
    links_json: str | None = None
    link_specs: tuple[str, ...] = ()
    actuators: tuple[str, ...] = ()
    linkmap: str | None = None
    head: str | None = None
    material: str | None = None
    E: float | None = None
    nu: float | None = None
    backend: str = "auto"
    load_steps: int | str = "auto"
    max_iterations: int = 30
    tol: float = 1e-6


def parse_load_steps(text: str) -> int | str:
    """``"auto"`` or an integer >= 1 (UsageError otherwise)."""
    if text == "auto":
        return text
    try:
        steps = int(text)
    except ValueError as exc:
        raise UsageError(f"--load-steps {text!r}: an integer >= 1 or 'auto'") from exc
    if steps < 1:
        raise UsageError(f"--load-steps {steps}: must be >= 1")
    return steps


def simulate_pose(settings: PoseSettings, say: Callable[[str], None] = print) -> bool:
    """Load the mesh, build the boundary conditions, solve and write the deformed mesh to ``settings.out``
    (deformed points, point data ``displacement`` in m); ``say`` gets the progress lines. Returns whether the solve
    converged (nothing is written when it did not)."""
    from offline.fem import NotConverged, SolverOptions, load_mesh, rigid_transform_dirichlet, solve_static
    from offline.fem.linsolve import available_backends
    from offline.material.models import MaterialParams

    material_spec = skin_material(settings.head, settings.material, settings.E, settings.nu)
    if settings.backend not in BACKENDS:
        raise UsageError(f"--backend {settings.backend}: choose auto, cholmod, pardiso or superlu")
    if settings.backend != "auto" and settings.backend not in available_backends():
        raise UsageError(f"--backend {settings.backend}: not available here (have {available_backends()})")
    load_steps = parse_load_steps(str(settings.load_steps))
    path = Path(settings.mesh)
    vtu = path / "skin.vtu" if path.is_dir() else path
    if not vtu.is_file():
        raise UsageError(f"--mesh {settings.mesh}: no skin.vtu there (build one with `likeness offline mesh`)")
    t0 = time.perf_counter()
    try:
        mesh = load_mesh(vtu)
    except Exception as exc:
        raise UsageError(f"--mesh {vtu}: cannot read: {exc}") from exc
    t_load = time.perf_counter() - t0
    if "skull" not in mesh.node_sets or len(mesh.node_sets["skull"]) == 0:
        raise UsageError(f"--mesh {vtu}: no 'skull' node set to hold the skin")
    links = [k for k in mesh.node_sets if k != "skull"]
    centroids = {k: mesh.nodes[mesh.node_sets[k]].mean(axis=0) for k in links if len(mesh.node_sets[k])}
    if settings.links_json:
        transforms = load_links_json(settings.links_json, centroids)
    elif settings.link_specs:
        transforms = link_motions(settings.link_specs, centroids)
    else:
        transforms = actuator_transforms(settings.head or str(SAMPLE_HEAD), settings.linkmap, settings.actuators,
                                         set(centroids))
    full = {k: transforms.get(k, np.eye(4)) for k in links if k in centroids}
    dirichlet = rigid_transform_dirichlet(mesh, full, fixed_sets=["skull"])
    material = MaterialParams.from_skin_material(material_spec).to_fem_material(material_spec.density)
    say(f"material: {material_spec.model}, E = {material_spec.E:.6g} Pa, nu = {material_spec.nu:g} "
        f"({material_spec.source})")
    opts = SolverOptions(backend=settings.backend, tol_force=settings.tol, max_iterations=settings.max_iterations,
                         load_steps=load_steps, failure_dir=Path(settings.out).resolve().parent)
    moved = {k: float(np.abs(T - np.eye(4)).max()) > 0 for k, T in full.items()}
    say(f"mesh {vtu}: {mesh.n_nodes} nodes, {mesh.n_tets} tets; {len(dirichlet.nodes)} constrained nodes; "
        f"moving {[k for k, m in moved.items() if m] or 'nothing'}")
    try:
        result = solve_static(mesh, material, dirichlet, options=opts)
        ok = True
    except NotConverged as exc:
        result = exc.result
        ok = False
        say(f"NOT CONVERGED: {exc}")
        say("  hint: more load steps (--load-steps N) or another backend (--backend superlu) may get through")
    for row in result.log:
        say("  step {step} it {iteration}: energy {energy:.6e} J, residual {residual:.3e} N, alpha {alpha:.3g}"
            "{proj}".format(proj=", projected" if row.get("projected") else "", **row))
    u = result.x - mesh.nodes
    tim = ", ".join(f"{k} {v:.2f} s" for k, v in result.timings.items())
    say(f"{'converged' if ok else 'stopped'} in {result.iterations} iterations, {result.load_steps} load steps; "
        f"load {t_load:.2f} s, {tim}")
    say(f"max displacement {np.linalg.norm(u, axis=1).max() * 1e3:.3f} mm; "
        f"total reaction {np.round(result.reaction_total(), 4).tolist()} N")
    if not ok:
        say(f"not writing {settings.out}: the solve did not converge")
        return False
    _write_deformed(Path(settings.out), mesh, result.x, u)
    say(f"wrote {settings.out}")
    return True


def _write_deformed(out: Path, mesh: TetMesh, x: np.ndarray, u: np.ndarray) -> None:
    """Write deformed points with displacement and node-set flags as point data, atomically."""
    from offline.fem import TetMesh, save_mesh

    save_mesh(out, TetMesh(x, mesh.tets, mesh.node_sets), point_data={"displacement": u})
