"""Fabrication export of a skin: STL files in millimetres for casting it in a two-part mold.

Everything is expressed in a casting frame (the head frame rotated, then shifted to centre the skin over the
plate): z is the skin's area-weighted mean outward normal (the direction the face looks), x the head's left-right
axis made orthogonal to it, the base plate's top at z = 0. Files:

- ``skin.stl``: the skin solid (its boundary: outer surface, inner surface and the rim walls), watertight.
- ``skin_outer_surface.stl`` / ``skin_inner_surface.stl``: the two design surfaces alone, for inspection (open
  sheets, consistently oriented, not solids).
- ``mold_core.stl``: the core: everything below the skin (seen along z) and above no part of it, plus pockets the
  shell cannot reach (closed between skin and core, e.g. the slot between overlapping lips), closed against a base
  plate that carries tapered registration keys at its corners.
- ``mold_shell_left.stl`` / ``mold_shell_right.stl``: the outer shell — the mold box less the skin, the core and
  the keys — split in two along the parting plane x = (the skin's centre). The halves part sideways, which frees
  regions that overhang along z (under the nose, the lips) without undercuts on the parting direction. Two tapered
  pins on the left half's parting face, in the side walls half-way up, enter sockets of the right half (with
  ``pin_clearance_mm`` of clearance) so the halves close in register.

By construction the shell's cavity is the skin plus the core above the plate plus the keys, so
vol(box) − vol(shell halves) − (vol(core) − vol(plate)) = vol(skin): the checker verifies it on the files. The
regions "below" and "above" the skin are sweeps of the skin along ∓z, built as unions of the convex prisms between
each boundary triangle and its projection onto the box's bottom or top (``manifold3d``, exact and manifold
booleans).

Pour hole and vents: with the face up (as cast), air collects under the local high points of the cavity's roof,
the skin's outer surface. The highest of them gets the pour hole (``pour_mm`` across), the next ``vents`` highest,
at least ``vent_spacing_mm`` apart, get vents (``vent_mm`` across); each is a vertical channel from the box's top
down into the skin by ``channel_overlap_mm`` (so it opens into the cavity), cut from the shell. The channels' volume
inside the shell is reported and enters the volume balance: cavity − core − channels − flash = skin. Silicone left
in the channels is a sprue to trim from the cast skin.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from .mesh_check import check_stl, merge_as_stl, self_intersecting_pairs


@dataclass(frozen=True)
class MoldSettings:
    """Mold dimensions (mm)."""

    margin_mm: float = 12.0
    plate_mm: float = 5.0
    below_mm: float = 4.0
    above_mm: float = 8.0
    key_radius_mm: float = 3.5
    key_height_mm: float = 6.0
    key_taper: float = 0.75
    sliver_mm3: float = 1.0
    tolerance_mm: float = 0.01
    notch_mm: float = 0.15
    pour_mm: float = 8.0
    vent_mm: float = 2.0
    vents: int = 4
    vent_spacing_mm: float = 15.0
    channel_overlap_mm: float = 0.5
    island_fraction: float = 0.01  # pieces of a part below this fraction of its volume are not printed
    pin_radius_mm: float = 2.5  # registration pins of the left shell half in sockets of the right half
    pin_length_mm: float = 5.0
    pin_clearance_mm: float = 0.15


#: (vertex-merging tolerance, notch width) in mm a mold is built again with, in turn, when its parts keep STL
#: defects at the settings given.
REPAIR_STEPS_MM = ((0.05, 0.15), (0.01, 0.3), (0.05, 0.3))


def _manifold(vertices: np.ndarray, faces: np.ndarray):
    from manifold3d import Manifold, Mesh64

    m = Manifold(Mesh64(vert_properties=np.ascontiguousarray(vertices, dtype=np.float64),
                        tri_verts=np.ascontiguousarray(faces, dtype=np.uint64)))
    if m.status().name != "NoError":
        raise ValueError(f"the skin surface is not a closed manifold ({m.status().name})")
    return m


def _arrays(m) -> tuple[np.ndarray, np.ndarray]:
    mesh = m.to_mesh64()
    return np.asarray(mesh.vert_properties)[:, :3].astype(np.float64), np.asarray(mesh.tri_verts).astype(np.int64)


def _clean(m, min_volume: float, tolerance: float):
    """Drop the slivers the prism unions leave (components under ``min_volume`` mm³) and collapse edges shorter
    than ``tolerance`` mm, so the part survives STL's single precision."""
    from manifold3d import Manifold, OpType

    parts = [c for c in m.decompose() if c.volume() >= min_volume]
    if not parts:
        raise ValueError("a mold part vanished: every component is below the sliver volume")
    return Manifold.batch_boolean(parts, OpType.Add).simplify(tolerance)


