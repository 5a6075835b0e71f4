"""URDF reading for the robot layer: joints, origins, serial chains and collision primitives.

Everything here is float64 numpy, read once when a robot is built; the batched
torch kinematics live in :mod:`torchrl_silp.robots.base`. pytorch-kinematics'
URDF parser keeps ``<visual>`` geometry only and rounds origins to float32, so
the collision geometry and the origins are read from the text here.

Examples:
    >>> from torchrl_silp.robots.urdf import asset_path, parse_collisions, parse_joints, read_urdf, serial_chain
    >>> text = read_urdf(asset_path("ur5e.urdf"))
    >>> [j.name for j in serial_chain(parse_joints(text), "base_link", "tcp")][:2]
    ['shoulder_pan_joint', 'shoulder_lift_joint']
    >>> prim = parse_collisions(text)[0]
    >>> prim.link, prim.kind, prim.size
    ('base_link', 'cylinder', (0.075, 0.12))
    >>> centres, radii = prim.sphere_cover()
    >>> centres.shape, radii.shape
    ((2, 3), (2,))
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from importlib import resources

import numpy as np

__all__ = [
    "asset_path",
    "read_urdf",
    "rpy_matrix",
    "origin_matrix",
    "UrdfJoint",
    "parse_joints",
    "serial_chain",
    "CollisionPrimitive",
    "parse_collisions",
]

#: joint types a chain may hold; ``continuous`` is a revolute joint without limits
JOINT_TYPES = ("revolute", "continuous", "fixed")
PRIMITIVE_KINDS = ("cylinder", "box", "sphere")


def asset_path(name: str) -> str:
    """Path of a robot description shipped with the package (``assets/`` installs as ``torchrl_silp.assets``)."""
    return str(resources.files("torchrl_silp.assets") / name)


def read_urdf(path: str | os.PathLike) -> str:
    """The text of a URDF file; a ValueError naming ``urdf_path`` when it cannot be read."""
    try:
        with open(path) as fh:
            return fh.read()
    except OSError as err:
        raise ValueError(f"urdf_path: cannot read URDF file {os.fspath(path)!r}: {err}") from err


def rpy_matrix(rpy) -> np.ndarray:
    """The 3x3 rotation of URDF roll-pitch-yaw angles: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Examples:
        >>> import math
        >>> rpy_matrix([0.0, 0.0, math.pi / 2]).round(12).tolist()
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _floats(text: str | None, default: str, n: int, what: str) -> np.ndarray:
    values = (text if text is not None else default).split()
    if len(values) != n:
        raise ValueError(f"urdf: {what} must hold {n} numbers, got {text!r}")
    return np.array([float(v) for v in values])


def origin_matrix(origin: ET.Element | None) -> np.ndarray:
    """The 4x4 pose (float64) of a URDF ``<origin xyz rpy>`` element; identity when it is None."""
    T = np.eye(4)
    if origin is not None:
        T[:3, :3] = rpy_matrix(_floats(origin.get("rpy"), "0 0 0", 3, "<origin rpy>"))
        T[:3, 3] = _floats(origin.get("xyz"), "0 0 0", 3, "<origin xyz>")
    return T


def _root(urdf_text: str) -> ET.Element:
    try:
        return ET.fromstring(urdf_text)
    except ET.ParseError as err:
        raise ValueError(f"urdf: not well-formed XML: {err}") from err


@dataclass(frozen=True)
class UrdfJoint:
    """One ``<joint>`` of a URDF.

    Attributes:
        name: the joint's name.
        type: ``"revolute"``, ``"continuous"``, ``"fixed"`` (or another URDF type, which chains reject).
        parent, child: the links it connects.
        origin: 4x4 pose (float64) of the child frame in the parent frame at zero angle.
        axis: unit rotation axis in the child frame (URDF's default is x).
        limits: ``(lower, upper)`` of ``<limit>``, or None.
    """

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray
    limits: tuple[float, float] | None


def parse_joints(urdf_text: str) -> list[UrdfJoint]:
    """Every ``<joint>`` of a URDF, in document order."""
    joints = []
    for joint in _root(urdf_text).iter("joint"):
        name = joint.get("name")
        parent, child = joint.find("parent"), joint.find("child")
        if parent is None or child is None:
            raise ValueError(f"urdf: joint {name!r} needs a <parent> and a <child>")
        axis = _floats(joint.find("axis").get("xyz") if joint.find("axis") is not None else None, "1 0 0", 3,
                       f"joint {name!r} <axis xyz>")
        norm = float(np.linalg.norm(axis))
        if joint.get("type") in ("revolute", "continuous") and norm < 1e-9:
            raise ValueError(f"urdf: joint {name!r} has a zero <axis>")
        limit = joint.find("limit")
        limits = None
        if limit is not None and limit.get("lower") is not None and limit.get("upper") is not None:
            limits = (float(limit.get("lower")), float(limit.get("upper")))
        joints.append(
            UrdfJoint(name, joint.get("type"), parent.get("link"), child.get("link"), origin_matrix(joint.find("origin")),
                      axis / norm if norm > 0 else axis, limits)
        )
    return joints


