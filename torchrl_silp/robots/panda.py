"""The Franka Emika Panda with the Franka Hand, from ``assets/panda.urdf``, seven active joints."""

from __future__ import annotations

import os

import torch

from torchrl_silp.robots.urdf import asset_path, load_description, serial_chain
from torchrl_silp.robots.urdf_arm import URDFArm

__all__ = ["Panda", "panda_urdf_path"]

JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))


def panda_urdf_path() -> str:
    """Path of ``assets/panda.urdf``, installed with the package as ``torchrl_silp.assets``."""
    return asset_path("panda.urdf")


class Panda(URDFArm):
    """Franka Emika Panda with the Franka Hand (fingers open), seven active joints (a :class:`URDFArm`).

    Collision geometry is the sphere cover of the URDF's ``<collision>``
    primitives; ``table_mask`` selects the spheres checked against the table
    plane ``z = 0`` (all but those of :attr:`TABLE_LINKS`, which stand on it).

    Self collision (:attr:`self_pair_a`, :attr:`self_pair_b`): each link gets
    the number of joints between it and the base (``panda_link0`` 0,
    ``panda_linkK`` K, and ``panda_link8`` / ``panda_hand`` 7, as they are rigid
    with ``panda_link7``). A pair of spheres is checked when their links are at
    least :attr:`SELF_COLLISION_GAP` (3) joints apart, e.g. hand / link7 /
    link6 against link0-link3, link5 against link0-link2, the hand against
    link4; closer links touch by construction around the joints they share.
    Pairs whose spheres already overlap at :attr:`HOME` (a collision-free pose
    of the real arm) would be dropped as artefacts of the conservative cover
    (:attr:`home_overlap_pairs`; none with the shipped URDF). Spheres that only
    touch do not collide.

    Args:
        urdf_path: URDF file; defaults to :func:`panda_urdf_path`.
        device: torch device of the constant tensors.
        dtype: floating dtype (float32 default; float64 for tests).

    Examples:
        >>> import torch
        >>> from torchrl_silp.robots import Panda
        >>> robot = Panda()
        >>> q = torch.tensor(Panda.HOME)
        >>> robot.fk(q).shape
        torch.Size([3])
        >>> rot, pos = robot.frames(torch.zeros(4, 2, 7))
        >>> rot.shape, pos.shape
        (torch.Size([4, 2, 11, 3, 3]), torch.Size([4, 2, 11, 3]))
        >>> centres, tcp = robot.spheres_and_tcp(q)
        >>> centres.shape == (robot.n_spheres, 3)
        True
        >>> bool(robot.self_collision(centres))
        False
    """

    #: Franka's "ready" pose, collision free and above the table.
    HOME = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
    #: minimum number of joints between two links whose spheres are checked for self collision
    SELF_COLLISION_GAP = 3
    TABLE_LINKS = ("panda_link0", "panda_link1")
    END_EFFECTOR_LINKS = ("panda_hand",)

    def __init__(
        self,
        urdf_path: str | os.PathLike | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        path = panda_urdf_path() if urdf_path is None else urdf_path
        super().__init__(
            path,
            root="panda_link0",
            joints=JOINTS,
            ee_link=self.TCP_FRAME,
            self_collision_pairs=self._gap_pairs(path),
            device=device,
            dtype=dtype,
        )

    @classmethod
    def _gap_pairs(cls, path) -> list[tuple[str, str]]:
        """Link pairs at least :attr:`SELF_COLLISION_GAP` moving joints apart along the chain."""
        depth, d = {}, 0
        chain = serial_chain(load_description(path).joints, "panda_link0", cls.TCP_FRAME)
        depth["panda_link0"] = 0
        for j in chain:
            d += j.moves
            depth[j.child] = d
        links = list(depth)
        return [(x, y) for i, x in enumerate(links) for y in links[i + 1:] if abs(depth[x] - depth[y]) >= cls.SELF_COLLISION_GAP]
