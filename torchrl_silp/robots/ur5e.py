"""The UR5e with a Robotiq 2F-140-sized gripper, from ``assets/ur5e.urdf``, three active joints."""

from __future__ import annotations

import math
import os

import torch

from torchrl_silp.robots.urdf import asset_path
from torchrl_silp.robots.urdf_arm import URDFArm

__all__ = ["UR5e", "default_urdf_path", "ACTIVE_JOINTS"]

ACTIVE_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint")
# wrist_2 = -pi/2 and wrist_1 = -pi/2 - (q2 + q3) keep the tool z axis at -z
# for every (q1, q2, q3): the three lift/elbow/wrist_1 axes are parallel, so the
# tool pitch is their sum.
WRIST_2_FIXED = -math.pi / 2
WRIST_3_FIXED = 0.0
COUPLED_JOINTS = {
    "wrist_1_joint": ((0.0, -1.0, -1.0), -math.pi / 2),
    "wrist_2_joint": ((0.0, 0.0, 0.0), WRIST_2_FIXED),
    "wrist_3_joint": ((0.0, 0.0, 0.0), WRIST_3_FIXED),
}


def default_urdf_path() -> str:
    """Path of ``assets/ur5e.urdf``, installed with the package as ``torchrl_silp.assets``."""
    return asset_path("ur5e.urdf")


class UR5e(URDFArm):
    """UR5e with a Robotiq 2F-140-sized gripper, three active joints (a :class:`URDFArm`).

    Only shoulder_pan, shoulder_lift and elbow are active; wrist_1 follows them
    (``wrist_1 = -pi/2 - (shoulder_lift + elbow)``) so that the tool axis points
    straight down, wrist_2 and wrist_3 are fixed (paper, sec. 3.1): in the engine
    that is a linear map from the 3 active angles to the chain's 6.

    The base may rest on the table (its spheres are not checked against ``z = 0``);
    the self test is the paper task's: every gripper sphere against every sphere of
    ``self_collision_links`` (the pairs found by sampling, :class:`URDFArm`'s default,
    would also check the upper arm against the wrist, which this task never did).

    Args:
        urdf_path: URDF file; defaults to the one shipped in the package.
        device: torch device of the constant tensors.
        dtype: floating dtype (float32 default; float64 for tests).
        self_collision_links: links whose spheres are checked against the gripper's.

    Examples:
        >>> import torch
        >>> from torchrl_silp import UR5e
        >>> robot = UR5e()
        >>> q = torch.tensor([0.0, -1.5708, 1.5708])
        >>> robot.fk(q).shape
        torch.Size([3])
        >>> robot.full_joints(torch.zeros(4, 2, 3)).shape
        torch.Size([4, 2, 6])
        >>> centres, radii = robot.link_spheres(q)
        >>> centres.shape[-1], radii.ndim
        (3, 1)
        >>> bool(robot.self_collision(centres))
        False
    """

    GRIPPER_LINKS = ("tool0",)
    END_EFFECTOR_LINKS = GRIPPER_LINKS
    TABLE_LINKS = ("base_link",)
    CONFIG_NAME = "q3"

    def __init__(
        self,
        urdf_path: str | os.PathLike | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        self_collision_links: tuple[str, ...] = ("base_link", "shoulder_link", "upper_arm_link"),
    ):
        super().__init__(
            default_urdf_path() if urdf_path is None else urdf_path,
            root="base_link",
            joints=ACTIVE_JOINTS,
            ee_link=self.TCP_FRAME,
            coupled=COUPLED_JOINTS,
            self_collision_pairs=[(g, o) for g in self.GRIPPER_LINKS for o in self_collision_links],
            device=device,
            dtype=dtype,
        )
        if not set(self.GRIPPER_LINKS) <= set(self.sphere_link_names):
            raise ValueError(f"urdf_path: {self.urdf_path!r}: no collision geometry on {self.GRIPPER_LINKS}")