def serial_chain(joints: list[UrdfJoint], root: str, tip: str) -> list[UrdfJoint]:
    """The joints from link ``root`` to link ``tip``, root first; a ValueError when no such path exists.

    Every joint on the path must be ``revolute``, ``continuous`` or ``fixed``.
    """
    by_child = {}
    for j in joints:
        if j.child in by_child:
            raise ValueError(f"urdf: link {j.child!r} is the child of two joints")
        by_child[j.child] = j
    path, link = [], tip
    while link != root:
        if link not in by_child:
            where = "is not a link of the URDF" if link == tip else f"is reached from {tip!r} but not from {root!r}"
            raise ValueError(f"urdf: link {link!r} {where}")
        j = by_child[link]
        if j.type not in JOINT_TYPES:
            raise ValueError(f"urdf: joint {j.name!r} has type {j.type!r}; allowed: {', '.join(JOINT_TYPES)}")
        path.append(j)
        link = j.parent
        if len(path) > len(joints):  # pragma: no cover - a loop, which the child check above rules out
            raise ValueError("urdf: the joints form a loop")
    return path[::-1]


class CollisionPrimitive:
    """One ``<collision>`` element: a cylinder (axis along local z), box or sphere.

    Attributes:
        link: name of the link it belongs to.
        kind: ``"cylinder"``, ``"box"`` or ``"sphere"``.
        size: cylinder ``(radius, length)``, box ``(x, y, z)`` or sphere ``(radius,)``.
        transform: 4x4 pose of the primitive in its link frame (float64 numpy).

    Examples:
        >>> import numpy as np
        >>> box = CollisionPrimitive("hand", "box", (0.2, 0.1, 0.1), np.eye(4))
        >>> centres, radii = box.sphere_cover()
        >>> len(radii), bool((np.abs(centres).max(0) + radii.max() >= [0.1, 0.05, 0.05]).all())
        (2, True)
    """

    def __init__(self, link: str, kind: str, size: tuple[float, ...], transform: np.ndarray):
        self.link, self.kind, self.size, self.transform = link, kind, tuple(size), transform

    def __repr__(self) -> str:
        return f"CollisionPrimitive(link={self.link!r}, kind={self.kind!r}, size={self.size})"

    def sphere_cover(self) -> tuple[np.ndarray, np.ndarray]:
        """A conservative sphere cover: every point of the solid lies in some sphere.

        Returns:
            centres ``(n, 3)`` in the link frame and radii ``(n,)`` (float64 numpy).
        """
        if self.kind == "sphere":
            local = np.zeros((1, 3))
            radii = np.array([self.size[0]])
        elif self.kind == "cylinder":
            r, length = self.size
            # n slabs of height h = length / n; the sphere at a slab's centre with
            # radius sqrt(r^2 + (h/2)^2) contains the whole slab (its rim corners
            # are the farthest points). h <= 1.2 r bounds the inflation to ~17 %.
            n = max(1, math.ceil(length / (1.2 * r)))
            h = length / n
            z = -length / 2 + h * (np.arange(n) + 0.5)
            local = np.stack([np.zeros(n), np.zeros(n), z], axis=1)
            radii = np.full(n, math.sqrt(r * r + (h / 2) ** 2))
        elif self.kind == "box":
            size = np.asarray(self.size, dtype=np.float64)
            # cells no longer than max(smallest side, largest side / 3); each cell
            # lies in the sphere through its corners. The bound keeps thin plates
            # (the fingers) to a handful of spheres.
            cell = max(size.min(), size.max() / 3)
            counts = np.maximum(1, np.ceil(size / cell - 1e-9)).astype(int)
            step = size / counts
            axes = [-size[i] / 2 + step[i] * (np.arange(counts[i]) + 0.5) for i in range(3)]
            local = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
            radii = np.full(len(local), 0.5 * float(np.linalg.norm(step)))
        else:  # pragma: no cover - rejected by the parser
            raise ValueError(f"unsupported primitive {self.kind!r}")
        centres = local @ self.transform[:3, :3].T + self.transform[:3, 3]
        return centres, radii


def parse_collisions(urdf_text: str) -> list[CollisionPrimitive]:
    """Every ``<collision>`` primitive of a URDF, link by link in document order.

    Only cylinders, boxes and spheres are read (meshes have no analytic sphere cover).
    """
    prims: list[CollisionPrimitive] = []
    for link in _root(urdf_text).iter("link"):
        for col in link.findall("collision"):
            T = origin_matrix(col.find("origin"))
            geom = col.find("geometry")
            if geom is None or len(geom) != 1:
                raise ValueError(f"urdf: link {link.get('name')!r} has a <collision> without one geometry")
            g = geom[0]
            if g.tag == "cylinder":
                size = (float(g.get("radius")), float(g.get("length")))
            elif g.tag == "box":
                size = tuple(float(v) for v in _floats(g.get("size"), "", 3, f"link {link.get('name')!r} <box size>"))
            elif g.tag == "sphere":
                size = (float(g.get("radius")),)
            else:
                raise ValueError(
                    f"urdf: link {link.get('name')!r}: collision geometry {g.tag!r} is not supported; "
                    f"allowed: {', '.join(PRIMITIVE_KINDS)}"
                )
            if min(size) <= 0:
                raise ValueError(f"urdf: link {link.get('name')!r}: {g.tag} size must be positive, got {size}")
            prims.append(CollisionPrimitive(link.get("name"), g.tag, size, T))
    return prims
