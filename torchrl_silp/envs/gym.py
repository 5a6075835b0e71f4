"""Gymnasium twins of the TorchRL reach envs (numpy in, numpy out).

Importing ``torchrl_silp`` registers their ids ``torchrl_silp/UR5eReach-v0`` and ``torchrl_silp/PandaReach-v0``.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import step_mdp

from torchrl_silp import GYM_IDS
from torchrl_silp.envs.reach import ReachEnv
from torchrl_silp.models.base import TaskModel
from torchrl_silp.models.panda import PandaReach
from torchrl_silp.models.ur5e import UR5eReach
from torchrl_silp.robots import UR5e
from torchrl_silp.transforms import CollisionHandling

__all__ = ["ReachGymEnv", "UR5eReachGymEnv", "PandaReachGymEnv", "ENV_ID", "PANDA_ENV_ID"]

ENV_ID, PANDA_ENV_ID = GYM_IDS  # registered by the package's import


class ReachGymEnv(gymnasium.Env):
    """A Gymnasium twin of a :class:`~torchrl_silp.envs.reach.ReachEnv` over any task model (numpy in, numpy out).

    The task is not re-implemented here: the Gymnasium env holds an unbatched
    ``ReachEnv`` (with :class:`~torchrl_silp.transforms.CollisionHandling` and the
    model's observation) and forwards ``reset``/``step`` to it, so task sampling,
    kinematics, collision checks, collision handling and truncation are the ones
    of the TorchRL env, bit for bit.

    Observation: the model's flat observation (float32, the named parts
    concatenated in :attr:`~torchrl_silp.models.TaskModel.observation_keys` order);
    the configuration's box bounds are the joint limits, the rest unbounded.
    Action in ``[-1, 1]`` per joint; out-of-range actions (including +-inf) are
    clipped, NaN actions raise ``ValueError``. ``info`` holds ``"collision"`` and
    ``"success"`` (bool), ``"collision_reason"`` (names of the set bits, from the
    model's ``collision_reasons``), ``"goal_q"`` (a goal configuration) and
    ``"discard"``.

    Seeding: ``reset(seed=s)`` seeds :attr:`np_random` and the torch generator
    that draws the tasks, so a seed gives the same task as the TorchRL env seeded
    with ``s`` (for ``s < 2**64``).

    Args:
        model: the :class:`~torchrl_silp.models.TaskModel`.
        max_steps: episode length before truncation.
        collision_type: 0, 1 or 2 (see :class:`~torchrl_silp.transforms.CollisionHandling`).
    """

    metadata = {"render_modes": [], "render_fps": 8}

    def __init__(self, model: TaskModel, max_steps: int = 50, collision_type: int = 2):
        self.model = model
        self._env = TransformedEnv(
            ReachEnv(model, batch_size=(), max_steps=max_steps),
            Compose(CollisionHandling(collision_type), model.observation_transform()),
        )
        size = int(self._env.observation_spec["observation"].shape[-1])
        low = np.full(size, -np.inf, dtype=np.float32)
        high = np.full(size, np.inf, dtype=np.float32)
        low[: model.config_dim] = model.config_low.cpu().numpy()
        high[: model.config_dim] = model.config_high.cpu().numpy()
        self.observation_space = spaces.Box(low=low, high=high, dtype=np.float32)
        self.action_space = spaces.Box(low=-1.0, high=1.0, shape=(model.action_dim,), dtype=np.float32)
        self._td = None
        self._path: list[np.ndarray] = []

    @property
    def torch_env(self) -> TransformedEnv:
        """The unbatched TorchRL env that runs the task (its ``model`` scores states of this env exactly)."""
        return self._env

    def _numpy(self, key) -> np.ndarray:
        return self._td[key].cpu().numpy().astype(np.float32)

    def _info(self, nxt) -> dict:
        flags = int(nxt["collision_reason"].item())
        reasons = [name for bit, name in enumerate(self.model.collision_reasons) if flags & (1 << bit)]
        return {
            "collision": bool(nxt["collision"].item()),
            "success": bool(nxt["success"].item()),
            "collision_reason": reasons,
            "goal_q": self._goal_q.copy(),
            "discard": bool(nxt["discard"].item()),
        }

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Draw a new task. ``options`` is accepted for API compatibility and must be ``None`` or empty."""
        super().reset(seed=seed)
        if options:
            raise ValueError(f"options: this env takes no reset options, got {sorted(options)}")
        if seed is not None:
            # Gymnasium seeds are non-negative ints of any size; torch takes 64 bits.
            self._env.set_seed(int(seed) % 2**64)
        self._td = self._env.reset()
        self._goal_q = self._numpy(self.model.goal_config_key)
        self._path = [self._numpy(self.model.achieved_goal_key)]
        return self._numpy("observation"), self._info(self._td)

    def step(self, action):
        """Move the joints by ``action * action_scale`` (clipped to ``[-1, 1]`` first)."""
        if self._td is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        a = self._check_action(action, self.model.action_dim)
        td = self._td.clone(False)
        td.set("action", torch.from_numpy(a).to(self._env.device))
        out = self._env.step(td)
        nxt = out["next"]
        self._td = step_mdp(out)
        self._path.append(self._numpy(self.model.achieved_goal_key))
        return (
            self._numpy("observation"),
            float(nxt["reward"].item()),
            bool(nxt["terminated"].item()),
            bool(nxt["truncated"].item()),
            self._info(nxt),
        )

    @staticmethod
    def _check_action(action, size: int) -> np.ndarray:
        if isinstance(action, torch.Tensor):
            action = action.detach().cpu().numpy()
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise TypeError(f"action must be an array of {size} numbers, got {action!r}") from err
        if a.shape != (size,):
            raise ValueError(f"action must have shape ({size},), got {a.shape}")
        if np.isnan(a).any():
            raise ValueError(f"action must not contain NaN, got {a}")
        return np.clip(a, -1.0, 1.0).astype(np.float32)


class UR5eReachGymEnv(ReachGymEnv):
    """The SILP+ UR5e reaching task as a :class:`gymnasium.Env`, registered as ``torchrl_silp/UR5eReach-v0``.

    Same task, dynamics, reward and collision handling as
    :class:`~torchrl_silp.envs.reach.UR5eReachEnv`, for one env, with numpy
    ``float32`` observations ``(15,)`` (joint angles, TCP xyz, obstacle AABB, goal xyz)
    and actions ``(3,)``. The observation box bounds the positions by ``+-reach``,
    the arm's length with a 1 % margin, which no TCP, obstacle or goal exceeds.
    ``render()`` in ``"rgb_array"`` mode returns a ``(480, 480, 3)`` uint8 picture.

    Args:
        max_steps: episode length before truncation.
        collision_type: 0, 1 or 2, as in :class:`~torchrl_silp.envs.reach.UR5eReachEnv`.
        success_distance: reach accuracy in metres (paper: 0.05).
        render_mode: ``None`` or ``"rgb_array"``.

    Examples:
        >>> import gymnasium as gym
        >>> import torchrl_silp  # registers the id
        >>> env = gym.make("torchrl_silp/UR5eReach-v0")
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, obs.dtype
        ((15,), dtype('float32'))
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        >>> sorted(info)
        ['collision', 'collision_reason', 'discard', 'goal_q', 'success']
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 8}
    RENDER_SIZE = (480, 480)  # width, height in pixels

    def __init__(
        self,
        max_steps: int = 50,
        collision_type: int = 2,
        success_distance: float = 0.05,
        render_mode: str | None = None,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        super().__init__(UR5eReach(success_distance=success_distance), max_steps, collision_type)
        self.render_mode = render_mode
        robot = self.robot
        with torch.no_grad():
            _, pos = robot.frames(torch.zeros(3, dtype=robot.dtype, device=robot.device))
        # Consecutive frame origins are a fixed distance apart whatever the
        # joint angles, so their sum bounds how far the TCP can be from the base.
        reach = float((pos[1:] - pos[:-1]).norm(dim=-1).sum()) * 1.01
        reach = max(reach, *map(abs, (*UR5eReach.WORKSPACE_LOW, *UR5eReach.WORKSPACE_HIGH)))
        low = np.full(15, -reach, dtype=np.float32)
        high = np.full(15, reach, dtype=np.float32)
        low[:3] = robot.joint_low.cpu().numpy()
        high[:3] = robot.joint_high.cpu().numpy()
        self.observation_space = spaces.Box(low=low, high=high, dtype=np.float32)

    @property
    def robot(self) -> UR5e:
        """The :class:`~torchrl_silp.robots.UR5e` of the task."""
        return self.model.robot

    def render(self):
        """The current state as a ``(480, 480, 3)`` uint8 picture in ``"rgb_array"`` mode; ``None`` otherwise."""
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() called with render_mode=None; pass render_mode='rgb_array' to the constructor "
                "(or gymnasium.make) to get pictures."
            )
            return None
        if self._td is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        # matplotlib is imported on first render only: `import torchrl_silp` stays light.
        from torchrl_silp.viz import render_rgb

        width, height = self.RENDER_SIZE
        return render_rgb(
            self.robot,
            self._numpy("joint_position"),
            self._numpy("obstacle"),
            self._numpy("desired_goal"),
            start_tcp=self._path[0],
            trajectory=np.stack(self._path),
            width=width,
            height=height,
        )


class PandaReachGymEnv(ReachGymEnv):
    """The Franka Panda reach task (:class:`~torchrl_silp.models.PandaReach`) as a :class:`gymnasium.Env`.

    Registered as ``torchrl_silp/PandaReach-v0``. Observation ``(7 + 3 + 6 * num_boxes + 3,)``
    float32: joint angles, TCP xyz, the boxes' AABBs, goal xyz; action ``(7,)`` in ``[-1, 1]``.

    Args:
        max_steps: episode length before truncation.
        collision_type: 0, 1 or 2 (see :class:`~torchrl_silp.transforms.CollisionHandling`).
        num_boxes: boxes on the table.

    Examples:
        >>> import gymnasium as gym
        >>> import torchrl_silp  # registers the id
        >>> env = gym.make("torchrl_silp/PandaReach-v0")
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, env.action_space.shape
        ((19,), (7,))
    """

    def __init__(self, max_steps: int = 50, collision_type: int = 2, num_boxes: int = 1):
        super().__init__(PandaReach(num_boxes=num_boxes), max_steps, collision_type)
