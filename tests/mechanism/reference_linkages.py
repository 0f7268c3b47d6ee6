"""The sample head's linkages as closed-form formulas: the test oracle the mechanism file is checked against.

These are the hand-written drives the sample head was first described by (four-bar rockers, crank-sliders whose
link rocks as it slides, a five-bar per lip corner turned by a fraction of its pull rod, the lower lip carried by
the jaw). ``tests/mechanism/test_sample.py`` asserts that solving ``heads/sample/mechanism.toml`` gives the same link
poses. The one difference: these formulas placed each lip corner's five-bar in a skewed plane (its two pull
directions 97 degrees apart, treated as perpendicular), which no rigid rods can build; the mechanism file keeps the
up direction and makes the back direction perpendicular to it, and the tests compare with :func:`orthonormal_corners`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from models.rigid import pose, rotvec_to_matrix

MIRROR = np.diag([-1.0, 1.0, 1.0])


# ---------------------------------------------------------------------------- linkage primitives
def _circle_intersection(p0: np.ndarray, r0: float, p1: np.ndarray, r1: float, near: np.ndarray) -> np.ndarray:
    """Intersection of two circles in the plane nearest to ``near`` (the assembly branch)."""
    d = float(np.linalg.norm(p1 - p0))
    if d > r0 + r1 or d < abs(r0 - r1) or d == 0.0:
        raise ValueError("linkage cannot assemble at this input (rods too short)")
    a = (r0**2 - r1**2 + d**2) / (2 * d)
    h = math.sqrt(max(r0**2 - a**2, 0.0))
    e = (p1 - p0) / d
    m = p0 + a * e
    perp = np.array([-e[1], e[0]])
    c1, c2 = m + h * perp, m - h * perp
    return c1 if np.linalg.norm(c1 - near) <= np.linalg.norm(c2 - near) else c2


@dataclass(frozen=True)
class FourBar:
    """Planar four-bar: ground pivots O2=(0,0), O4=(ground,0); crank angle in → rocker angle out (rad)."""

    ground: float
    crank: float
    coupler: float
    rocker: float
    crank0: float  # crank angle at motor zero

    def rocker_angle(self, q: float) -> float:
        th = self.crank0 + q
        A = self.crank * np.array([math.cos(th), math.sin(th)])
        O4 = np.array([self.ground, 0.0])
        # assembly branch: rocker tip above the ground line
        B = _circle_intersection(A, self.coupler, O4, self.rocker, near=O4 + np.array([0.0, self.rocker]))
        return math.atan2(B[1] - O4[1], B[0] - O4[0])

    def output(self, q: float) -> float:
        """Rocker rotation from its position at motor zero (rad)."""
        return self.rocker_angle(q) - self.rocker_angle(0.0)


@dataclass(frozen=True)
class CrankSlider:
    """Crank of radius ``crank`` and rod ``rod`` pushing a slider: motor angle → slider travel (m)."""

    crank: float
    rod: float
    crank0: float
    ratio: float = 1.0  # crank turns per motor turn (belt reduction)

    def position(self, q: float) -> float:
        th = self.crank0 + self.ratio * q
        return self.crank * math.cos(th) + math.sqrt(self.rod**2 - (self.crank * math.sin(th)) ** 2)

    def output(self, q: float) -> float:
        """Slider travel from its position at motor zero (m)."""
        return self.position(0.0) - self.position(q)


# ---------------------------------------------------------------------------- link drives
def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


@dataclass(frozen=True)
class HingeDrive:
    """A link rotating about a fixed axis through ``pivot``, driven by a four-bar rocker."""

    motor: str
    linkage: FourBar
    pivot: tuple[float, float, float]
    axis: tuple[float, float, float]
    gain: float = 1.0

    def motors(self) -> tuple[str, ...]:
        return (self.motor,)

    def transform(self, q: Mapping[str, float]) -> np.ndarray:
        phi = self.gain * self.linkage.output(q[self.motor])
        R = rotvec_to_matrix(_unit(self.axis) * phi)
        c = np.asarray(self.pivot)
        return pose(R, c - R @ c)


@dataclass(frozen=True)
class SliderDrive:
    """A link translated along ``direction`` by a crank-slider, tilting about ``tilt_axis`` as it slides."""

    motor: str
    linkage: CrankSlider
    direction: tuple[float, float, float]
    anchor: tuple[float, float, float]
    tilt_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    tilt_per_m: float = 0.0  # rad of tilt per metre of travel

    def motors(self) -> tuple[str, ...]:
        return (self.motor,)

    def transform(self, q: Mapping[str, float]) -> np.ndarray:
        s = self.linkage.output(q[self.motor])
        R = rotvec_to_matrix(_unit(self.tilt_axis) * self.tilt_per_m * s)
        c = np.asarray(self.anchor)
        return pose(R, c - R @ c + _unit(self.direction) * s)


@dataclass(frozen=True)
class FiveBarDrive:
    """A point pulled by two motors: crank tips A1, A2 joined to the link point C by rods (coupled motors).

    The plane has axes ``u`` (first motor's pull, e.g. up) and ``v`` (second motor's pull, e.g. back);
    C starts at the origin of the plane at motor zero. The link turns about the plane normal with the
    first rod.
    """

    motors_: tuple[str, str]
    pivot1: tuple[float, float]  # plane coordinates (m)
    pivot2: tuple[float, float]
    crank1: float
    crank2: float
    crank0_1: float
    crank0_2: float
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    anchor: tuple[float, float, float]
    turn_gain: float = 1.0
    ratio: float = 1.0  # crank turns per motor turn (belt reduction)

    def motors(self) -> tuple[str, ...]:
        return self.motors_

    def _tips(self, q1: float, q2: float) -> tuple[np.ndarray, np.ndarray]:
        t1, t2 = self.crank0_1 + self.ratio * q1, self.crank0_2 + self.ratio * q2
        a1 = np.asarray(self.pivot1) + self.crank1 * np.array([math.cos(t1), math.sin(t1)])
        a2 = np.asarray(self.pivot2) + self.crank2 * np.array([math.cos(t2), math.sin(t2)])
        return a1, a2

    def point(self, q1: float, q2: float) -> tuple[np.ndarray, float]:
        """Plane position of C and the first rod's angle."""
        a10, a20 = self._tips(0.0, 0.0)
        L1 = float(np.linalg.norm(a10))
        L2 = float(np.linalg.norm(a20))
        a1, a2 = self._tips(q1, q2)
        c = _circle_intersection(a1, L1, a2, L2, near=np.zeros(2))
        d = c - a1
        return c, math.atan2(d[1], d[0])

    def transform(self, q: Mapping[str, float]) -> np.ndarray:
        c, ang = self.point(q[self.motors_[0]], q[self.motors_[1]])
        _, ang0 = self.point(0.0, 0.0)
        u, v = _unit(self.u), _unit(self.v)
        n = _unit(np.cross(u, v))
        R = rotvec_to_matrix(n * self.turn_gain * (ang - ang0))
        a = np.asarray(self.anchor)
        return pose(R, a - R @ a + c[0] * u + c[1] * v)


