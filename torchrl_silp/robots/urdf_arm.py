"""Any serial arm from its own URDF: :class:`URDFArm`."""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import torch

from torchrl_silp.robots.base import ArmKinematics
from torchrl_silp.robots.covers import CoverReport, cover_volume
from torchrl_silp.robots.self_collision import SelfCollisionMatrix, find_self_collision_pairs

__all__ = ["URDFArm"]


class URDFArm(ArmKinematics):
    """An :class:`ArmKinematics` for any serial arm: its URDF, the joints it moves and its TCP.

    The URDF is read by yourdfpy (meshes, ``package://`` paths, transmissions, mimic and
    continuous joints); collision meshes get fitted sphere covers (cached on disk),
    primitives analytic ones. The configuration is the named ``joints``; the other movable
    joints are held (``held``, default 0 within their limits), coupled (``coupled``) or
    follow their ``<mimic>``. The TCP is ``ee_link``'s origin moved by ``ee_offset`` in
    that link's frame.

    Found, not listed: the self-collision pairs (:func:`~torchrl_silp.robots.self_collision.find_self_collision_pairs`,
    kept in :attr:`self_collision_matrix`) and, unless given, the table links: those that
    never move vertically (the base, and a link turning about a vertical axis through it),
    whose spheres are not tested against the table plane.

    Args:
        urdf_path: the URDF file.
        joints: the revolute joints of the configuration, in its order.
        ee_link: the link the TCP rides on.
        ee_offset: the TCP in ``ee_link``'s frame (m).
        package_dirs: folders holding ``package://`` packages, or ``{package: folder}``.
        root: the base link (default: the URDF's root link).
        coupled, held: see :class:`ArmKinematics`.
        home: a collision-free configuration (default: every joint at 0 within its limits).
        table_links: links standing on the table (default: found, as above).
        self_collision_pairs: the link pairs to check, as a task defines them; default: found
            by sampling (:attr:`self_collision_matrix`; None when the pairs are given).
        self_collision_samples: configurations sampled to sort the link pairs.
        max_spheres_per_link, cover_volume_ratio: a mesh's cover (:mod:`torchrl_silp.robots.covers`).
        device, dtype: of the constant tensors (float32 default).

    Examples:
        >>> import torch
        >>> from torchrl_silp.robots import URDFArm, asset_path
        >>> arm = URDFArm(asset_path("panda.urdf"), joints=[f"panda_joint{i}" for i in range(1, 8)],
        ...               ee_link="panda_hand", ee_offset=(0, 0, 0.1034), self_collision_samples=2000)
        >>> arm.fk(torch.zeros(5, 7)).shape
        torch.Size([5, 3])
        >>> arm.table_links
        ('panda_link0', 'panda_link1')
        >>> len(arm.self_collision_matrix.kept) > 0
        True
    """

    def __init__(
        self,
        urdf_path: str | os.PathLike,
        *,
        joints: Sequence[str],
        ee_link: str,
        ee_offset: Sequence[float] = (0.0, 0.0, 0.0),
        package_dirs=None,
        root: str | None = None,
        coupled: Mapping[str, tuple[Sequence[float], float]] | None = None,
        held: Mapping[str, float] | None = None,
        home: Sequence[float] | None = None,
        table_links: Iterable[str] | None = None,
        self_collision_pairs: Iterable[tuple[str, str]] | None = None,
        self_collision_samples: int = 10_000,
        max_spheres_per_link: int = 8,
        cover_volume_ratio: float = 2.5,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        if isinstance(joints, str) or not isinstance(joints, Sequence):
            raise TypeError(f"joints must be a list of joint names, got {joints!r}")
        super().__init__(
            urdf_path, root=root, config_joints=joints, tcp_link=ee_link, tcp_offset=ee_offset, coupled=coupled,
            held=held, package_dirs=package_dirs, max_spheres_per_link=max_spheres_per_link,
            cover_volume_ratio=cover_volume_ratio, device=device, dtype=dtype,
        )
        if home is not None:
            home = tuple(float(v) for v in home)
            if len(home) != self.config_dim:
                raise ValueError(f"home must hold {self.config_dim} angles (the joints {list(self.joint_names)}), "
                                 f"got {len(home)}")
            self.HOME = home
        self._set_table_links(self.TABLE_LINKS or (table_links if table_links is not None else self._level_links()))
        if not self.END_EFFECTOR_LINKS:
            last = self.frame_body[self.frame_names.index(self.tcp_frame)]
            self.END_EFFECTOR_LINKS = tuple(
                n for n, b in zip(self.frame_names, self.frame_body)
                if b == last and n != self.tcp_frame and self.frame_names.index(n) >= self.frame_names.index(ee_link)
            )
        self.self_collision_matrix: SelfCollisionMatrix | None = None
        if self_collision_pairs is None:
            self.self_collision_matrix = find_self_collision_pairs(self, home=self.HOME, samples=self_collision_samples)
            self_collision_pairs = self.self_collision_matrix.kept
        self._set_self_pairs(self_collision_pairs)

    def _level_links(self) -> tuple[str, ...]:
        """Links whose spheres never change height: the root's, and those turning about a vertical axis through it."""
        t = self._tables64
        gen = torch.Generator().manual_seed(0)
        low, high = t["joint_low"], t["joint_high"]
        q = low + torch.rand(64, low.numel(), generator=gen, dtype=torch.float64) * (high - low)
        from torchrl_silp.robots.base import apply_map, chain_bodies

        theta = t["_moving_map"] @ q.T + t["_moving_offset"].unsqueeze(-1)
        z = apply_map(chain_bodies(t["_origins_t"], theta.cos(), theta.sin()), t["_point_map"])[2, :, :-1]
        still = (z.amax(0) - z.amin(0)) < 1e-9
        names = np.asarray(self.sphere_link_names)
        return tuple(n for n in dict.fromkeys(self.sphere_link_names) if bool(still[names == n].all()))

    def cover_report(self, samples: int = 40_000) -> list[CoverReport]:
        """Per link: its spheres, the volume of their union and that of its collision solids (m^3).

        A link's solid volume is the union of its elements' (a mesh's enclosed volume if it is
        watertight, else its convex hull's), counted by the same Monte Carlo as the cover's.
        """
        import trimesh

        out = []
        radii = self.sphere_radii.double().cpu().numpy()
        local = self.sphere_local.double().cpu().numpy()
        names = np.asarray(self.sphere_link_names)
        for link in dict.fromkeys(self.sphere_link_names):
            mine = names == link
            # the link's spheres in the link frame: the cover was built there, so sphere_local is it
            centres, r = local[mine], radii[mine]
            solids = []
            for prim in self.primitives:
                if prim.link == link:
                    mesh = prim.trimesh()
                    solids.append(mesh if mesh.is_watertight else mesh.convex_hull)
            solid = trimesh.util.concatenate(solids) if len(solids) > 1 else solids[0]
            lo, hi = solid.bounds
            pts = lo + np.random.default_rng(0).random((samples, 3)) * (hi - lo)
            inside = np.zeros(samples, dtype=bool)
            for s in solids:
                inside |= s.contains(pts)
            out.append(CoverReport(link, int(mine.sum()), cover_volume(centres, r, samples),
                                   float(inside.mean() * np.prod(hi - lo))))
        return out
