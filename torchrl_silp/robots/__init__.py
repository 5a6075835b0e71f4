"""The robot layer: URDF parsing, the arm-kinematics interface and its one batched FK engine, the arms."""

from torchrl_silp.robots.base import ArmKinematics
from torchrl_silp.robots.panda import Panda, panda_urdf_path
from torchrl_silp.robots.ur5e import UR5e, default_urdf_path
from torchrl_silp.robots.urdf import CollisionPrimitive

__all__ = ["ArmKinematics", "UR5e", "Panda", "CollisionPrimitive", "default_urdf_path", "panda_urdf_path"]