def _shell_pins(left, right, xm: float, y_walls: tuple[float, float], z_mid: float, forbidden, s: MoldSettings):
    """Two tapered pins on the left half's parting face (in the side walls, half-way up) and matching sockets,
    ``pin_clearance_mm`` larger, in the right half; returns (left, right, the clearance gap's volume in mm³)."""
    from manifold3d import Manifold

    r, L, c = s.pin_radius_mm, s.pin_length_mm, s.pin_clearance_mm
    before = left.volume() + right.volume()
    for y in y_walls:
        # along +x from 1 mm inside the left half: a cylinder along z, turned onto x
        pin = Manifold.cylinder(L + 1.0, r, r * 0.8, 48).rotate([0.0, 90.0, 0.0]).translate([xm - 1.0, y, z_mid])
        socket = (Manifold.cylinder(L + 1.0 + c, r + c, r * 0.8 + c, 48).rotate([0.0, 90.0, 0.0])
                  .translate([xm - 1.0, y, z_mid]))
        if not (socket ^ forbidden).is_empty():
            raise ValueError("a shell registration pin meets the cavity: raise margin_mm")
        left = left + pin
        right = right - socket
    return left, right, before - (left.volume() + right.volume())


def _drop_islands(m, fraction: float):
    """The part without the pieces smaller than ``fraction`` of its largest piece (the islands repair notches and
    channels cut off: loose in the mold, they would float in the silicone), and their volume (mm³)."""
    from manifold3d import Manifold, OpType

    pieces = m.decompose()
    if len(pieces) < 2:
        return m, 0.0
    largest = max(c.volume() for c in pieces)
    keep = [c for c in pieces if c.volume() >= fraction * largest]
    dropped = sum(c.volume() for c in pieces) - sum(c.volume() for c in keep)
    return Manifold.batch_boolean(keep, OpType.Add), dropped


def _notch(segments: np.ndarray, radius: float):
    """Union of thin convex sleeves (half-width ``radius`` mm) around segments (K, 2, 3)."""
    from manifold3d import Manifold, OpType

    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64) * radius
    parts = [Manifold.hull_points(np.vstack([a + corners, b + corners])) for a, b in segments]
    return Manifold.batch_boolean(parts, OpType.Add)


def _stl_defects(m) -> np.ndarray:
    """Segments (K, 2, 3) where the part, written as STL, would not be a clean solid: edges that are not shared by
    exactly two triangles after single-precision merging (pinches where the part touches itself along an edge) and
    edges of triangles that cross after rounding (walls of near-zero thickness)."""
    from .mesh_check import bad_edges, merge_as_stl, self_intersecting_pairs

    v, f = merge_as_stl(*_arrays(m))
    segs = [v[bad_edges(f)]] if len(f) else []
    pairs = self_intersecting_pairs(v, f)
    if len(pairs):
        tri = v[f[np.unique(pairs.ravel())]]
        segs.append(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]))
    return np.concatenate(segs) if segs else np.zeros((0, 2, 3))


