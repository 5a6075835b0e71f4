"""The arm-kinematics interface and the one batched forward-kinematics engine every arm runs on.

:class:`ArmKinematics` reads a URDF once (:mod:`torchrl_silp.robots.urdf`, through
yourdfpy) and turns the serial chain from its root to the TCP's link, and every link
hanging off it (held joints), into flat tables, as pytorch-kinematics'
``Chain.__init__`` does, so no Python tree walk runs per call:

- the effective origin ``E_k`` of every *moving* joint (``(K, 4, 4)``): the
  fixed frames since the previous moving joint and the joint's own origin,
  with the joint axis turned onto local ``z``;
- a linear map from the configuration ``q`` ``(D,)`` to the moving joints'
  angles, ``theta = A q + b``: a coupled joint (the UR5e's wrist_1) is a row
  of ``A``; a joint whose row is zero is locked at ``b`` and folded into the
  static origins at construction;
- point and frame maps: every collision-sphere centre, the TCP and every
  frame is a constant linear function of the moving bodies' poses.

The hot path (:func:`chain_bodies`, :func:`apply_map`) holds each body pose
column-major, as the four columns of ``[R | p]``, each a ``(3, N)`` block
with the batch innermost. ``T_{k-1} @ E_k`` is then one ``(4, 4) @ (4, 3N)``
matrix product over the whole batch, ``@ Rz(theta_k)`` mixes two columns in
closed form, and the sphere centres are one more product with the point map.
The centres come out coordinate-major, ``(3, N, S + 1)``: one ``(N, S + 1)``
block per coordinate, the spheres innermost, so that the collision kernels of
:mod:`torchrl_silp.models` reduce over a sample's spheres (and sphere pairs)
in contiguous memory.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import torch
from torch import nn

from torchrl_silp.robots.urdf import CollisionPrimitive, load_description, serial_chain

__all__ = ["ArmKinematics", "chain_bodies", "apply_map"]


# --------------------------------------------------------------- the engine
def chain_bodies(origins_t: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Poses of the root and the moving bodies of a serial chain of z-axis revolute joints, column-major.

    Body 0 is the root, the identity; body ``k + 1`` is ``T_{k+1} = T_k @ E_k @ Rz(theta_k)``.

    Args:
        origins_t: the transposed effective origins ``E_k^T``, ``(K, 4, 4)``.
        cos, sin: cosines and sines of the joint angles, ``(K, N)``.

    Returns:
        ``(K + 1, 4, 3, N)``: for body ``k`` and column ``c`` of its ``[R | p]``, the column's
        three rows over the batch.

    Examples:
        >>> import math, torch
        >>> E = torch.eye(4).expand(2, 4, 4)  # two joints on one axis
        >>> theta = torch.tensor([[0.3], [0.4]])
        >>> X = chain_bodies(E.transpose(1, 2), theta.cos(), theta.sin())
        >>> round(float(X[2, 0, 0, 0]), 6) == round(math.cos(0.7), 6)  # R[0, 0] after the second joint
        True
    """
    n = cos.shape[-1]
    # the root is a body of the stack, so that points riding on it are rows of the one
    # product in apply_map too (a bias added after it would be fused into, and recomputed
    # by, every loop of a compiled caller that reads the points)
    out = [torch.eye(4, 3, dtype=cos.dtype, device=cos.device).unsqueeze(-1).expand(4, 3, n)]
    # T_root @ E_0 is E_0 for every sample: the first moving body needs no product
    M = origins_t[0, :, :3].unsqueeze(-1).expand(4, 3, n)
    for k in range(origins_t.shape[0]):
        if k:
            M = (origins_t[k] @ out[-1].reshape(4, 3 * n)).view(4, 3, n)
        c, s = cos[k], sin[k]
        # @ Rz(theta): column 0 becomes c col0 + s col1, column 1 becomes c col1 - s col0
        out.append(torch.stack([M[0] * c + M[1] * s, M[1] * c - M[0] * s, M[2], M[3]]))
    return torch.stack(out)


