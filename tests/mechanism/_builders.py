"""Small mechanism files for the tests: a planar four-bar, and one body of every joint kind."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np


def four_bar(ground: float = 0.040, crank: float = 0.020, coupler: float = 0.042, rocker: float = 0.024,
             crank0_deg: float = 100.0) -> dict[str, Any]:
    """A four-bar in the xy plane: crank pivot at the origin, rocker pivot ``ground`` along x; the rocker is a link."""
    th = math.radians(crank0_deg)
    A = np.array([crank * math.cos(th), crank * math.sin(th), 0.0])
    O4 = np.array([ground, 0.0, 0.0])
    d = float(np.linalg.norm(O4 - A))
    a = (coupler**2 - rocker**2 + d**2) / (2 * d)
    h = math.sqrt(coupler**2 - a**2)
    e = (O4 - A) / d
    perp = np.array([-e[1], e[0], 0.0])
    B = A + a * e + h * perp  # the rocker tip above the ground line
    return {
        "mechanism": {"name": "four-bar", "ground": "frame"},
        "bodies": {
            "frame": {"origin": [0.02, 0.0, 0.0], "extent": 0.05},
            "crank": {"origin": [0.0, 0.0, 0.0], "extent": crank * 1.2},
            "rocker": {"origin": O4.tolist(), "extent": rocker * 1.5, "node_set": "rocker"},
        },
        "joints": {
            "crank_pivot": {"kind": "revolute", "parent": "frame", "child": "crank", "anchor": [0.0, 0.0, 0.0],
                            "axis": [0.0, 0.0, 1.0], "actuated": True},
            "rocker_pivot": {"kind": "revolute", "parent": "frame", "child": "rocker", "anchor": O4.tolist(),
                             "axis": [0.0, 0.0, 1.0]},
        },
        "couplers": {"coupler": {"kind": "rod", "a": "crank", "a_point": A.tolist(), "b": "rocker",
                                 "b_point": B.tolist(), "length": coupler}},
        "motors": {"m": {"joint": "crank_pivot"}},
    }


def every_kind() -> dict[str, Any]:
    """A four-bar whose rocker carries a slider (prismatic, rocking), a ball-jointed arm held by two rods and a
    gear, and a plate fixed to the arm: every joint and coupler kind in one group."""
    doc = copy.deepcopy(four_bar())
    doc["bodies"]["rocker"]["extent"] = 0.05
    pin = np.array([0.05, 0.01, 0.0])
    d = np.array([1.0, 0.2, 0.1]) / np.linalg.norm([1.0, 0.2, 0.1])
    n = np.cross(d, [0.0, 0.0, 1.0])
    n /= np.linalg.norm(n)
    tip = pin - 0.03 * d  # the push rod lies along the guide: no dead point near neutral
    pivot = tip - 0.012 * np.cross(n, d)
    doc["bodies"].update({
        "slider": {"origin": [0.05, 0.01, 0.0], "extent": 0.03, "node_set": "slider"},
        "slider_crank": {"origin": pivot.tolist(), "extent": 0.02},
        "arm": {"origin": [0.03, 0.0, 0.02], "extent": 0.04},
        "plate": {"origin": [0.03, 0.01, 0.03], "extent": 0.02, "node_set": "plate"},
    })
    doc["joints"].update({
        "slide": {"kind": "prismatic", "parent": "rocker", "child": "slider", "anchor": [0.05, 0.01, 0.0],
                  "axis": [1.0, 0.2, 0.1], "tilt_axis": [0.0, 0.3, 1.0], "tilt_deg_per_m": 300.0},
        "slider_crank_pivot": {"kind": "revolute", "parent": "rocker", "child": "slider_crank",
                               "anchor": pivot.tolist(), "axis": n.tolist(), "actuated": True},
        "ball": {"kind": "spherical", "parent": "frame", "child": "arm", "anchor": [0.03, 0.0, 0.02]},
        "weld": {"kind": "fixed", "parent": "arm", "child": "plate", "anchor": [0.03, 0.01, 0.03]},
    })
    doc["couplers"].update({
        "push": {"kind": "rod", "a": "slider_crank", "a_point": tip.tolist(), "b": "slider", "b_point": pin.tolist(),
                 "length": 0.03},
        "arm_rod1": {"kind": "rod", "a": "rocker", "a_point": [0.04, 0.02, 0.0], "b": "arm",
                     "b_point": [0.03, 0.02, 0.02], "length": float(np.linalg.norm([-0.01, 0.0, 0.02]))},
        "arm_rod2": {"kind": "rod", "a": "frame", "a_point": [0.05, 0.0, 0.0], "b": "arm",
                     "b_point": [0.03, 0.0, 0.05], "length": float(np.linalg.norm([-0.02, 0.0, 0.05]))},
        "arm_gear": {"kind": "gear", "a": "rocker", "b": "arm", "axis": [0.0, 0.0, 1.0], "ratio": 0.5},
    })
    doc["motors"]["s"] = {"joint": "slider_crank_pivot", "ratio": 0.6}
    return doc


def sample_layout(weights: dict[str, float]):
    """The layout-design problem of the sample head's face for one target (ARKit unit weights), default envelope."""
    from models.mechanism import load_mechanism
    from offline.design.face import load_face
    from offline.design.mechanism_design import LayoutProblem, LayoutSettings
    from offline.design.mechanism_design_envelope import Envelope, design_space
    from offline.design.targets import target_surface
    from tests.runtime.conftest import SAMPLE

    face = load_face(SAMPLE)
    space = design_space(load_mechanism(face.skin.head.path("mechanism")), Envelope())
    names, offsets = face.skin.face_units()
    rest = np.asarray(face.mesh.nodes)[face.outer]
    return LayoutProblem(face, [target_surface(rest, offsets, names, weights)], space, LayoutSettings())
