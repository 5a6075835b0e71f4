"""The UR5e reach task of the SILP+ paper (sec. 3.1, 4.1) as a task model."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_silp.geometry import CollisionReason, in_box
from torchrl_silp.models.arm import ArmReach
from torchrl_silp.models.base import _check_finite, _check_tensor, check_boxes
from torchrl_silp.robots import UR5e

__all__ = ["UR5eReach", "TASK_BRANCHES", "WORKSPACE_EXIT_MODES", "TABLE_CONTACT_MODES"]

WORKSPACE_EXIT_MODES = ("collision", "block")
TABLE_CONTACT_MODES = ("collision", "block")
TASK_BRANCHES = ("front", "any")


class UR5eReach(ArmReach):
    """Reach a goal with a UR5e around a box: the paper's task as a :class:`TaskModel`.

    Three active joints (shoulder_pan, shoulder_lift, elbow; the wrist keeps
    the gripper pointing down); one action unit is 0.125 rad per joint. The
    achieved goal is the TCP position; the scene is one axis-aligned box
    ``"obstacle"`` ``(xmin, xmax, ymin, ymax, zmin, zmax)``.

    A configuration collides when a collision sphere of the arm or gripper
    meets the box, reaches below the table (the base may rest on it), the
    gripper meets the base, shoulder or upper arm, or the TCP leaves the
    workspace (bits of :class:`~torchrl_silp.geometry.CollisionReason`).

    Args:
        robot: a :class:`~torchrl_silp.robots.UR5e` to share; built from the packaged URDF by default.
        num_boxes, boxes: the scene (see :class:`ArmReach`); by default the paper's one box of fixed
            size. Any other scene is tested by :class:`ArmReach`'s test of every box, the paper's
            by a kernel fused for one box (``compile_collision`` applies to it alone).
        success_distance: reach accuracy in metres (paper: 0.05).
        motion_resolution, conservative: the swept check of a motion (see :class:`TaskModel`).
        workspace_exit: ``"collision"`` (a step taking the TCP out of the workspace is a
            collision) or ``"block"`` (such a step is not taken: the configuration stays).
        task_branch: ``"front"`` (start and goal with the TCP in front of the shoulder, one
            inverse-kinematics branch) or ``"any"`` (the whole task joint box, which also holds
            the shoulder-flipped branch).
        compile_collision: ``torch.compile`` the collision kernel (FK, spheres, checks).
        device, dtype: of the model's tensors.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> tasks = model.sample_tasks(4, torch.Generator().manual_seed(0))
        >>> nxt, reward, collision, success, flags = model.step(tasks, torch.zeros(4, 3))
        >>> bool((nxt["joint_position"] == tasks["joint_position"]).all()), reward.shape
        (True, torch.Size([4, 1]))
    """

    robot_class = UR5e
    config_dim = 3
    action_scale = 0.125  # rad per action unit
    WORKSPACE_LOW = (0.0, -0.3, 0.0)
    WORKSPACE_HIGH = (0.8, 0.8, 0.6)
    OBSTACLE_SIZE = (0.2, 0.2, 0.3)
    OBSTACLE_CENTER_LOW = (0.3, 0.1, 0.15)
    OBSTACLE_CENTER_HIGH = (0.7, 0.4, 0.15)
    # Joint box of start and goal configurations (then rejected unless collision-free,
    # in the workspace and d2 > d1 > d3): the arm stays "elbow up". With a lift below
    # -pi/2 it also holds the shoulder-flipped branch, which task_branch="front" rejects.
    TASK_JOINT_LOW = (-math.pi / 2, -math.pi, 0.0)
    TASK_JOINT_HIGH = (math.pi, 0.0, math.pi)

    def __init__(
        self,
        robot: UR5e | None = None,
        *,
        num_boxes: int = 1,
        boxes=None,
        success_distance: float = 0.05,
        motion_resolution: float = 0.01,
        conservative: bool = True,
        workspace_exit: str = "collision",
        table_contact: str = "collision",
        task_branch: str = "front",
        compile_collision: bool = False,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        if workspace_exit not in WORKSPACE_EXIT_MODES:
            raise ValueError(f"workspace_exit must be one of {WORKSPACE_EXIT_MODES}, got {workspace_exit!r}")
        if table_contact not in TABLE_CONTACT_MODES:
            raise ValueError(f"table_contact must be one of {TABLE_CONTACT_MODES}, got {table_contact!r}")
        if task_branch not in TASK_BRANCHES:
            raise ValueError(f"task_branch must be one of {TASK_BRANCHES}, got {task_branch!r}")
        if not isinstance(compile_collision, bool):
            raise TypeError(f"compile_collision must be a bool, got {compile_collision!r}")
        super().__init__(
            robot, num_boxes=num_boxes, boxes=boxes, success_distance=success_distance, motion_resolution=motion_resolution,
            conservative=conservative, device=device, dtype=dtype,
        )
        self.workspace_exit = workspace_exit
        self.table_contact = table_contact
        self.task_branch = task_branch
        self.compile_collision = compile_collision
        self._kernel = self._collision_kernel
        if compile_collision:
            # inductor vectorises a static-shape kernel better than a dynamic-shape one: batches are
            # padded to a power of two, one compilation per size and margins met, more than dynamo's
            # default limit of 8 before it runs the kernel eagerly
            self._kernel = torch.compile(self._collision_kernel_from_trig, dynamic=False, recompile_limit=64)

    # ------------------------------------------------------------ kinematics
    @property
    def blocks_steps(self) -> bool:
        """Whether some steps are not taken (``workspace_exit`` or ``table_contact`` is ``"block"``)."""
        return self.workspace_exit == "block" or self.table_contact == "block"

    def transition(self, state: TensorDictBase, action: torch.Tensor) -> TensorDict:
        out = super().transition(state, action)
        if self.blocks_steps:
            self._block_steps(state, out)
        return out

    def step(self, state, action):
        if self.blocks_steps:
            # a blocked step falls back on the previous state
            nxt = self.transition(state, action)
            return (nxt, *self.outcome(state, nxt))
        return super().step(state, action)

    def _block_steps(self, state: TensorDictBase, nxt: TensorDictBase) -> None:
        # judged where the step ends, exactly, as the arm's controller would refuse the target
        blocked = torch.zeros(nxt.batch_size, dtype=torch.bool, device=nxt.device)
        if self.workspace_exit == "block":
            blocked = blocked | ~in_box(nxt.get(self.achieved_goal_key), self.workspace_low, self.workspace_high)
        if self.table_contact == "block":
            config = nxt.get(self.config_key)
            centres, _ = self.robot.spheres_and_tcp(config.reshape(-1, self.config_dim))
            mask, r = self.robot.table_mask, self.robot.sphere_radii
            below = (centres[:, mask, 2] < r[mask]).any(-1).reshape(config.shape[:-1])
            blocked = blocked | below
        blocked = blocked.unsqueeze(-1)
        for key in (self.config_key, self.achieved_goal_key):
            nxt.set(key, torch.where(blocked, state.get(key).to(nxt.get(key).dtype), nxt.get(key)))

    # ------------------------------------------------------------- collisions
    def collision_flags(self, config, scene, margin=None):
        if self.num_boxes != 1:
            return super().collision_flags(config, scene, margin)
        _check_tensor("config", config, 3)
        obstacle = scene.get("obstacle") if isinstance(scene, TensorDictBase) else scene
        _check_tensor("obstacle", obstacle, 6)
        _check_finite("config", config)
        check_boxes("obstacle", obstacle)
        batch = torch.broadcast_shapes(config.shape[:-1], obstacle.shape[:-1])
        q = config.to(self.dtype).expand(*batch, 3).reshape(-1, 3)
        # contiguous: an expanded (stride-0) box would recompile the compiled kernel per layout
        box = obstacle.to(self.dtype).expand(*batch, 6).reshape(-1, 6).contiguous()
        m = margin or {}
        margins = (float(m.get("obstacle", 0.0)), float(m.get("table", 0.0)), float(m.get("self", 0.0)),
                   float(m.get("workspace", 0.0)))
        n = q.shape[0]
        if self.compile_collision and n and not torch.compiler.is_compiling():
            size = max(64, 1 << (n - 1).bit_length())
            if size != n:  # padded with copies of the first row, dropped below
                q = torch.cat([q, q[:1].expand(size - n, 3)])
                box = torch.cat([box, box[:1].expand(size - n, 6)])
            cos, sin = self.robot.joint_trig(q)  # outside the compiled code: see ArmKinematics.joint_trig
            flags, tcp = self._kernel(cos, sin, box, *margins)
            flags, tcp = flags[:n], tcp[:n]
        else:
            flags, tcp = self._collision_kernel(q, box, *margins)
        return flags.reshape(*batch, 1), tcp.reshape(*batch, 3)

    def _collision_kernel(self, q, box, m_obstacle: float = 0.0, m_table: float = 0.0, m_self: float = 0.0,
                          m_workspace: float = 0.0):
        # q (N, 3), box (N, 6) -> flags (N,) uint8, tcp (N, 3); margins inflate the spheres
        points = self.robot.cover_points(q)
        return self._flags_of_points(points, box, m_obstacle, m_table, m_self, m_workspace)

    def _collision_kernel_from_trig(self, cos, sin, box, m_obstacle: float = 0.0, m_table: float = 0.0,
                                    m_self: float = 0.0, m_workspace: float = 0.0):
        # the compiled kernel: the moving joints' cosines and sines (K, N) in, as _collision_kernel otherwise
        points = self.robot.cover_points_from_trig(cos, sin)
        return self._flags_of_points(points, box, m_obstacle, m_table, m_self, m_workspace)

    def _flags_of_points(self, points, box, m_obstacle, m_table, m_self, m_workspace):
        # points (3, N, S + 1) from robot.cover_points: each test reduces over a sample's spheres
        robot = self.robot
        s = robot.n_spheres
        r = robot.sphere_radii
        gap2 = None
        for axis in range(3):
            x = points[axis, :, :s]
            g = torch.maximum(box[:, 2 * axis, None] - x, x - box[:, 2 * axis + 1, None]).clamp(min=0).square()
            gap2 = g if gap2 is None else gap2 + g
        hit_obstacle = (gap2 < (r + m_obstacle).square()).any(-1)
        t = robot.table_index
        hit_table = (points[2, :, t] < r[t] + m_table).any(-1)
        rows, cols, reach = robot.self_rows, robot.self_cols, robot.self_reach
        reach2 = torch.where(reach > 0, (reach + m_self).square(), -1.0)  # (R, C)
        d2 = sum((points[axis, :, rows].unsqueeze(-1) - points[axis, :, cols].unsqueeze(-2)).square() for axis in range(3))
        hit_self = (d2 < reach2).flatten(-2).any(-1)
        tcp = points[:, :, s].T.contiguous()
        out_ws = ~in_box(tcp, self.workspace_low + m_workspace, self.workspace_high - m_workspace)
        flags = CollisionReason.pack(hit_obstacle, hit_table, hit_self, out_ws)
        return flags, tcp

    def clearance(self, config, scene):
        if self.num_boxes != 1:
            return super().clearance(config, scene)
        _check_tensor("config", config, 3)
        obstacle = scene.get("obstacle") if isinstance(scene, TensorDictBase) else scene
        batch = torch.broadcast_shapes(config.shape[:-1], obstacle.shape[:-1])
        q = config.to(self.dtype).expand(*batch, 3).reshape(-1, 3)
        box = obstacle.to(self.dtype).expand(*batch, 6).reshape(-1, 6)
        robot = self.robot
        centres, tcp = robot.spheres_and_tcp(q)
        r = robot.sphere_radii
        lo, hi = box[:, None, 0::2], box[:, None, 1::2]
        gap = torch.maximum(lo - centres, centres - hi).clamp(min=0)
        obstacle_c = (gap.norm(dim=-1) - r).amin(-1)
        table_c = torch.where(robot.table_mask, centres[..., 2] - r, math.inf).amin(-1)  # static shapes
        self_c = robot.self_clearance(centres)
        ws_c = torch.minimum(tcp - self.workspace_low, self.workspace_high - tcp).amin(-1)
        return torch.stack([obstacle_c, table_c, self_c, ws_c], -1).reshape(*batch, 4)

    # --------------------------------------------------------------- sampling
    @staticmethod
    def reach_along_pan(q: torch.Tensor, tcp: torch.Tensor) -> torch.Tensor:
        """Horizontal reach of the TCP along the pan direction ``(...)``: negative when the shoulder is flipped."""
        pan = q[..., 0]
        return tcp[..., 0] * torch.cos(pan) + tcp[..., 1] * torch.sin(pan)

    def task_filter(self, config: torch.Tensor, tcp: torch.Tensor) -> torch.Tensor:
        """``task_branch="front"``: the TCP in front of the shoulder; ``"any"``: every configuration."""
        if self.task_branch == "any":
            return super().task_filter(config, tcp)
        return self.reach_along_pan(config, tcp) > 0