def apply_map(bodies: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Points (or frame columns) that are constant linear functions of the body poses.

    Args:
        bodies: ``(B, 4, 3, N)`` from :func:`chain_bodies`.
        weights: ``(R, 4B)``: row ``r`` weighs column ``c`` of body ``b`` by ``weights[r, 4b + c]``.

    Returns:
        ``(3, N, R)``: coordinate-major, the points (rows of ``weights``) innermost.
    """
    k, _, _, n = bodies.shape
    # one (3N, 4K) @ (4K, R) product; both operands are transposed views, which BLAS reads as they are
    return (bodies.reshape(4 * k, 3 * n).T @ weights.T).view(3, n, weights.shape[0])


def _axis_alignment(axis: np.ndarray) -> np.ndarray:
    # a rotation A with A e_z = axis, so Rot(axis, q) = A Rz(q) A^T
    z = np.array([0.0, 0.0, 1.0])
    A = np.eye(4)
    c = float(np.dot(z, axis))
    if c > 1 - 1e-12:
        return A
    if c < -1 + 1e-12:
        A[:3, :3] = np.diag([1.0, -1.0, -1.0])
        return A
    v = np.cross(z, axis)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    A[:3, :3] = np.eye(3) + K + K @ K / (1 + c)
    return A


def _rz(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _index_of(indices: Sequence[int]) -> slice | list[int]:
    """A ``slice`` equal to a run of consecutive indices (a view, not a gather), else the list itself."""
    indices = list(indices)
    if indices and indices == list(range(indices[0], indices[-1] + 1)):
        return slice(indices[0], indices[-1] + 1)
    return indices


# ---------------------------------------------------------------- the arm
def _translation(v: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = v
    return T


def _held_transform(j, value: float) -> np.ndarray:
    """The child frame of joint ``j`` in its parent's, the joint held at ``value``."""
    if j.type == "fixed":
        return j.origin
    if j.type == "prismatic":
        return j.origin @ _translation(value * j.axis)
    align = _axis_alignment(j.axis)
    return j.origin @ align @ _rz(value) @ align.T


class ArmKinematics(nn.Module):
    """A robot arm from a URDF: TCP and frame kinematics and a collision-sphere cover, batched.

    Every method takes configurations with any leading batch dims ``(..., D)``
    (``D = config_dim``, the joints of :attr:`joint_names`) on the module's
    device and is differentiable. Constants are buffers, so ``.to(device)`` and
    ``.to(dtype)`` move them.

    The URDF is read by :func:`~torchrl_silp.robots.urdf.load_description` (yourdfpy). The
    configuration joints and the joints coupled to them (``coupled``, and ``mimic`` joints
    of either) must lie on the chain from ``root`` to ``tcp_link``; every other movable
    joint of the tree below ``root`` (a wrist not in the configuration, the fingers, a
    prismatic joint) is held at ``held[name]`` (default: 0 clipped into its limits), so
    each link rides rigidly on one moving body.

    What tasks and pictures read:

    - kinematics: :meth:`fk` (TCP position), :meth:`tcp_pose`, :meth:`frames`
      (every frame of :attr:`frame_names`: the chain's links root first, the links off the
      chain, then :attr:`tcp_frame` when it is not a link), :meth:`full_joints` (the angles of all moving chain joints,
      :attr:`chain_joint_names`);
    - joints: :attr:`joint_names`, :attr:`joint_low`, :attr:`joint_high` (URDF limits);
    - the sphere cover of the URDF's ``<collision>`` elements (:attr:`primitives`):
      sphere ``i`` rides on frame ``frame_names[sphere_frame[i]]`` at ``sphere_local[i]``
      with radius ``sphere_radii[i]``, covering primitive ``sphere_primitive[i]`` of link
      ``sphere_link_names[i]``; :meth:`spheres_and_tcp`, :meth:`link_spheres`,
      :meth:`cover_report`; a mesh's cover is fitted (:mod:`torchrl_silp.robots.covers`);
    - the table test: :attr:`table_mask` (spheres checked against ``z = 0``: all but
      those of :attr:`table_links`), :attr:`table_index` (the same as a slice or list);
    - the self test: sphere pairs :attr:`self_pair_a` < :attr:`self_pair_b`; they lie in
      one block of the sphere-distance matrix, rows :attr:`self_rows` by columns
      :attr:`self_cols`, whose :attr:`self_reach` holds the radius sum of a checked pair and
      ``-1`` elsewhere; :meth:`self_collision`, :meth:`self_clearance`;
    - the hot-path form: :meth:`joint_trig` then :meth:`cover_points_from_trig` (or
      :meth:`cover_points`) give every sphere centre and the TCP coordinate-major;
    - :attr:`urdf_path`, :attr:`package_dirs`, and :meth:`reference_fk` through
      pytorch-kinematics (for checks).

    Subclasses (:class:`~torchrl_silp.robots.URDFArm`) choose the self pairs
    (:meth:`_set_self_pairs`) and the table links.

    Args:
        urdf_path: the URDF file.
        root: the chain's root link (the world frame); default: the URDF's root link.
        config_joints: the revolute chain joints the configuration holds, in its order.
        tcp_link: the link the TCP rides on; default :attr:`TCP_FRAME`.
        tcp_offset: the TCP in ``tcp_link``'s frame (m).
        coupled: revolute chain joints as ``name: (coefficients, offset)``, the angle
            ``coefficients . q + offset``; all-zero coefficients lock it at ``offset``.
        held: the value (rad or m) of movable joints that are neither configured nor coupled.
        package_dirs: where ``package://`` meshes are found (:mod:`torchrl_silp.robots.urdf`).
        max_spheres_per_link, cover_volume_ratio: a mesh's cover (:func:`~torchrl_silp.robots.covers.mesh_sphere_cover`).
        device, dtype: of the constant tensors (float32 default; float64 for tests).
    """

    #: the default TCP link, and the name of the TCP frame added when the TCP is another link or offset
    #: (:attr:`tcp_frame` is the TCP's frame)
    TCP_FRAME = "tcp"
    #: links standing on the table: their spheres are not checked against the plane z = 0
    TABLE_LINKS: tuple[str, ...] = ()
    #: links drawn as the end effector in pictures
    END_EFFECTOR_LINKS: tuple[str, ...] = ()
    #: a collision-free configuration: self pairs whose spheres overlap there are dropped (None: no check)
    HOME: tuple[float, ...] | None = None
    #: the configuration's name in error messages
    CONFIG_NAME = "q"

    def __init__(
        self,
        urdf_path: str | os.PathLike,
        *,
        root: str | None = None,
        config_joints: Sequence[str],
        tcp_link: str | None = None,
        tcp_offset: Sequence[float] = (0.0, 0.0, 0.0),
        coupled: Mapping[str, tuple[Sequence[float], float]] | None = None,
        held: Mapping[str, float] | None = None,
        package_dirs=None,
        max_spheres_per_link: int = 8,
        cover_volume_ratio: float = 2.5,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        super().__init__()
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        desc = load_description(urdf_path, package_dirs)
        path = desc.path
        self.urdf_path, self.package_dirs, self.description = path, package_dirs, desc
        self._reference_chain = None  # pytorch-kinematics' chain, built on first use by reference_fk
        root = desc.root if root is None else root
        tcp_link = self.TCP_FRAME if tcp_link is None else tcp_link
        for key, link in (("root", root), ("ee_link", tcp_link)):
            if link not in desc.links:
                raise ValueError(f"{key}: no link {link!r} in urdf_path {path!r}; its links: {desc.links}")
        tcp_offset = np.asarray(tcp_offset, dtype=np.float64)
        if tcp_offset.shape != (3,) or not np.isfinite(tcp_offset).all():
            raise ValueError(f"ee_offset must be 3 finite numbers (m), got {tcp_offset.tolist()}")
        virtual_tcp = tcp_link != self.TCP_FRAME or bool(tcp_offset.any())
        # the TCP's frame: the link itself, or a frame added after the links ("tcp", unless a link has that name)
        self.tcp_frame = tcp_link if not virtual_tcp else (
            self.TCP_FRAME if self.TCP_FRAME not in desc.links else f"{tcp_link}_tcp")
        try:
            chain = serial_chain(desc.joints, root, tcp_link)
        except ValueError as err:
            raise ValueError(f"ee_link: {path!r}: {err}") from err
        self.tcp_link, self.tcp_offset = tcp_link, tuple(tcp_offset.tolist())

        by_name = {j.name: j for j in desc.joints}
        config_joints, coupled, held = tuple(config_joints), dict(coupled or {}), dict(held or {})
        moving = [j for j in chain if j.moves]
        chain_names = [j.name for j in moving]
        for name in (*config_joints, *coupled):
            if name not in by_name:
                raise ValueError(f"joints: {path!r} has no joint {name!r}; its movable joints: "
                                 f"{[j.name for j in desc.joints if j.moves]}")
            if name not in chain_names:
                raise ValueError(f"joints: joint {name!r} is not on the chain from {root!r} to {tcp_link!r}, "
                                 f"whose movable joints are {chain_names}")
            if by_name[name].type == "prismatic":
                raise ValueError(f"joints: joint {name!r} is prismatic; the configuration holds revolute joints")
        if len(set(config_joints)) != len(config_joints) or set(config_joints) & set(coupled):
            raise ValueError(f"joints: each joint may be named once, got {list(config_joints)} and coupled {list(coupled)}")
        unknown = sorted(set(held) - {j.name for j in desc.joints if j.moves})
        if unknown:
            raise ValueError(f"held: {path!r} has no movable joints {unknown}")
        d = len(config_joints)
        if d == 0:
            raise ValueError("joints: the configuration needs at least one joint")

        def row(j, seen=()):
            """The joint's angle as (coefficients over q, offset); zero coefficients: held."""
            if j.name in config_joints:
                return np.eye(d)[config_joints.index(j.name)], 0.0
            if j.name in coupled:
                coeffs, offset = coupled[j.name]
                if len(coeffs) != d:
                    raise ValueError(f"coupled: joint {j.name!r} needs {d} coefficients, got {len(coeffs)}")
                return np.asarray(coeffs, dtype=np.float64), float(offset)
            if j.name in held:
                return np.zeros(d), float(held[j.name])
            if j.mimic is not None and j.mimic[0] in by_name and j.name not in seen:
                coeffs, offset = row(by_name[j.mimic[0]], (*seen, j.name))
                return j.mimic[1] * coeffs, j.mimic[1] * offset + j.mimic[2]
            lo, hi = j.limits if j.limits is not None else (0.0, 0.0)
            return np.zeros(d), float(np.clip(0.0, lo, hi))

        jmap, joff = np.zeros((len(moving), d)), np.zeros(len(moving))
        for i, j in enumerate(moving):
            jmap[i], joff[i] = row(j)
            if jmap[i].any() and j.type == "prismatic":
                raise ValueError(f"joints: prismatic joint {j.name!r} cannot follow the configuration")
        self.chain_joint_names = tuple(chain_names)
        self.joint_names = config_joints
        limits = {j.name: j.limits for j in moving}
        missing = [n for n in config_joints if limits[n] is None]
        if missing:
            raise ValueError(f"joints: {path!r}: joints {missing} have no <limit lower upper> (continuous joints)")

        # Walk the chain once. A body is the root or the child of a moving joint; every
        # frame is a constant offset from its body, and a moving joint's effective origin
        # absorbs the fixed frames (and held joints) since the previous body.
        frame_names, frame_body, frame_offset, frame_depth = [root], [0], [np.eye(4)], [0]
        origins, moving_rows = [], []
        pending, depth = np.eye(4), 0
        for j in chain:
            if j.moves:
                i = chain_names.index(j.name)
                depth += 1
                if jmap[i].any():
                    align = _axis_alignment(j.axis)
                    origins.append(pending @ j.origin @ align)
                    moving_rows.append(i)
                    pending = align.T.copy()
                else:
                    pending = pending @ _held_transform(j, joff[i])
            else:
                pending = pending @ j.origin
            frame_names.append(j.child)
            frame_body.append(len(origins))
            frame_offset.append(pending.copy())
            frame_depth.append(depth)
        if not origins:
            raise ValueError(f"joints: no joint between {root!r} and {tcp_link!r} moves")
        # The links off the chain (a hand's fingers, a camera mount) ride on the body of
        # their parent, every movable joint among them held.
        children: dict[str, list] = {}
        for j in desc.joints:
            children.setdefault(j.parent, []).append(j)
        queue = list(frame_names)
        while queue:
            parent = queue.pop(0)
            f = frame_names.index(parent)
            for j in children.get(parent, []):
                if j.child in frame_names:
                    continue
                if j.type not in ("revolute", "continuous", "prismatic", "fixed"):
                    raise ValueError(f"urdf_path: {path!r}: joint {j.name!r} of type {j.type!r} below {root!r}; "
                                     "allowed: revolute, continuous, prismatic, fixed")
                if j.moves:
                    coeffs, value = row(j)
                    if coeffs.any():
                        raise ValueError(f"joints: joint {j.name!r} follows the configuration but is not on the "
                                         f"chain from {root!r} to {tcp_link!r}")
                    T = _held_transform(j, value)
                else:
                    T = j.origin
                frame_names.append(j.child)
                frame_body.append(frame_body[f])
                frame_offset.append(frame_offset[f] @ T)
                frame_depth.append(frame_depth[f])
                queue.append(j.child)
        if virtual_tcp:
            f = frame_names.index(tcp_link)
            frame_names.append(self.tcp_frame)
            frame_body.append(frame_body[f])
            frame_offset.append(frame_offset[f] @ _translation(tcp_offset))
            frame_depth.append(frame_depth[f])
        self.frame_names = frame_names
        self.frame_depth = frame_depth  # moving joints between the root and each frame
        self.frame_body = frame_body  # the moving body each frame rides on (0: the root)
        n_moving = len(origins)

        f64 = dict(dtype=torch.float64)
        tables: dict[str, torch.Tensor] = {
            "joint_low": torch.tensor([limits[n][0] for n in config_joints], **f64),
            "joint_high": torch.tensor([limits[n][1] for n in config_joints], **f64),
            "_moving_map": torch.tensor(jmap[moving_rows], **f64),  # (K, D)
            "_moving_offset": torch.tensor(joff[moving_rows], **f64),  # (K,)
            "_joint_map": torch.tensor(jmap, **f64),  # (J, D)
            "_joint_offset": torch.tensor(joff, **f64),  # (J,)
            "_origins_t": torch.tensor(np.stack(origins).transpose(0, 2, 1).copy(), **f64),  # (K, 4, 4)
        }

        # frame f = body(f) @ offset(f): column c of the frame weighs column l of the body by offset[l, c]
        n_frames, n_bodies = len(frame_names), n_moving + 1
        W = np.zeros((n_frames, 4, n_bodies, 4))
        for f, (b, off) in enumerate(zip(frame_body, frame_offset)):
            W[f, :, b, :] = off.T
        tables["_frame_map"] = torch.tensor(W.reshape(4 * n_frames, 4 * n_bodies), **f64)

        # The sphere cover, in frame order (a link's spheres together, the root's first).
        # Geometry on links above the root (a world or pedestal link) does not move with the arm.
        prims = [p for p in desc.collisions if p.link in frame_names]
        self.ignored_links = sorted({p.link for p in desc.collisions} - set(frame_names))
        if not prims:
            raise ValueError(f"urdf_path: {path!r} has no <collision> geometry below {root!r}")
        prims = sorted(prims, key=lambda p: frame_names.index(p.link))
        self.primitives: list[CollisionPrimitive] = prims
        local, radii, sframe, sprim = [], [], [], []
        for k, prim in enumerate(prims):
            try:
                c, r = prim.sphere_cover(max_spheres_per_link, cover_volume_ratio)
            except ValueError as err:
                raise ValueError(f"urdf_path: {path!r}: link {prim.link!r}: {err}") from err
            local.append(c)
            radii.append(r)
            sframe += [frame_names.index(prim.link)] * len(r)
            sprim += [k] * len(r)
        local, radii = np.concatenate(local), np.concatenate(radii)
        self.sphere_link_names = [frame_names[f] for f in sframe]
        # the points: every sphere centre, then the TCP, in the frame of their body
        tcp = frame_names.index(self.tcp_frame)
        points = [(sframe[i], np.append(local[i], 1.0)) for i in range(len(radii))] + [(tcp, np.eye(4)[:, 3])]
        P = np.zeros((len(points), n_bodies, 4))
        for i, (f, h) in enumerate(points):
            P[i, frame_body[f]] = frame_offset[f] @ h
        tables["_point_map"] = torch.tensor(P.reshape(len(points), 4 * n_bodies), **f64)
        tables["sphere_radii"] = torch.tensor(radii, **f64)
        tables["sphere_local"] = torch.tensor(local, **f64)
        for name, value in tables.items():
            self.register_buffer(name, value.to(device=device, dtype=dtype), persistent=not name.startswith("_"))
        self.register_buffer("sphere_frame", torch.tensor(sframe, dtype=torch.long, device=device))
        self.register_buffer("sphere_primitive", torch.tensor(sprim, dtype=torch.long, device=device))
        self._tables64 = tables  # float64 copies for construction-time checks (self pairs at HOME)
        self._set_table_links(self.TABLE_LINKS)
        self._set_self_pairs([])

    def _set_table_links(self, links: Iterable[str]) -> None:
        """Exempt the spheres of ``links`` (which stand on the table) from the table test."""
        self.table_links = tuple(links)
        unknown = sorted(set(self.table_links) - set(self.frame_names))
        if unknown:
            raise ValueError(f"table_links: unknown links {unknown}; allowed: {self.frame_names}")
        table = [n not in self.table_links for n in self.sphere_link_names]
        self.register_buffer("table_mask", torch.tensor(table, device=self.sphere_radii.device))
        self.table_index = _index_of(np.flatnonzero(table).tolist())

    # ------------------------------------------------------------ self pairs
    def _set_self_pairs(self, link_pairs: Iterable[tuple[str, str]]) -> None:
        """Check every sphere of link ``x`` against every sphere of link ``y``, for ``(x, y)`` in ``link_pairs``.

        Pairs whose spheres already overlap at :attr:`HOME` are dropped (listed in
        :attr:`home_overlap_pairs`): there they are artefacts of the conservative cover.
        """
        wanted = {frozenset(p) for p in link_pairs}
        unknown = sorted({n for p in wanted for n in p} - set(self.frame_names))
        if unknown:
            raise ValueError(f"self_collision_links: unknown links {unknown}; allowed: {self.frame_names}")
        names = self.sphere_link_names
        a, b = np.triu_indices(len(names), k=1)
        keep = np.array([names[i] != names[j] and frozenset((names[i], names[j])) in wanted for i, j in zip(a, b)],
                        dtype=bool)
        a, b = a[keep], b[keep]
        radii = self._tables64["sphere_radii"].numpy()
        self.home_overlap_pairs: list[tuple[str, str]] = []
        if self.HOME is not None and len(a):
            t = self._tables64
            q = torch.tensor(self.HOME, dtype=torch.float64).unsqueeze(-1)  # (D, 1)
            theta = t["_moving_map"] @ q + t["_moving_offset"].unsqueeze(-1)
            pts = apply_map(chain_bodies(t["_origins_t"], theta.cos(), theta.sin()), t["_point_map"])
            home = pts[:, 0, :-1].T.numpy()
            apart = np.linalg.norm(home[a] - home[b], axis=-1) >= radii[a] + radii[b]
            self.home_overlap_pairs = [(names[i], names[j]) for i, j in zip(a[~apart], b[~apart])]
            a, b = a[apart], b[apart]
        device, dtype = self.sphere_radii.device, self.sphere_radii.dtype
        self.register_buffer("self_pair_a", torch.tensor(a, dtype=torch.long, device=device))
        self.register_buffer("self_pair_b", torch.tensor(b, dtype=torch.long, device=device))
        # rows b (the distal spheres) by columns a (the proximal ones): contiguous slices of
        # the chain-ordered spheres, so the hot path takes a view of that block
        lo, hi = (int(b.min()), int(a.max()) + 1) if len(a) else (len(radii), 0)
        self.self_rows, self.self_cols = slice(lo, len(radii)), slice(0, hi)
        reach = np.full((len(radii) - lo, hi), -1.0)
        reach[b - lo, a] = radii[a] + radii[b]
        self.register_buffer("self_reach", torch.tensor(reach, dtype=dtype, device=device), persistent=False)

    # ------------------------------------------------------------ basics
    @property
    def dtype(self) -> torch.dtype:
        return self.joint_low.dtype

    @property
    def device(self) -> torch.device:
        return self.joint_low.device

    @property
    def config_dim(self) -> int:
        """Joints of the configuration (``len(joint_names)``)."""
        return len(self.joint_names)

    @property
    def n_spheres(self) -> int:
        return self.sphere_radii.shape[0]

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_tables64", None)  # construction only
        return state

    def _check_q(self, q, name: str | None = None) -> None:
        name = name or self.CONFIG_NAME
        d = self.config_dim
        if not isinstance(q, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor of shape (..., {d}), got {type(q).__name__}")
        if not q.is_floating_point():
            raise TypeError(f"{name} must be a floating tensor, got {q.dtype}")
        if q.shape[-1:] != (d,):
            raise ValueError(f"{name} must have shape (..., {d}) (the joints {list(self.joint_names)}), "
                             f"got {tuple(q.shape)}")

    def _flat(self, q: torch.Tensor) -> torch.Tensor:
        self._check_q(q)
        return q.reshape(-1, self.config_dim).to(self.dtype)

    # ------------------------------------------------------------ joints
    def full_joints(self, q: torch.Tensor) -> torch.Tensor:
        """The angles ``(..., J)`` of every revolute chain joint (:attr:`chain_joint_names`) at ``q``."""
        flat = self._flat(q)
        full = torch.addmm(self._joint_offset, flat, self._joint_map.T)
        return full.reshape(*q.shape[:-1], len(self.chain_joint_names))

    def joint_trig(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Cosines and sines ``(K, N)`` of the moving joints' angles at ``q``, flattened over the batch.

        The first half of :meth:`cover_points`; a ``torch.compile``'d caller computes them
        outside its graph, where ATen's vectorised kernels evaluate them once (traced, inductor's
        CPU code evaluates them element by element and again in every loop that reads them).
        """
        theta = torch.addmm(self._moving_offset.unsqueeze(-1), self._moving_map, self._flat(q).T)
        return theta.cos(), theta.sin()

    def _bodies(self, q: torch.Tensor) -> torch.Tensor:
        return chain_bodies(self._origins_t, *self.joint_trig(q))

    # ------------------------------------------------------------ kinematics
    def cover_points_from_trig(self, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        """:meth:`cover_points` from the moving joints' cosines and sines ``(K, N)`` (:meth:`joint_trig`)."""
        k = self._origins_t.shape[0]
        if cos.dim() != 2 or cos.shape[0] != k or sin.shape != cos.shape:
            raise ValueError(f"cos and sin must both have shape ({k}, N), got {tuple(cos.shape)} and {tuple(sin.shape)}")
        return apply_map(chain_bodies(self._origins_t, cos, sin), self._point_map)

    def cover_points(self, q: torch.Tensor) -> torch.Tensor:
        """Every sphere centre and then the TCP, coordinate-major: ``(3, N, S + 1)``, ``N`` the flattened batch.

        ``points[:, n, i]`` is sphere ``i``'s centre in sample ``n`` for ``i < S``, and the TCP for
        ``i = S``; one coordinate of every sphere, ``points[0, :, :S]``, is an ``(N, S)`` block.
        """
        return apply_map(self._bodies(q), self._point_map)

    def spheres_and_tcp(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Sphere centres ``(..., S, 3)`` and TCP position ``(..., 3)`` from one FK pass.

        Both are views of :meth:`cover_points` (coordinate-major in memory): call
        ``.contiguous()`` before ``.view()``.
        """
        pts = self.cover_points(q).permute(1, 2, 0)  # (N, S + 1, 3)
        batch = q.shape[:-1]
        return pts[:, :-1].reshape(*batch, self.n_spheres, 3), pts[:, -1].reshape(*batch, 3)

    def link_spheres(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Centres ``(..., S, 3)`` and radii ``(S,)`` of the collision-sphere cover."""
        centres, _ = self.spheres_and_tcp(q)
        return centres, self.sphere_radii

    def fk(self, q: torch.Tensor) -> torch.Tensor:
        """TCP position ``(..., 3)`` in the root frame (metres)."""
        tcp = apply_map(self._bodies(q), self._point_map[-1:])  # (3, N, 1)
        return tcp[..., 0].T.reshape(*q.shape[:-1], 3)

    def _frames(self, q: torch.Tensor, rows: slice) -> tuple[torch.Tensor, torch.Tensor]:
        cols = apply_map(self._bodies(q), self._frame_map[rows])  # (3, N, 4F)
        f = cols.shape[-1] // 4
        T = cols.view(3, cols.shape[1], f, 4).permute(1, 2, 0, 3)  # (N, F, row, column)
        T = T.reshape(*q.shape[:-1], f, 3, 4)
        return T[..., :3], T[..., 3]

    def frames(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World poses of every frame (:attr:`frame_names`) at ``q``.

        Returns:
            rotations ``(..., F, 3, 3)`` and positions ``(..., F, 3)``.
        """
        return self._frames(q, slice(None))

    def tcp_pose(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotation ``(..., 3, 3)`` and position ``(..., 3)`` of the tcp frame."""
        f = self.frame_names.index(self.tcp_frame)
        rot, pos = self._frames(q, slice(4 * f, 4 * f + 4))
        return rot[..., 0, :, :], pos[..., 0, :]

    # ------------------------------------------------------------ self test
    def _self_block(self, centres: torch.Tensor) -> tuple[tuple, torch.Tensor]:
        if not isinstance(centres, torch.Tensor):
            raise TypeError(f"centres must be a torch.Tensor, got {type(centres).__name__}")
        if centres.shape[-2:] != (self.n_spheres, 3):
            raise ValueError(f"centres must have shape (..., {self.n_spheres}, 3), got {tuple(centres.shape)}")
        batch = centres.shape[:-2]
        c = centres.reshape(math.prod(batch), self.n_spheres, 3).to(self.dtype)
        if self.self_pair_a.numel() == 0:
            return batch, c.new_zeros(c.shape[0], 0)
        # (N, rows, columns) distances of the block; cdist's matrix product keeps the
        # (N, rows, columns, 3) differences out of memory
        return batch, torch.cdist(c[:, self.self_rows].contiguous(), c[:, self.self_cols].contiguous())

    def self_collision(self, centres: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
        """Whether a checked sphere pair overlaps (their spheres inflated by ``margin`` together), bool ``(...)``.

        Args:
            centres: sphere centres ``(..., S, 3)`` (:meth:`spheres_and_tcp`).
            margin: added to every pair's radius sum (m). Spheres that only touch do not collide.
        """
        batch, d = self._self_block(centres)
        if d.shape[-1] == 0:
            return torch.zeros(batch, dtype=torch.bool, device=centres.device)
        return ((d < self.self_reach + margin) & (self.self_reach > 0)).flatten(1).any(-1).reshape(batch)

    def self_clearance(self, centres: torch.Tensor) -> torch.Tensor:
        """The least gap (m) between two checked spheres, ``(...)``; negative where they overlap, inf with no pairs."""
        batch, d = self._self_block(centres)
        if d.shape[-1] == 0:
            return torch.full(batch, math.inf, dtype=self.dtype, device=centres.device)
        gap = torch.where(self.self_reach > 0, d - self.self_reach, torch.full_like(d, math.inf))
        return gap.flatten(1).amin(-1).reshape(batch)

    # ------------------------------------------------------------ reference
    def reference_fk(self, q: torch.Tensor) -> torch.Tensor:
        """TCP position through pytorch-kinematics' generic chain on the same URDF (slow; for checks)."""
        import pytorch_kinematics as pk

        self._check_q(q)
        if self._reference_chain is None:
            with open(self.urdf_path, "rb") as fh:
                root = self.frame_names[0]
                self._reference_chain = pk.build_serial_chain_from_urdf(fh.read(), self.tcp_link, root)
        full = self.full_joints(q.to(self.dtype)).to(q.dtype)
        chain = self._reference_chain.to(dtype=q.dtype, device=q.device)
        names = chain.get_joint_parameter_names()
        order = [self.chain_joint_names.index(n) for n in names]
        m = chain.forward_kinematics(full.reshape(-1, full.shape[-1])[:, order]).get_matrix()
        offset = torch.tensor(self.tcp_offset, dtype=q.dtype, device=q.device)
        tcp = m[:, :3, 3] + m[:, :3, :3] @ offset
        return tcp.reshape(*q.shape[:-1], 3)