# ---------------------------------------------------------------------------- the mechanism
@dataclass
class LinkDef:
    """One link: its rest frame (4x4, head frame), its drive (None: rigid), an optional carrier link."""

    name: str
    rest: np.ndarray
    drive: HingeDrive | SliderDrive | FiveBarDrive | None = None
    carrier: str | None = None
    mirror: bool = False


@dataclass
class Mechanism:
    """Ground truth of a head: per-actuator zero error and hard stops, and the links' drives.

    ``link_poses(actuators)`` maps measured SI actuator values to each link's true 4x4 pose; the joint
    angle the linkage sees is ``clip(value - zero_error, stop_lo, stop_hi)``.
    """

    links: dict[str, LinkDef]
    zero_error: dict[str, float] = field(default_factory=dict)
    stops: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def actuators(self) -> tuple[str, ...]:
        names: list[str] = []
        for link in self.links.values():
            if link.drive is not None:
                names.extend(m for m in link.drive.motors() if m not in names)
        return tuple(names)

    def joint_angles(self, actuators: Mapping[str, float]) -> dict[str, float]:
        """What the linkages see: actuator values minus zero error, clipped at the hard stops."""
        out = {}
        for name in self.actuators:
            value = float(actuators.get(name, 0.0)) - self.zero_error.get(name, 0.0)
            lo, hi = self.stops.get(name, (-math.inf, math.inf))
            out[name] = min(max(value, lo), hi)
        return out

    def transforms(self, actuators: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Each link's true rigid transform from its rest pose (4x4, head frame)."""
        q = self.joint_angles(actuators)
        out: dict[str, np.ndarray] = {}
        for name in self._order():
            link = self.links[name]
            T = np.eye(4)
            if link.drive is not None:
                T = link.drive.transform(q)
                if link.mirror:
                    M = np.eye(4)
                    M[:3, :3] = MIRROR
                    T = M @ T @ M
            if link.carrier is not None:
                T = out[link.carrier] @ T
            out[name] = T
        return out

    def link_poses(self, actuators: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Ground-truth 4x4 pose (head frame, SI) of every link at these actuator values."""
        return {n: T @ self.links[n].rest for n, T in self.transforms(actuators).items()}

    def rest_poses(self) -> dict[str, np.ndarray]:
        """Each link's rest frame (its pose when every joint is at its mechanical zero)."""
        return {n: link.rest.copy() for n, link in self.links.items()}

    def _order(self) -> list[str]:
        done: list[str] = []
        pending = list(self.links)
        while pending:
            for n in list(pending):
                c = self.links[n].carrier
                if c is None or c in done:
                    done.append(n)
                    pending.remove(n)
        return done


def _rest(origin, rotvec) -> np.ndarray:
    return pose(rotvec_to_matrix(np.asarray(rotvec, dtype=float)), np.asarray(origin, dtype=float))


def _mirror_rest(T: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = MIRROR
    return M @ T @ M


#: Link frame origins (m): the centroids of the node sets of the shipped skin mesh ``heads/sample/skin/skin.vtu``
#: (mesh frame: x to the head's left, y up, z forward; checked against the mesh by the tests), so the link
#: map's transforms apply to the mesh nodes directly.
SAMPLE_ANCHORS: dict[str, tuple[float, float, float]] = {
    "skull": (-0.0005, 0.7632, 0.1245),
    "jaw": (0.0000, 0.6310, 0.1224),
    "lip_corner_l": (0.0292, 0.6590, 0.1326),
    "lip_corner_r": (-0.0292, 0.6591, 0.1326),
    "upper_lip": (0.0002, 0.6723, 0.1486),
    "lower_lip": (-0.0005, 0.6483, 0.1447),
    "cheek_l": (0.0459, 0.6980, 0.1224),
    "cheek_r": (-0.0465, 0.6970, 0.1220),
    "brow_l": (0.0313, 0.7461, 0.1338),
    "brow_r": (-0.0313, 0.7461, 0.1333),
    "lid_l": (0.0325, 0.7344, 0.1340),
    "lid_r": (-0.0325, 0.7343, 0.1340),
}


def sample_linkages(anchors: Mapping[str, tuple[float, float, float]] | None = None) -> Mechanism:
    """The sample head's linkages at their design values (13 motors, 12 links; no zero error, no hard stops).

    Each link's frame origin is its anchor (default :data:`SAMPLE_ANCHORS`, the skin mesh's node-set
    centroids); pivots and linkages sit at fixed offsets from it (the jaw hinge 65 mm above and 85 mm behind
    the chin, each lid's hinge 12 mm behind the lid).
    """
    A = {k: np.asarray(v, dtype=float) for k, v in (anchors or SAMPLE_ANCHORS).items()}
    deg = math.pi / 180.0
    jaw_bar = FourBar(ground=0.040, crank=0.020, coupler=0.042, rocker=0.024, crank0=100 * deg)
    lid_bar = FourBar(ground=0.020, crank=0.010, coupler=0.021, rocker=0.011, crank0=95 * deg)
    lip_slider = CrankSlider(crank=0.018, rod=0.040, crank0=80 * deg, ratio=0.6)
    cheek_slider = CrankSlider(crank=0.016, rod=0.036, crank0=75 * deg, ratio=0.6)
    brow_slider = CrankSlider(crank=0.013, rod=0.032, crank0=85 * deg, ratio=0.6)

    def t(v: np.ndarray) -> tuple[float, float, float]:
        return (float(v[0]), float(v[1]), float(v[2]))

    L: dict[str, LinkDef] = {}
    L["skull"] = LinkDef("skull", _rest(A["skull"], (0.0, 0.0, 0.0)))
    L["jaw"] = LinkDef(
        "jaw", _rest(A["jaw"], (0.05, 0.0, 0.0)),
        HingeDrive("jaw", jaw_bar, pivot=t(np.add(A["jaw"], (0.0, 0.065, -0.085))), axis=(1.0, 0.0, 0.0)),
    )
    L["lower_lip"] = LinkDef(
        "lower_lip", _rest(A["lower_lip"], (-0.1, 0.0, 0.0)),
        SliderDrive("lower_lip", lip_slider, direction=(0.0, -0.3, 1.0), anchor=t(A["lower_lip"]),
                    tilt_axis=(1.0, 0.0, 0.0), tilt_per_m=12.0),
        carrier="jaw",
    )
    L["upper_lip"] = LinkDef(
        "upper_lip", _rest(A["upper_lip"], (0.08, 0.0, 0.0)),
        SliderDrive("upper_lip", lip_slider, direction=(0.0, 1.0, 0.4), anchor=t(A["upper_lip"]),
                    tilt_axis=(-1.0, 0.0, 0.0), tilt_per_m=10.0),
    )
    corner = dict(
        pivot1=(0.045, 0.004), pivot2=(0.004, 0.045), crank1=0.014, crank2=0.014, ratio=0.5,
        crank0_1=-math.pi / 2, crank0_2=0.0, u=(0.0, 1.0, 0.15), v=(0.6, 0.0, -0.8), turn_gain=0.6,
    )
    for side, mirror in (("l", False), ("r", True)):
        # right-side links are built as left ones at the mirrored anchor, then mirrored back (x → -x)
        def at(name: str, m: bool = mirror, sd: str = side) -> np.ndarray:
            return A[f"{name}_{sd}"] * ((-1.0, 1.0, 1.0) if m else 1.0)

        defs = {
            f"lip_corner_{side}": LinkDef(
                f"lip_corner_{side}", _rest(at("lip_corner"), (0.0, 0.2, 0.1)),
                FiveBarDrive((f"lip_corner_{side}_up", f"lip_corner_{side}_back"), anchor=t(at("lip_corner")),
                             **corner),
            ),
            f"cheek_{side}": LinkDef(
                f"cheek_{side}", _rest(at("cheek"), (0.0, 0.3, 0.0)),
                SliderDrive(f"cheek_{side}", cheek_slider, direction=(0.2, 1.0, 0.3), anchor=t(at("cheek")),
                            tilt_axis=(0.0, 0.0, 1.0), tilt_per_m=8.0),
            ),
            f"brow_{side}": LinkDef(
                f"brow_{side}", _rest(at("brow"), (0.0, 0.1, -0.05)),
                SliderDrive(f"brow_{side}", brow_slider, direction=(0.0, 1.0, 0.1), anchor=t(at("brow")),
                            tilt_axis=(0.0, 0.0, 1.0), tilt_per_m=15.0),
            ),
            f"lid_{side}": LinkDef(
                f"lid_{side}", _rest(at("lid"), (-0.2, 0.0, 0.0)),
                HingeDrive(f"lid_{side}", lid_bar, pivot=t(np.add(at("lid"), (0.0, 0.0, -0.012))),
                           axis=(-1.0, 0.0, 0.0)),
            ),
        }
        for name, d in defs.items():
            if mirror:
                d.rest = _mirror_rest(d.rest)
                d.mirror = True
            L[name] = d

    return Mechanism(L)


def orthonormal_corners(mech: Mechanism) -> Mechanism:
    """The formulas with each lip corner's back direction made perpendicular to its up direction (as built)."""
    from dataclasses import replace

    for link in mech.links.values():
        d = link.drive
        if isinstance(d, FiveBarDrive):
            u, v = _unit(d.u), _unit(d.v)
            w = _unit(v - (v @ u) * u)
            link.drive = replace(d, u=tuple(float(x) for x in u), v=tuple(float(x) for x in w))
    return mech
