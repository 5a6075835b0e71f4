"""The robot layer: URDF reading (yourdfpy, trimesh), sphere covers fitted to meshes, self-collision pairs
found by sampling, the arm-kinematics interface and its one batched FK engine, and the arms."""

from torchrl_silp.robots.base import ArmKinematics
from torchrl_silp.robots.panda import Panda, panda_urdf_path
from torchrl_silp.robots.self_collision import SelfCollisionMatrix, find_self_collision_pairs
from torchrl_silp.robots.ur5e import UR5e, default_urdf_path
from torchrl_silp.robots.urdf import CollisionPrimitive, asset_path, load_description
from torchrl_silp.robots.urdf_arm import URDFArm

__all__ = ["ArmKinematics", "URDFArm", "UR5e", "Panda", "CollisionPrimitive", "SelfCollisionMatrix",
           "find_self_collision_pairs", "load_description", "asset_path", "default_urdf_path", "panda_urdf_path"]
