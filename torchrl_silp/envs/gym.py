"""A Gymnasium twin of :class:`~torchrl_silp.envs.reach.UR5eReachEnv` (numpy in, numpy out).

The model is not re-implemented here: each Gymnasium env holds an unbatched
``UR5eReachEnv`` and forwards ``reset``/``step`` to it, so task sampling,
kinematics, collision checks, collision handling and truncation are the ones
of the TorchRL env, bit for bit. Importing this module registers the id
``torchrl_silp/UR5eReach-v0``.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict

from torchrl_silp.envs.reach import UR5eReachEnv
from torchrl_silp.geometry import CollisionReason
from torchrl_silp.robot import UR5e

__all__ = ["UR5eReachGymEnv", "ENV_ID"]

ENV_ID = "torchrl_silp/UR5eReach-v0"


class UR5eReachGymEnv(gymnasium.Env):
    """The SILP+ UR5e reaching task as a :class:`gymnasium.Env`.

    Same task, dynamics, reward and collision handling as
    :class:`~torchrl_silp.envs.reach.UR5eReachEnv` (see there), for one env,
    with numpy ``float32`` observations and actions.

    Observation ``(15,)`` float32: the 3 active joint angles, TCP xyz, obstacle
    AABB ``(xmin, xmax, ymin, ymax, zmin, zmax)``, goal xyz. Its box bounds
    are the joint limits for the angles and ``+-reach`` for the positions,
    ``reach`` being the arm's length (with a 1 % margin), which no TCP,
    obstacle or goal can exceed.

    Action ``(3,)`` in ``[-1, 1]``; one unit is 0.125 rad on each active
    joint. Out-of-range actions (including +-inf) are clipped to ``[-1, 1]``,
    as the TorchRL env does; NaN actions raise ``ValueError``.

    ``step`` returns ``(obs, reward, terminated, truncated, info)``: success
    (and, with ``collision_type=0``, a collision) terminates; ``max_steps``
    truncates (stepping on after either goes on from the last state; call
    ``reset``). ``info`` holds ``"collision"`` and ``"success"`` (bool),
    ``"collision_reason"`` (list of names from
    :meth:`~torchrl_silp.geometry.CollisionReason.names`, e.g. ``["obstacle"]``),
    ``"goal_q"`` (a goal configuration, ``(3,)`` float32) and ``"discard"``
    (bool; ``collision_type=1`` marks collision transitions to drop).

    Seeding: ``reset(seed=s)`` seeds :attr:`np_random` and the torch generator
    that draws the tasks, so a seed gives the same task as
    ``UR5eReachEnv(seed=s).reset()`` (for ``s < 2**64``); later resets without a
    seed continue both streams.

    Args:
        max_steps: episode length before truncation (paper: 50).
        collision_type: 0, 1 or 2, as in :class:`~torchrl_silp.envs.reach.UR5eReachEnv`.
        success_distance: reach accuracy in metres (paper: 0.05).
        render_mode: ``None`` or ``"rgb_array"`` (``render()`` then returns a
            ``(480, 480, 3)`` uint8 picture of the current state and the TCP path).

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
        # UR5eReachEnv validates max_steps, collision_type and success_distance.
        self._env = UR5eReachEnv(
            batch_size=(), max_steps=max_steps, collision_type=collision_type, success_distance=success_distance
        )
        self.render_mode = render_mode
        robot = self._env.robot
        with torch.no_grad():
            _, pos = robot.frames(torch.zeros(3, dtype=robot.dtype, device=robot.device))
        # Consecutive frame origins are a fixed distance apart whatever the
        # joint angles, so their sum bounds how far the TCP can be from the base.
        reach = float((pos[1:] - pos[:-1]).norm(dim=-1).sum()) * 1.01
        reach = max(reach, *map(abs, (*UR5eReachEnv.WORKSPACE_LOW, *UR5eReachEnv.WORKSPACE_HIGH)))
        low = np.full(15, -reach, dtype=np.float32)
        high = np.full(15, reach, dtype=np.float32)
        low[:3] = robot.joint_low.cpu().numpy()
        high[:3] = robot.joint_high.cpu().numpy()
        self.observation_space = spaces.Box(low=low, high=high, dtype=np.float32)
        self.action_space = spaces.Box(low=-1.0, high=1.0, shape=(3,), dtype=np.float32)
        self._obs: np.ndarray | None = None
        self._goal_q: np.ndarray | None = None
        self._path: list[np.ndarray] = []

    # -------------------------------------------------------------- access
    @property
    def torch_env(self) -> UR5eReachEnv:
        """The unbatched :class:`~torchrl_silp.envs.reach.UR5eReachEnv` that runs the task.

        Its pure functions (``transition``, ``reward``, ``outcome``,
        ``collides``) score states of this env exactly.
        """
        return self._env

    @property
    def robot(self) -> UR5e:
        """The :class:`~torchrl_silp.robot.UR5e` of the task."""
        return self._env.robot

    # ----------------------------------------------------------------- API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Draw a new task. ``options`` is accepted for API compatibility and must be ``None`` or empty."""
        super().reset(seed=seed)
        if options:
            raise ValueError(f"options: this env takes no reset options, got {sorted(options)}")
        if seed is not None:
            # Gymnasium seeds are non-negative ints of any size; torch takes 64 bits.
            self._env.set_seed(int(seed) % 2**64)
        td = self._env.reset()
        self._obs = td["observation"].cpu().numpy().astype(np.float32)
        self._goal_q = td["goal_q"].cpu().numpy().astype(np.float32)
        self._path = [self._obs[3:6].copy()]
        info = {
            "collision": False,
            "success": False,
            "collision_reason": [],
            "goal_q": self._goal_q.copy(),
            "discard": False,
        }
        return self._obs.copy(), info

    def step(self, action):
        """Move the three active joints by ``action * 0.125`` rad (clipped to ``[-1, 1]`` first)."""
        if self._obs is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        a = self._check_action(action)
        td = self._env.step(TensorDict(action=torch.from_numpy(a).to(self._env.device)))
        nxt = td["next"]
        self._obs = nxt["observation"].cpu().numpy().astype(np.float32)
        self._path.append(self._obs[3:6].copy())
        flags = int(nxt["collision_reason"].item())
        info = {
            "collision": bool(nxt["collision"].item()),
            "success": bool(nxt["success"].item()),
            "collision_reason": CollisionReason.names(flags),
            "goal_q": self._goal_q.copy(),
            "discard": bool(nxt["discard"].item()),
        }
        return (
            self._obs.copy(),
            float(nxt["reward"].item()),
            bool(nxt["terminated"].item()),
            bool(nxt["truncated"].item()),
            info,
        )

    def render(self):
        """The current state as a ``(480, 480, 3)`` uint8 picture in ``"rgb_array"`` mode; ``None`` otherwise."""
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() called with render_mode=None; pass render_mode='rgb_array' to the constructor "
                "(or gymnasium.make) to get pictures."
            )
            return None
        if self._obs is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        # matplotlib is imported on first render only: `import torchrl_silp` stays light.
        from torchrl_silp.viz import render_rgb

        width, height = self.RENDER_SIZE
        return render_rgb(
            self.robot,
            self._obs[:3],
            self._obs[6:12],
            self._obs[12:15],
            start_tcp=self._path[0],
            trajectory=np.stack(self._path),
            width=width,
            height=height,
        )

    # ------------------------------------------------------------ helpers
    @staticmethod
    def _check_action(action) -> np.ndarray:
        if isinstance(action, torch.Tensor):
            action = action.detach().cpu().numpy()
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise TypeError(f"action must be an array of 3 numbers, got {action!r}") from err
        if a.shape != (3,):
            raise ValueError(f"action must have shape (3,), got {a.shape}")
        if np.isnan(a).any():
            raise ValueError(f"action must not contain NaN, got {a}")
        return np.clip(a, -1.0, 1.0).astype(np.float32)


def _register() -> None:
    # A second import (reload, or a test that re-imports) must not register
    # twice: gymnasium warns about overriding an existing id.
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="torchrl_silp.envs.gym:UR5eReachGymEnv")


_register()