def _repair(m, settings: MoldSettings, rounds: int = 4):
    """Cut thin notches (flash, filled by the casting) at the part's STL defects until none is left; returns the
    part and the volume removed (mm³)."""
    removed = 0.0
    for _ in range(rounds):
        segs = _stl_defects(m)
        if len(segs) == 0:
            return m, removed
        before = m.volume()
        m = _clean(m - _notch(segs, settings.notch_mm), settings.sliver_mm3, settings.tolerance_mm)
        removed += before - m.volume()
    if len(_stl_defects(m)):
        raise ValueError("a mold part keeps pinched or crossing walls after repair")
    return m, removed


def _write_stl(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    import trimesh

    trimesh.Trimesh(vertices, faces, process=False).export(str(path))


def casting_frame(nodes: np.ndarray, outer_faces: np.ndarray) -> np.ndarray:
    """Rotation R (rows x, y, z of the casting frame) for head-frame points."""
    t = nodes[outer_faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]).sum(axis=0)
    z = n / np.linalg.norm(n)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - z[1] * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _sweep(V: np.ndarray, F: np.ndarray, z_to: float):
    """Union of the prisms between each (non-vertical) triangle and its projection onto z = z_to."""
    from manifold3d import Manifold, OpType

    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(n, axis=1)
    keep = np.abs(n[:, 2]) > 1e-9 * np.maximum(area, 1e-300)
    parts = []
    for t in tri[keep]:
        proj = t.copy()
        proj[:, 2] = z_to
        h = Manifold.hull_points(np.vstack([t, proj]))
        if not h.is_empty():
            parts.append(h)
    return Manifold.batch_boolean(parts, OpType.Add)


def high_points(V: np.ndarray, faces: np.ndarray, radius_mm: float, count: int) -> np.ndarray:
    """Indices of up to ``count`` local maxima in z of the surface ``faces`` (vertices ``V``, mm), highest first:
    vertices at least as high as every surface vertex within ``radius_mm`` of them (in plan), and at least
    ``radius_mm`` apart from a higher one already taken."""
    from scipy.spatial import cKDTree

    idx = np.unique(faces)
    P = V[idx]
    tree = cKDTree(P[:, :2])
    chosen: list[int] = []
    for k in np.argsort(-P[:, 2], kind="stable"):
        if len(chosen) >= count:
            break
        near = tree.query_ball_point(P[k, :2], radius_mm)
        if P[near, 2].max() > P[k, 2]:
            continue  # not a local maximum
        if any(np.hypot(*(P[k, :2] - P[j, :2])) < radius_mm for j in chosen):
            continue
        chosen.append(int(k))
    return idx[np.asarray(chosen, dtype=np.int64)]


def _channels(V: np.ndarray, outer_faces: np.ndarray, z_top: float, s: MoldSettings):
    """The pour hole and vents as vertical cylinders (see the module docstring), and where they are (mm)."""
    from manifold3d import Manifold

    tops = high_points(V, outer_faces, s.vent_spacing_mm, 1 + max(0, s.vents))
    parts, where = [], []
    for k, v in enumerate(tops):
        d = s.pour_mm if k == 0 else s.vent_mm
        z0 = V[v, 2] - s.channel_overlap_mm
        height = z_top + 1.0 - z0
        parts.append(Manifold.cylinder(height, d / 2, d / 2, 32).translate([V[v, 0], V[v, 1], z0]))
        where.append({"kind": "pour" if k == 0 else "vent", "diameter_mm": d,
                      "at_mm": [float(V[v, 0]), float(V[v, 1]), float(V[v, 2])]})
    return parts, where


