"""The skin FEM as a pose problem: actuators → link transforms m(p) → Dirichlet conditions → quasi-static solve.

Per pose: the link map gives each attachment link's rigid transform from neutral, each link's node set (named in
the head config) is moved rigidly by it, the skull set stays fixed, and ``offline.fem.solve_static`` finds the
equilibrium from the warm-start state (the nearest solved pose). The dataset stores the outer-surface nodes.

Mesh input: a ``.vtu`` written by ``offline.fem.save_mesh`` or a folder holding ``skin.vtu`` (as written by
``likeness offline mesh``). The outer surface comes from ``face_units.npz`` beside it (``surface_nodes``: outer
mesh node indices, ``surface_triangles``: triangles in mesh numbering; ``names`` + ``offsets`` (U, S, 3): the face
units on those nodes), else from the node set ``outer`` (or ``outer_surface``/``surface``) with triangles taken
from the mesh boundary faces whose three nodes are all outer.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import SpecError
from models.material import SkinMaterial
from offline.dataset.problem import PoseProblem, PoseSolution, ProblemSpec

OUTER_SET_NAMES = ("outer", "outer_surface", "surface")


def _mesh_file(mesh: str | Path) -> Path:
    p = Path(mesh)
    if p.is_dir():
        cand = p / "skin.vtu"
        if not cand.exists():
            raise SpecError(str(p), "skin.vtu", "mesh folder has no skin.vtu")
        return cand
    if not p.exists():
        raise SpecError(str(p), "file", "mesh not found")
    return p


def material_fields(material: SkinMaterial | None) -> dict[str, Any]:
    """:class:`FemSpec` keyword arguments for a head's skin material (empty: the FEM default, said so)."""
    if material is None:
        return {}
    return {"material_model": material.model, "youngs_modulus": material.E, "poisson_ratio": material.nu,
            "material_shape": tuple(sorted(material.shape.items())), "density": material.density,
            "material_source": material.source + (f" — {material.note}" if material.note else "")}


@dataclass(frozen=True)
class FemSpec(ProblemSpec):
    """Paths and solver settings of the FEM pose problem (picklable; built once per worker)."""

    config: str
    mesh: str
    linkmap: str
    backend: str = "auto"
    threads: int = 1
    #: The skin material (names and parameters of :mod:`models.material`); :func:`material_fields` fills these
    #: from a head's ``[skin_material]``. With only prescribed displacements (no loads, no gravity) the poses do
    #: not depend on E, only on ν and the shape parameters.
    material_model: str = "neo_hookean"
    youngs_modulus: float = 78_000.0  # Pa
    poisson_ratio: float = 0.47
    material_shape: tuple[tuple[str, float], ...] = ()
    density: float = 1070.0
    material_source: str = "FEM default E = 78 kPa, nu = 0.47 (the head config names no [skin_material])"
    skull_set: str = "skull"
    max_iterations: int = 30
    load_steps: int | str = 1
    #: "auto": if the link map's neutral link frames lie far (> 20 mm RMS) from their node sets, the link map was
    #: fitted in another head frame: estimate the translation between the frames from the node-set centroids and
    #: express the transforms in the mesh frame. "on" always aligns, "off" never.
    align_frames: str = "auto"
    #: 1: the mesh file's linear tets as they are; 2: the same tets made quadratic (one mid-edge node per edge,
    #: :func:`offline.fem.to_quadratic`), which removes most of a one-element-thick skin's bending stiffness error.
    #: The stored surface is the same outer nodes either way (corner nodes come first), so predictors trained on
    #: either order have the same vertices.
    element_order: int = 1

    @property
    def token(self) -> str:
        stamp = []
        for p in (self.config, self.linkmap, str(_mesh_file(self.mesh))):
            st = Path(p).stat()
            stamp.append((str(Path(p).resolve()), st.st_size, st.st_mtime_ns))
        doc = json.dumps({**self.__dict__, "stamp": stamp}, sort_keys=True, default=str)
        return "fem-" + hashlib.sha1(doc.encode()).hexdigest()[:16]

    def skin_material(self) -> SkinMaterial:
        """The material of this spec in the shared vocabulary."""
        return SkinMaterial(self.material_model, self.youngs_modulus, self.poisson_ratio, dict(self.material_shape),
                            self.density, source=self.material_source)

    def describe(self) -> dict[str, Any]:
        return {"kind": "fem", "config": self.config, "mesh": self.mesh, "linkmap": self.linkmap,
                "element_order": self.element_order, "backend": self.backend, "align_frames": self.align_frames,
                "material": self.skin_material().as_dict()}

    def check(self) -> None:
        """Load everything once in this process so bad inputs fail before any worker starts."""
        self.build()

    def build(self) -> FemSkin:
        return FemSkin(self)


