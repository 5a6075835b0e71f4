"""Alias of :mod:`torchrl_silp.robots.ur5e` (the UR5e) and the URDF helpers of :mod:`torchrl_silp.robots.urdf`.

Examples:
    >>> from torchrl_silp.robot import UR5e
    >>> from torchrl_silp.robots import UR5e as Same
    >>> UR5e is Same
    True
"""

from torchrl_silp.robots.ur5e import ACTIVE_JOINTS, WRIST_2_FIXED, WRIST_3_FIXED, UR5e, default_urdf_path
from torchrl_silp.robots.urdf import CollisionPrimitive, origin_matrix, read_urdf

TCP_FRAME = UR5e.TCP_FRAME

__all__ = ["UR5e", "default_urdf_path", "CollisionPrimitive", "read_urdf", "origin_matrix", "ACTIVE_JOINTS",
           "WRIST_2_FIXED", "WRIST_3_FIXED", "TCP_FRAME"]
