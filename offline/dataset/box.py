"""A small FEM pose problem on a skin slab: two patches of its underside lifted by two linear actuators.

It exercises the whole FEM dataset path (head config, link map m(p), tet mesh with node sets, Newton solves) in
seconds, for tests and for the engine benchmark. :func:`write_box_problem` writes ``head.toml``, ``linkmap.json``
and ``skin.vtu`` into a folder and returns the :class:`FemSpec` that reads them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from offline.dataset.fem_problem import FemSpec

BOX_HEAD = """# A slab of skin on a rigid base, lifted by two linear actuators from below.
[head]
name = "box"
[buses.b]
driver = "dynamixel"
[[actuators]]
name = "lift_l"
bus = "b"
id = 1
unit = "mm"
min = 0.0
max = 1.5
max_velocity = 10.0
max_acceleration = 100.0
[[actuators]]
name = "lift_r"
bus = "b"
id = 2
unit = "mm"
min = -1.0
max = 1.0
max_velocity = 10.0
max_acceleration = 100.0
[links.skull]
rigid = true
[links.left]
actuators = ["lift_l"]
[links.right]
actuators = ["lift_r"]
"""


def write_box_problem(folder: str | Path, size: tuple[float, float, float] = (0.04, 0.02, 0.006),
                      divisions: tuple[int, int, int] = (8, 4, 2), backend: str = "superlu") -> FemSpec:
    """Write the slab problem into ``folder``; the outer surface is the top face (node set ``outer``)."""
    from models.headspec import load_head
    from models.linkmap import LinkFit, LinkMap
    from offline.fem import box_mesh, save_mesh

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lx = size[0]
    mesh = box_mesh(size, divisions)
    X = np.asarray(mesh.nodes)
    z0 = np.asarray(mesh.node_sets["z0"])
    left = z0[X[z0, 0] < 0.25 * lx + 1e-9]
    right = z0[X[z0, 0] > 0.75 * lx - 1e-9]
    skull = z0[(X[z0, 0] > 0.375 * lx - 1e-9) & (X[z0, 0] < 0.625 * lx + 1e-9)]
    mesh = mesh.with_node_sets(skull=skull, left=left, right=right, outer=mesh.node_sets["z1"])
    save_mesh(folder / "skin.vtu", mesh)
    (folder / "head.toml").write_text(BOX_HEAD)
    head = load_head(folder / "head.toml")

    def lift(name: str, acts: tuple[str, ...], centroid: np.ndarray) -> LinkFit:
        coef = np.zeros((3, 6))  # quadratic features [1, x, x²] of the link's one actuator, x = p / 1 mm
        coef[0, :3] = centroid
        coef[1, 2] = 0.001  # the patch rises by p
        return LinkFit(name, acts, coef, np.eye(3))

    links = {
        "skull": LinkFit("skull", (), np.zeros((1, 6)), np.eye(3), rigid=True),
        "left": lift("left", ("lift_l",), X[left].mean(0)),
        "right": lift("right", ("lift_r",), X[right].mean(0)),
    }
    LinkMap(head.actuator_names, [0.0, 0.0], [0.001, 0.001], links, head="box").save(folder / "linkmap.json")
    return FemSpec(config=str(folder / "head.toml"), mesh=str(folder), linkmap=str(folder / "linkmap.json"),
                   backend=backend)