class FemSkin(PoseProblem):
    """The loaded FEM problem of a :class:`FemSpec`."""

    def __init__(self, spec: FemSpec) -> None:
        from models.headspec import load_head
        from models.linkmap import LinkMap
        from offline.fem import SolverOptions, load_mesh, to_quadratic
        from offline.material.models import MaterialParams

        if spec.element_order not in (1, 2):
            raise SpecError(str(spec.mesh), "element_order", "must be 1 (linear) or 2 (quadratic)",
                            spec.element_order)
        self.spec = spec
        self.head = load_head(spec.config)
        self.linkmap = LinkMap.load(spec.linkmap)
        self.linkmap.check_against(self.head)
        mesh_path = _mesh_file(spec.mesh)
        self.mesh = load_mesh(mesh_path)
        sets = self.mesh.node_sets
        if spec.skull_set not in sets:
            raise SpecError(str(mesh_path), f"node set {spec.skull_set}", "missing (the fixed skull attachment)")
        self.moving: dict[str, str] = {}  # link name → node set
        for link in self.head.links:
            if link.rigid:
                continue
            if link.node_set not in sets:
                raise SpecError(str(mesh_path), f"node set {link.node_set}",
                                f"missing (attachment of link {link.name!r} in {spec.config})")
            self.moving[link.name] = link.node_set
        self.frame_offset, self.frame_residual = self._frame_offset()
        if spec.align_frames == "off" or (spec.align_frames == "auto" and self._misfit(np.zeros(3)) <= 0.02):
            self.frame_offset = np.zeros(3)
        self.outer, self._faces = self._outer_surface(mesh_path)
        # Frame alignment, outer surface and regions come from the linear mesh, so both orders store the same vertices
        # with the same labels; the quadratic mesh keeps the linear nodes first and in order.
        self._linear = self.mesh
        if spec.element_order == 2:
            self.mesh = to_quadratic(self.mesh)
        self._fu_names, self._fu = self._face_units(mesh_path.parent)
        mat = spec.skin_material()
        self.material = MaterialParams.from_skin_material(mat).to_fem_material(mat.density)
        self.options = SolverOptions(backend=spec.backend, max_iterations=spec.max_iterations,
                                     load_steps=spec.load_steps)

    def _link_points(self) -> tuple[np.ndarray, np.ndarray]:
        neutral = {a.name: a.neutral for a in self.head.actuators}
        poses = self.linkmap.poses(neutral)
        X = np.asarray(self.mesh.nodes)
        names = [n for n in self.moving if n in poses]
        frames = np.array([poses[n][:3, 3] for n in names])
        centroids = np.array([X[self.mesh.node_sets[self.moving[n]]].mean(axis=0) for n in names])
        return frames, centroids

    def _misfit(self, offset: np.ndarray) -> float:
        frames, centroids = self._link_points()
        return float(np.sqrt(np.mean(np.sum((centroids + offset - frames) ** 2, axis=1))))

    def _frame_offset(self) -> tuple[np.ndarray, float]:
        """Translation o with x_linkmap ≈ x_mesh + o (least squares over the moving links), and its RMS residual."""
        frames, centroids = self._link_points()
        if len(frames) == 0:
            return np.zeros(3), 0.0
        offset = (frames - centroids).mean(axis=0)
        return offset, self._misfit(offset)

    def _outer_surface(self, mesh_path: Path) -> tuple[np.ndarray, np.ndarray]:
        from offline.fem import boundary_faces

        surf = mesh_path.parent / "face_units.npz"
        tris = None
        outer = None
        if surf.exists():
            with np.load(surf) as z:
                if "surface_nodes" in z.files:
                    outer = np.asarray(z["surface_nodes"], dtype=np.int64)
                    if "surface_triangles" in z.files:
                        tris = np.asarray(z["surface_triangles"], dtype=np.int64)
        if outer is None:
            name = next((n for n in OUTER_SET_NAMES if n in self.mesh.node_sets), None)
            if name is None:
                raise SpecError(str(mesh_path), "outer surface",
                                f"no surface.npz beside the mesh and no node set named {' / '.join(OUTER_SET_NAMES)}")
            outer = np.asarray(self.mesh.node_sets[name], dtype=np.int64)
        if tris is None:
            bf = boundary_faces(self.mesh)
            mask = np.zeros(self.mesh.n_nodes, dtype=bool)
            mask[outer] = True
            tris = bf[mask[bf].all(axis=1)]
        lookup = np.full(self.mesh.n_nodes, -1, dtype=np.int64)
        lookup[outer] = np.arange(len(outer))
        faces = lookup[tris]
        if (faces < 0).any():
            raise SpecError(str(mesh_path), "surface triangles", "use nodes outside the outer surface")
        return outer, faces

    def _face_units(self, folder: Path) -> tuple[tuple[str, ...], np.ndarray | None]:
        path = folder / "face_units.npz"
        if not path.exists():
            return (), None
        with np.load(path) as z:
            if "names" not in z.files or "offsets" not in z.files:
                return (), None
            names = tuple(str(n) for n in z["names"])
            offsets = np.asarray(z["offsets"], dtype=np.float32)
        if offsets.shape[1:] != (len(self.outer), 3):
            raise SpecError(str(path), "offsets", f"expected (U, {len(self.outer)}, 3) on the outer nodes",
                            offsets.shape)
        return names, offsets

    def base_surface(self) -> np.ndarray:
        return np.asarray(self.mesh.nodes)[self.outer].copy()

    def faces(self) -> np.ndarray:
        return self._faces.copy()

    def face_units(self) -> tuple[tuple[str, ...], np.ndarray | None]:
        return self._fu_names, self._fu

    def surface_regions(self) -> tuple[tuple[str, ...], np.ndarray]:
        from offline.dataset.regions import label_surface

        sets = self._linear.node_sets
        named = {n: sets[n] for n in (self.spec.skull_set, *self.moving.values())}
        return label_surface(self.base_surface(), self._linear.nodes, named)

    def mesh_info(self) -> dict[str, Any]:
        return {"kind": "tetrahedral FEM", "file": str(_mesh_file(self.spec.mesh)), "element_order": self.mesh.order,
                "n_elements": int(self.mesh.n_tets), "n_nodes": int(self.mesh.n_nodes),
                "n_surface_vertices": len(self.outer), "n_surface_triangles": len(self._faces)}

    def dirichlet(self, p: np.ndarray):
        """Boundary conditions of pose p: link node sets moved rigidly by m(p), the skull fixed."""
        from offline.fem import rigid_transform_dirichlet

        values = dict(zip(self.head.actuator_names, (float(x) for x in p), strict=True))
        T = self.linkmap.transforms(values)
        if np.any(self.frame_offset):
            fwd = np.eye(4)
            fwd[:3, 3] = self.frame_offset
            back = np.eye(4)
            back[:3, 3] = -self.frame_offset
            T = {n: back @ t @ fwd for n, t in T.items()}
        moves = {self.moving[name]: T[name] for name in self.moving if name in T}
        return rigid_transform_dirichlet(self.mesh, moves, fixed_sets=[self.spec.skull_set])

    def solve(self, p: np.ndarray, warm_state: np.ndarray | None, index: int | None = None) -> PoseSolution:
        from offline.fem import kernel_threads

        with kernel_threads(self.spec.threads):
            return self._solve(p, warm_state)

    def _solve(self, p: np.ndarray, warm_state: np.ndarray | None) -> PoseSolution:
        from offline.fem import NotConverged, solve_static

        bc = self.dirichlet(p)
        x0 = None if warm_state is None else np.asarray(warm_state, dtype=np.float64).reshape(-1, 3)
        if x0 is not None and x0.shape != (self.mesh.n_nodes, 3):
            x0 = None
        tries = [x0, None] if x0 is not None else [None]
        last_msg = ""
        for start in tries:
            try:
                res = solve_static(self.mesh, self.material, bc, x0=start, options=self.options)
            except NotConverged as exc:
                res = exc.result
                last_msg = str(exc)
                if start is not None:
                    continue  # a bad warm start: try once more from rest
                return PoseSolution(res.x[self.outer], res.x, False, res.iterations, last_msg)
            except ValueError as exc:  # e.g. the warm start inverts an element under the new boundary
                last_msg = str(exc)
                continue
            msg = "" if start is not None or x0 is None else "warm start rejected; solved from rest"
            return PoseSolution(res.x[self.outer], res.x, bool(res.converged), res.iterations, msg)
        rest = np.asarray(self.mesh.nodes, dtype=np.float64)
        return PoseSolution(rest[self.outer], None, False, 0, last_msg or "no solve possible")