def build_mold(nodes_m: np.ndarray, skin_faces: np.ndarray, outer_faces: np.ndarray, inner_faces: np.ndarray,
               settings: MoldSettings = MoldSettings()) -> dict:
    """All parts as (vertices mm, faces) arrays in the casting frame, plus the frame and the volumes (mm³).

    ``skin_faces``: the closed, outward boundary of the skin solid; ``outer_faces``/``inner_faces``: the two design
    surfaces (all in the node numbering of ``nodes_m``, metres).
    """
    from manifold3d import Manifold, OpType

    s = settings
    R = casting_frame(nodes_m, outer_faces)
    V = (np.asarray(nodes_m, dtype=np.float64) @ R.T) * 1e3
    lo, hi = V.min(axis=0), V.max(axis=0)
    z_b = lo[2] - s.below_mm
    centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), z_b])
    V -= centre  # skin centred over the plate, plate top at z = 0
    lo, hi = V.min(axis=0), V.max(axis=0)
    used = np.unique(skin_faces)
    skin = _manifold(V, skin_faces)
    x0, y0 = lo[0] - s.margin_mm, lo[1] - s.margin_mm
    x1, y1 = hi[0] + s.margin_mm, hi[1] + s.margin_mm
    z_t = hi[2] + s.above_mm
    box = Manifold.cube([x1 - x0, y1 - y0, z_t]).translate([x0, y0, 0.0])
    plate = Manifold.cube([x1 - x0, y1 - y0, s.plate_mm]).translate([x0, y0, -s.plate_mm])
    below = _sweep(V, skin_faces, 0.0)
    above = _sweep(V, skin_faces, z_t)
    core_body = (below ^ box) - above
    inset = s.margin_mm / 2
    keys = []
    for kx, ky in ((x0 + inset, y0 + inset), (x1 - inset, y0 + inset), (x0 + inset, y1 - inset),
                   (x1 - inset, y1 - inset)):
        keys.append(Manifold.cylinder(s.key_height_mm, s.key_radius_mm, s.key_radius_mm * s.key_taper, 48)
                    .translate([kx, ky, 0.0]))
    key_union = keys[0] + keys[1] + keys[2] + keys[3]
    if not (key_union ^ (below + skin)).is_empty():
        raise ValueError("registration keys overlap the skin's footprint: raise margin_mm")
    core_body = _clean(core_body, s.sliver_mm3, s.tolerance_mm)
    shell = box - skin - core_body - key_union
    channels, channel_at = _channels(V, outer_faces, z_t, s)
    channel_mm3 = 0.0
    if channels:
        from manifold3d import OpType

        before = shell.volume()
        shell = shell - Manifold.batch_boolean(channels, OpType.Add)
        channel_mm3 = before - shell.volume()  # what the channels took from the shell
    # Pockets the shell cannot reach (closed between the skin and the core, e.g. the slot between overlapping
    # lips) would touch the shell along edges only: they belong to the core.
    pieces = sorted(shell.decompose(), key=lambda c: -c.volume())
    pockets = [c for c in pieces[1:] if c.volume() >= s.sliver_mm3]
    shell = pieces[0]
    if pockets:
        core_body = core_body + Manifold.batch_boolean(pockets, OpType.Add)
    core = _clean(plate + core_body + key_union, s.sliver_mm3, s.tolerance_mm)
    xm = 0.5 * (lo[0] + hi[0])
    right, left = (_clean(h, s.sliver_mm3, s.tolerance_mm) for h in shell.split_by_plane([1.0, 0.0, 0.0], xm))
    left, right, pin_gap = _shell_pins(left, right, xm, (y0 + s.margin_mm / 2, y1 - s.margin_mm / 2), 0.5 * z_t,
                                       skin + core + key_union, s)
    core, notched_core = _repair(core, s)
    left, notched_left = _repair(left, s)
    right, notched_right = _repair(right, s)
    core, islands_core = _drop_islands(core, s.island_fraction)
    left, islands_left = _drop_islands(left, s.island_fraction)
    right, islands_right = _drop_islands(right, s.island_fraction)
    parts = {"skin": _arrays(skin), "mold_core": _arrays(core), "mold_shell_left": _arrays(left),
             "mold_shell_right": _arrays(right)}
    volumes = {"skin_mm3": skin.volume(), "core_mm3": core.volume(), "plate_mm3": plate.volume(),
               "keys_mm3": key_union.volume(), "box_mm3": box.volume(), "shell_left_mm3": left.volume(),
               "shell_right_mm3": right.volume(), "channels_mm3": channel_mm3, "pin_gap_mm3": pin_gap}
    surfaces = {"skin_outer_surface": (V, outer_faces), "skin_inner_surface": (V, inner_faces)}
    return {"parts": parts, "surfaces": surfaces,
            "frame": {"rotation_rows_xyz": R.tolist(), "offset_mm": centre.tolist(), "parting_plane_x_mm": float(xm),
                      "box_mm": [[x0, y0, 0.0], [x1, y1, z_t]], "plate_mm": s.plate_mm},
            "volumes": volumes, "vertices_used": int(used.size), "pockets_to_core": len(pockets),
            "channels": channel_at,
            "notched_mm3": {"core": notched_core, "shell_left": notched_left, "shell_right": notched_right},
            "islands_mm3": {"core": islands_core, "shell_left": islands_left, "shell_right": islands_right},
            "flash_mm3": notched_core + notched_left + notched_right + islands_core + islands_left + islands_right}


