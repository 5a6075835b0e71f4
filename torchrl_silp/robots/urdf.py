"""URDF reading for the robot layer, through yourdfpy: joints, the link tree and collision geometry.

:func:`load_description` parses a robot description with ``yourdfpy`` (transmissions,
``mimic`` and ``continuous`` joints, several ``<collision>`` elements per link and links
without any are all part of the format it reads) and resolves every mesh file,
``package://`` paths included, before anything else is built. What the robot layer keeps
is plain float64 numpy, read once when a robot is built: :class:`UrdfJoint` for each
joint and :class:`CollisionPrimitive` for each collision element (a box, cylinder,
sphere or mesh); the batched torch kinematics live in :mod:`torchrl_silp.robots.base`.

``package://<package>/<path>`` is looked up, in order, in the folders of ``package_dirs``
(a folder that holds ``<package>/``, as Pinocchio's ``package_dirs``; or a mapping from a
package name to its own folder), in those of ``ROS_PACKAGE_PATH``, in the folders above the
URDF file (a description shipped as ``<package>/urdf/robot.urdf``) and in the share folder
of pip's robotics packages (``<site-packages>/cmeel.prefix/share``, where
``example-robot-data`` installs). A relative mesh path is taken from the URDF's folder. The
URDF itself may be named by a ``package://`` path too (:func:`resolve_urdf_path`).

Examples:
    >>> from torchrl_silp.robots.urdf import asset_path, load_description, serial_chain
    >>> desc = load_description(asset_path("ur5e.urdf"))
    >>> [j.name for j in serial_chain(desc.joints, "base_link", "tcp")][:2]
    ['shoulder_pan_joint', 'shoulder_lift_joint']
    >>> prim = desc.collisions[0]
    >>> prim.link, prim.kind, prim.size
    ('base_link', 'cylinder', (0.075, 0.12))
    >>> centres, radii = prim.sphere_cover()
    >>> centres.shape, radii.shape
    ((2, 3), (2,))
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

__all__ = [
    "asset_path",
    "rpy_matrix",
    "UrdfJoint",
    "CollisionPrimitive",
    "RobotDescription",
    "load_description",
    "resolve_package_path",
    "resolve_urdf_path",
    "serial_chain",
]

#: joint types an arm's tree may hold; ``continuous`` is a revolute joint without limits
JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed")
PRIMITIVE_KINDS = ("cylinder", "box", "sphere", "mesh")

PackageDirs = str | os.PathLike | Sequence[str | os.PathLike] | Mapping[str, str | os.PathLike] | None


def asset_path(name: str) -> str:
    """Path of a robot description shipped with the package (``assets/`` installs as ``torchrl_silp.assets``)."""
    return str(resources.files("torchrl_silp.assets") / name)


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


@dataclass(frozen=True)
class UrdfJoint:
    """One ``<joint>`` of a URDF.

    Attributes:
        name: the joint's name.
        type: ``"revolute"``, ``"continuous"``, ``"prismatic"``, ``"fixed"`` (or another URDF type).
        parent, child: the links it connects.
        origin: 4x4 pose (float64) of the child frame in the parent frame at zero angle.
        axis: unit axis in the child frame (URDF's default is x).
        limits: ``(lower, upper)`` of ``<limit>``, or None (a ``continuous`` joint's).
        mimic: ``(joint, multiplier, offset)`` of a ``<mimic>`` element, or None.
    """

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray
    limits: tuple[float, float] | None
    mimic: tuple[str, float, float] | None = None

    @property
    def moves(self) -> bool:
        return self.type in ("revolute", "continuous", "prismatic")


class CollisionPrimitive:
    """One ``<collision>`` element: a cylinder (axis along local z), box, sphere or mesh.

    Attributes:
        link: name of the link it belongs to.
        kind: ``"cylinder"``, ``"box"``, ``"sphere"`` or ``"mesh"``.
        size: cylinder ``(radius, length)``, box ``(x, y, z)``, sphere ``(radius,)``; a mesh's
            ``scale`` ``(sx, sy, sz)``.
        transform: 4x4 pose of the primitive in its link frame (float64 numpy).
        mesh_path: the resolved mesh file (meshes only).

    Examples:
        >>> import numpy as np
        >>> box = CollisionPrimitive("hand", "box", (0.2, 0.1, 0.1), np.eye(4))
        >>> centres, radii = box.sphere_cover()
        >>> len(radii), bool((np.abs(centres).max(0) + radii.max() >= [0.1, 0.05, 0.05]).all())
        (2, True)
    """

    def __init__(self, link: str, kind: str, size: tuple[float, ...], transform: np.ndarray,
                 mesh_path: str | None = None):
        if kind not in PRIMITIVE_KINDS:
            raise ValueError(f"kind must be one of {PRIMITIVE_KINDS}, got {kind!r}")
        self.link, self.kind, self.size, self.transform = link, kind, tuple(float(s) for s in size), transform
        self.mesh_path = mesh_path

    def __repr__(self) -> str:
        where = f", mesh_path={self.mesh_path!r}" if self.mesh_path else ""
        return f"CollisionPrimitive(link={self.link!r}, kind={self.kind!r}, size={self.size}{where})"

    def trimesh(self):
        """The element's surface as a ``trimesh.Trimesh`` in its link frame (scaled and placed)."""
        import trimesh

        if self.kind == "mesh":
            mesh = load_mesh(self.mesh_path, self.size)
        elif self.kind == "box":
            mesh = trimesh.creation.box(extents=self.size)
        elif self.kind == "cylinder":
            mesh = trimesh.creation.cylinder(radius=self.size[0], height=self.size[1], sections=64)
        else:
            mesh = trimesh.creation.icosphere(subdivisions=3, radius=self.size[0])
        return mesh.copy().apply_transform(self.transform)

    def sphere_cover(self, max_spheres: int = 8, volume_ratio: float = 2.5) -> tuple[np.ndarray, np.ndarray]:
        """A conservative sphere cover: every point of the element lies in some sphere.

        Primitives have an analytic cover (every point of the solid); a mesh's is fitted by
        :func:`torchrl_silp.robots.covers.mesh_sphere_cover` (every point of its surface, no
        tolerance: each triangle lies in one sphere) and cached on disk.

        Args:
            max_spheres, volume_ratio: a mesh's bound on spheres and its target of the cover's
                volume over the mesh's (see :func:`~torchrl_silp.robots.covers.mesh_sphere_cover`).

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
        else:
            from torchrl_silp.robots.covers import cached_mesh_cover

            mesh = load_mesh(self.mesh_path, self.size)
            local, radii = cached_mesh_cover(mesh, max_spheres=max_spheres, volume_ratio=volume_ratio)
        centres = local @ self.transform[:3, :3].T + self.transform[:3, 3]
        return centres, radii


def load_mesh(path: str, scale=(1.0, 1.0, 1.0)):
    """A mesh file as one ``trimesh.Trimesh`` (a scene's parts concatenated), scaled; ValueError if unreadable."""
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as err:  # trimesh raises many types for a file it cannot read
        raise ValueError(f"cannot read mesh {path!r}: {err}") from err
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"mesh {path!r} holds no triangles")
    mesh = mesh.copy()
    mesh.apply_scale(np.asarray(scale, dtype=np.float64)) if np.ptp(scale) else mesh.apply_scale(float(scale[0]))
    return mesh


def _package_roots(package_dirs: PackageDirs) -> tuple[dict[str, Path], list[Path]]:
    if package_dirs is None:
        return {}, []
    if isinstance(package_dirs, Mapping):
        return {str(k): Path(v) for k, v in package_dirs.items()}, []
    if isinstance(package_dirs, (str, os.PathLike)):
        package_dirs = [package_dirs]
    return {}, [Path(p) for p in package_dirs]


def resolve_package_path(filename: str, urdf_path: str | os.PathLike | None, package_dirs: PackageDirs = None) -> Path:
    """The file a URDF's ``<mesh filename>`` names (see the module docstring); ValueError naming what was tried.

    Examples:
        >>> import os, tempfile
        >>> root = tempfile.mkdtemp()
        >>> os.makedirs(os.path.join(root, "my_robot", "meshes"))
        >>> open(os.path.join(root, "my_robot", "meshes", "link.stl"), "w").close()
        >>> resolve_package_path("package://my_robot/meshes/link.stl", "/x/robot.urdf", [root]).name
        'link.stl'
    """
    urdf_dir = Path(urdf_path).resolve().parent if urdf_path is not None else None
    if filename.startswith("file://"):
        filename = filename[len("file://"):]
    if not filename.startswith("package://"):
        path = Path(filename) if os.path.isabs(filename) or urdf_dir is None else urdf_dir / filename
        if path.is_file():
            return path
        raise ValueError(f"mesh file {filename!r} not found (looked for {str(path)!r})")
    package, _, rest = filename[len("package://"):].partition("/")
    by_name, parents = _package_roots(package_dirs)
    candidates = []
    if package in by_name:
        candidates.append(by_name[package] / rest)
    ros = [Path(p) for p in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if p]
    near = [*urdf_dir.parents, urdf_dir] if urdf_dir is not None else []
    for parent in [*parents, *ros, *near, *_cmeel_shares()]:
        candidates.append(parent / package / rest)
        if parent.name == package:
            candidates.append(parent / rest)
    for path in candidates:
        if path.is_file():
            return path
    raise ValueError(
        f"mesh {filename!r} not found: package {package!r} is in none of package_dirs "
        f"{[str(p) for p in [*by_name.values(), *parents]] or 'None'}, ROS_PACKAGE_PATH or the folders above the URDF"
    )


def _cmeel_shares() -> list[Path]:
    import site
    import sys

    folders = [*site.getsitepackages(), site.getusersitepackages(), *sys.path]
    return [Path(f) / "cmeel.prefix" / "share" for f in dict.fromkeys(folders) if f and (Path(f) / "cmeel.prefix").is_dir()]


def resolve_urdf_path(urdf_path: str | os.PathLike, package_dirs: PackageDirs = None) -> str:
    """A URDF file's path: the path itself, or the file a ``package://`` path names (ValueError naming ``urdf_path``).

    Examples:
        >>> resolve_urdf_path(asset_path("ur5e.urdf")) == asset_path("ur5e.urdf")
        True
    """
    path = os.fspath(urdf_path)
    if not path.startswith("package://"):
        return path
    try:
        return str(resolve_package_path(path, None, package_dirs))
    except ValueError as err:
        raise ValueError(f"urdf_path: {err}") from err


@dataclass
class RobotDescription:
    """What the robot layer reads of a URDF.

    Attributes:
        path: the URDF file.
        name: the ``<robot name>``.
        root: the root link of the link tree.
        links: every link's name, in document order.
        joints: every kinematic joint (transmissions are not joints), in document order.
        collisions: every ``<collision>`` element, link by link in document order; meshes resolved.
    """

    path: str
    name: str
    root: str
    links: list[str]
    joints: list[UrdfJoint]
    collisions: list[CollisionPrimitive]


def load_description(urdf_path: str | os.PathLike, package_dirs: PackageDirs = None) -> RobotDescription:
    """Read a URDF through yourdfpy and resolve its collision meshes.

    Every error is a ValueError whose message starts with the parameter to fix: ``urdf_path:``
    (a file that cannot be read, is not a URDF or has no link) or ``package_dirs:`` (a mesh that
    cannot be found).
    """
    import yourdfpy

    path = resolve_urdf_path(urdf_path, package_dirs)
    if not os.path.isfile(path):
        raise ValueError(f"urdf_path: no such file {path!r}")
    # yourdfpy logs what it cannot resolve and goes on; every mesh is resolved (or refused) below
    logging.getLogger("yourdfpy").setLevel(logging.CRITICAL)
    try:
        urdf = yourdfpy.URDF.load(path, build_scene_graph=False, build_collision_scene_graph=False,
                                  load_meshes=False, load_collision_meshes=False)
        robot = urdf.robot
    except Exception as err:  # lxml and yourdfpy raise many types for a file that is not a URDF
        raise ValueError(f"urdf_path: {path!r} is not a URDF: {type(err).__name__}: {err}") from err
    if not robot.links:
        raise ValueError(f"urdf_path: {path!r} is not a robot description: its <robot> holds no <link>")
    joints = []
    for j in robot.joints:
        axis = np.asarray(j.axis if j.axis is not None else (1.0, 0.0, 0.0), dtype=np.float64)
        norm = float(np.linalg.norm(axis))
        if j.type in ("revolute", "continuous", "prismatic") and norm < 1e-9:
            raise ValueError(f"urdf_path: {path!r}: joint {j.name!r} has a zero <axis>")
        limits = None
        if j.type != "continuous" and j.limit is not None and j.limit.lower is not None and j.limit.upper is not None:
            limits = (float(j.limit.lower), float(j.limit.upper))
        mimic = None
        if j.mimic is not None:
            mimic = (j.mimic.joint, float(j.mimic.multiplier if j.mimic.multiplier is not None else 1.0),
                     float(j.mimic.offset if j.mimic.offset is not None else 0.0))
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
        joints.append(UrdfJoint(j.name, j.type, j.parent, j.child, origin, axis / norm if norm > 0 else axis,
                                limits, mimic))
    collisions = []
    for link in robot.links:
        for col in link.collisions:
            T = np.eye(4) if col.origin is None else np.asarray(col.origin, dtype=np.float64)
            g = col.geometry
            where = f"urdf_path: {path!r}: link {link.name!r}"
            if g is None:
                raise ValueError(f"{where} has a <collision> without a geometry")
            if g.box is not None:
                kind, size = "box", tuple(float(v) for v in np.asarray(g.box.size).reshape(-1))
            elif g.cylinder is not None:
                kind, size = "cylinder", (float(g.cylinder.radius), float(g.cylinder.length))
            elif g.sphere is not None:
                kind, size = "sphere", (float(g.sphere.radius),)
            elif g.mesh is not None:
                scale = g.mesh.scale if g.mesh.scale is not None else 1.0
                kind, size = "mesh", tuple(float(s) for s in np.broadcast_to(np.asarray(scale, dtype=float), (3,)))
            else:
                raise ValueError(f"{where} has a <collision> geometry of no known kind; allowed: {PRIMITIVE_KINDS}")
            if min(size) <= 0:
                raise ValueError(f"{where}: {kind} size must be positive, got {size}")
            mesh_path = None
            if kind == "mesh":
                try:
                    mesh_path = str(resolve_package_path(g.mesh.filename, path, package_dirs))
                except ValueError as err:
                    raise ValueError(f"package_dirs: link {link.name!r} of {path!r}: {err}") from err
            collisions.append(CollisionPrimitive(link.name, kind, size, T, mesh_path))
    links = [link.name for link in robot.links]
    children = {j.child for j in joints}
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise ValueError(f"urdf_path: {path!r}: the links form no single tree (links without a parent joint: {roots})")
    return RobotDescription(path, robot.name, roots[0], links, joints, collisions)


def serial_chain(joints: list[UrdfJoint], root: str, tip: str) -> list[UrdfJoint]:
    """The joints from link ``root`` to link ``tip``, root first; a ValueError when no such path exists.

    Every joint on the path must be ``revolute``, ``continuous``, ``prismatic`` or ``fixed``.
    """
    by_child = {}
    for j in joints:
        if j.child in by_child:
            raise ValueError(f"urdf: link {j.child!r} is the child of two joints")
        by_child[j.child] = j
    path, link = [], tip
    while link != root:
        if link not in by_child:
            where = "is not a link of the URDF" if link == tip and not path else f"is reached from {tip!r} but not from {root!r}"
            raise ValueError(f"urdf: link {link!r} {where}")
        j = by_child[link]
        if j.type not in JOINT_TYPES:
            raise ValueError(f"urdf: joint {j.name!r} has type {j.type!r}; allowed: {', '.join(JOINT_TYPES)}")
        path.append(j)
        link = j.parent
        if len(path) > len(joints):  # pragma: no cover - a loop, which the child check above rules out
            raise ValueError("urdf: the joints form a loop")
    return path[::-1]
