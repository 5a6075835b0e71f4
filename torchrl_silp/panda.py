"""Alias of :mod:`torchrl_silp.robots.panda` (the Franka Emika Panda).

Examples:
    >>> from torchrl_silp.panda import Panda
    >>> from torchrl_silp.robots import Panda as Same
    >>> Panda is Same
    True
"""

from torchrl_silp.robots.panda import Panda, panda_urdf_path

N_JOINTS = len(Panda.HOME)
TCP_FRAME = Panda.TCP_FRAME
ROOT_FRAME = "panda_link0"

__all__ = ["Panda", "panda_urdf_path", "N_JOINTS", "TCP_FRAME", "ROOT_FRAME"]