def volume_balance(volumes: dict, flash_mm3: float = 0.0) -> dict:
    """The shell's cavity less the core above the plate, the pour and vent channels, the shell pins' clearance and
    the repair notches and islands (flash), against the skin (mm³)."""
    cavity = volumes["box_mm3"] - volumes["shell_left_mm3"] - volumes["shell_right_mm3"]
    core_above = volumes["core_mm3"] - volumes["plate_mm3"]
    channels = volumes.get("channels_mm3", 0.0)
    pin_gap = volumes.get("pin_gap_mm3", 0.0)
    skin_from_mold = cavity - core_above - channels - pin_gap - flash_mm3
    return {"shell_cavity_mm3": cavity, "core_above_plate_mm3": core_above, "channels_mm3": channels,
            "pin_gap_mm3": pin_gap,
            "flash_mm3": flash_mm3,
            "skin_from_mold_mm3": skin_from_mold, "skin_mm3": volumes["skin_mm3"],
            "relative_difference": abs(skin_from_mold - volumes["skin_mm3"]) / volumes["skin_mm3"]}


def skin_surfaces(mesh, outer: np.ndarray, inner: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(closed outward boundary, outer-surface faces, inner-surface faces) of a skin tet mesh, mesh numbering."""
    from offline.fem import boundary_faces

    bf = boundary_faces(mesh)
    mo = np.zeros(mesh.n_nodes, dtype=bool)
    mo[outer] = True
    mi = np.zeros(mesh.n_nodes, dtype=bool)
    mi[inner] = True
    return bf, bf[mo[bf].all(axis=1)], bf[mi[bf].all(axis=1)]


def export_mold(skin_dir: str | Path, out_dir: str | Path, settings: MoldSettings = MoldSettings(),
                check: bool = True) -> dict:
    """Write the STL set of the skin in ``skin_dir`` (``skin.vtu`` + ``face_units.npz``) into ``out_dir`` with
    ``mold_report.json`` (frame, volumes, the volume balance and, with ``check``, each solid's checks)."""
    from models.errors import SpecError
    from offline.fem import load_mesh

    skin_dir, out = Path(skin_dir), Path(out_dir)
    fu = skin_dir / "face_units.npz"
    if not (skin_dir / "skin.vtu").is_file() or not fu.is_file():
        raise SpecError(str(skin_dir), "skin folder", "needs skin.vtu and face_units.npz")
    mesh = load_mesh(skin_dir / "skin.vtu")
    with np.load(fu) as z:
        if "surface_nodes" not in z.files or "inner_nodes" not in z.files:
            raise SpecError(str(fu), "surface_nodes/inner_nodes", "missing: the mold needs both design surfaces")
        outer, inner = np.asarray(z["surface_nodes"]), np.asarray(z["inner_nodes"])
    skin_faces, outer_faces, inner_faces = skin_surfaces(mesh, outer, inner)
    nodes = np.asarray(mesh.nodes)
    crossing = self_intersecting_pairs(nodes * 1e3, skin_faces)  # in mm, as the mold is built
    if len(crossing):
        at = nodes[skin_faces[np.unique(crossing.ravel())]].reshape(-1, 3).mean(axis=0) * 1e3
        raise SpecError(str(skin_dir / "skin.vtu"), "surface",
                        f"{len(crossing)} pairs of its boundary triangles cross each other, around "
                        f"({at[0]:.1f}, {at[1]:.1f}, {at[2]:.1f}) mm: no mold can be cast from a skin that passes "
                        "through itself")
    # A part whose STL defects the notches cannot clear is built again with a coarser vertex-merging tolerance and
    # wider notches (flash the casting fills; all still below a printer's resolution): a layered skin's finer inner
    # surface needs it.
    tries = [settings, *(replace(settings, tolerance_mm=max(t, settings.tolerance_mm),
                                 notch_mm=max(n, settings.notch_mm)) for t, n in REPAIR_STEPS_MM
                         if t > settings.tolerance_mm or n > settings.notch_mm)]
    for k, attempt in enumerate(tries):
        try:
            result = build_mold(nodes, skin_faces, outer_faces, inner_faces, attempt)
            break
        except ValueError as exc:
            if k == len(tries) - 1:
                tried = ", ".join(f"{t.tolerance_mm:g}/{t.notch_mm:g}" for t in tries)
                raise SpecError(str(skin_dir / "skin.vtu"), "mold",
                                f"{exc} (tolerance/notch tried: {tried} mm)") from exc
    settings = attempt
    flash = float(result["flash_mm3"])
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    for name, (v, f) in {**result["parts"], **result["surfaces"]}.items():
        v, f = merge_as_stl(v, f)  # what the file holds: single precision, collapsed slivers dropped
        used = np.unique(f)
        remap = np.full(len(v), -1)
        remap[used] = np.arange(used.size)
        path = out / f"{name}.stl"
        _write_stl(path, v[used], remap[f])
        files[name] = path.name
    report = {"units": "mm", "settings": asdict(settings), "files": files, "frame": result["frame"],
              "volumes": result["volumes"], "volume_balance": volume_balance(result["volumes"], flash),
              "pockets_to_core": result["pockets_to_core"], "notched_mm3": result["notched_mm3"],
              "islands_mm3": result["islands_mm3"], "channels": result["channels"],
              "open_sheets": ["skin_outer_surface", "skin_inner_surface"]}
    if check:
        report["checks"] = {name: check_stl(out / files[name]).as_dict() for name in result["parts"]}
        files_v = {name: report["checks"][name]["volume"] for name in result["parts"]}
        # the same balance with the solids' volumes as the written files hold them
        from_files = {**result["volumes"], "skin_mm3": files_v["skin"], "core_mm3": files_v["mold_core"],
                      "shell_left_mm3": files_v["mold_shell_left"], "shell_right_mm3": files_v["mold_shell_right"]}
        report["volume_balance_from_files"] = volume_balance(from_files, flash)
    mold_picture(out / "mold.png", result)
    report["picture"] = "mold.png"
    (out / "mold_report.json").write_text(json.dumps(report, indent=1, default=float))
    return report


def mold_picture(path: Path, result: dict) -> None:
    """The parts side by side (3-D views, mm): skin, core, the two shell halves pulled apart along x."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parts = result["parts"]
    fig = plt.figure(figsize=(13, 3.8))
    for k, (name, colour) in enumerate((("skin", "tab:orange"), ("mold_core", "tab:blue"),
                                        ("mold_shell_left", "tab:gray"), ("mold_shell_right", "tab:gray"))):
        v, f = parts[name]
        ax = fig.add_subplot(1, 4, k + 1, projection="3d")
        ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=f, color=colour, linewidth=0, antialiased=False,
                        shade=True)
        ax.view_init(elev=25, azim=-60 if "right" not in name else -120)
        ax.set_title(name.replace("_", " "), fontsize=9)
        ax.set_box_aspect(np.ptp(v, axis=0))
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
