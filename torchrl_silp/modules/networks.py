"""Network wrappers that use the task model: the Q-network that sees where the action leads."""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, unravel_key
from torch import nn

from torchrl_silp.validation import check_bool, check_positive_float

__all__ = ["NextGoalOffsetQ"]


class NextGoalOffsetQ(nn.Module):
    """A Q-network that also sees the vector from where the action takes the achieved goal to the desired goal.

    Success is a step in the *next* achieved goal's distance to the desired goal
    (5 cm for the reach tasks), so a Q-network on ``(s, a)`` alone must learn the
    robot's kinematics to place that step and blurs it near the goal. The task
    model's transition f_s gives the next achieved goal exactly; this wrapper
    computes ``desired_goal - model.transition(state, action)[achieved_goal_key]``
    and appends it to the inputs of ``mlp``::

        mlp(*observations, action, desired_goal - next_achieved_goal)

    The transition is differentiable in the action (through the clip to
    ``[-1, 1]`` and the joint limits, then the forward kinematics), so an actor
    loss that differentiates Q in the action gets that gradient too.

    The state is rebuilt as a TensorDict from the model's named keys
    (:attr:`TaskModel.state_keys <torchrl_silp.models.TaskModel.state_keys>`),
    which the wrapper takes as further inputs: :attr:`in_keys` lists them all
    in the order :meth:`forward` takes them, for the
    :class:`~torchrl.modules.ValueOperator` that wraps it. A batch the critic
    reads (root and ``"next"``) must therefore hold the named state keys, as
    :class:`~torchrl_silp.envs.ReachEnv` writes them. TorchRL's ``SACLoss`` and
    ``DDPGLoss`` pass the critic's further inputs; ``TD3Loss`` (0.14) passes it
    only the actor's ``in_keys`` and the action, so with TD3 list the state keys
    among the actor's ``in_keys`` too (a missing input raises a ``KeyError``).

    With ``clearance=True`` (ours) the MLP also reads the model's per-reason
    clearance of the next configuration (:meth:`TaskModel.clearance
    <torchrl_silp.models.TaskModel.clearance>`, metres, negative where that
    reason collides), clipped to ``[-clearance_clip, clearance_clip]``::

        mlp(*observations, action, desired_goal - next_achieved_goal, clip(clearance(next_config, scene)))

    A critic on the raw scene must learn which action brings which link into which
    obstacle; the clearance says it in one number per reason, and its gradient
    (through the distances of the model's geometry) reaches the actor.

    The model is a plain attribute, not a submodule (a task model is no
    ``nn.Module``): ``.to(device)`` does not move it, pass a model on the
    device of the inputs. A deep copy of the wrapper shares the model (the model
    is stateless). The transition is the model's own: an env's collision
    handling (:class:`~torchrl_silp.transforms.CollisionHandling`, which puts
    the arm back after a collision) is not applied.

    Args:
        mlp: the network; called with ``len(observation_keys) + 2`` tensors
            (TorchRL's :class:`~torchrl.modules.MLP` concatenates them).
        model: the :class:`~torchrl_silp.models.TaskModel`.
        observation_keys: the keys the MLP reads before the action (a list of keys; a string is one key).
        action_key: the action's key.
        clearance: also feed the next configuration's clipped clearance (``len(model.collision_reasons)``
            more inputs).
        clearance_clip: the clip of the clearance (m): a reason farther than this reads as this far.

    Examples:
        >>> import torch
        >>> from torchrl.modules import MLP, ValueOperator
        >>> from torchrl_silp.models import UR5eReach
        >>> from torchrl_silp.modules.networks import NextGoalOffsetQ
        >>> model = UR5eReach()
        >>> q_net = NextGoalOffsetQ(MLP(num_cells=[32], out_features=1), model)
        >>> q_net.in_keys
        ['observation', 'action', 'joint_position', 'achieved_goal', 'obstacle', 'desired_goal']
        >>> critic = ValueOperator(q_net, in_keys=q_net.in_keys)
        >>> td = model.sample_tasks(4, torch.Generator().manual_seed(0))
        >>> td["observation"] = model.observation(td)
        >>> td["action"] = torch.zeros(4, 3)
        >>> critic(td)["state_action_value"].shape
        torch.Size([4, 1])
    """

    def __init__(
        self,
        mlp: nn.Module,
        model,
        observation_keys: Sequence[NestedKey] = ("observation",),
        action_key: NestedKey = "action",
        clearance: bool = False,
        clearance_clip: float = 0.2,
    ):
        super().__init__()
        if not callable(mlp):
            raise TypeError(f"mlp must be callable (an nn.Module), got {type(mlp).__name__}")
        for name in ("state_keys", "transition", "achieved_goal_key", "desired_goal_key"):
            if not hasattr(model, name):
                raise TypeError(f"model must be a TaskModel (it has no {name!r}), got {type(model).__name__}")
        if isinstance(observation_keys, str):
            observation_keys = [observation_keys]
        self.mlp = mlp
        self.model = model  # a TaskModel is no nn.Module: not registered, not in the state_dict
        self.observation_keys = [unravel_key(k) for k in observation_keys]
        self.action_key = unravel_key(action_key)
        self.clearance = check_bool(clearance, name="clearance")
        self.clearance_clip = check_positive_float(clearance_clip, name="clearance_clip", unit="metres")
        if not self.observation_keys:
            raise ValueError("observation_keys must name at least one key")
        self.in_keys = self.in_keys_for(model, self.observation_keys, self.action_key)
        #: how many leading inputs go to the MLP (the observations and the action)
        self.num_mlp_inputs = len(self.observation_keys) + 1
        self._state_index = {key: self.in_keys.index(unravel_key(key)) for key in model.state_keys}

    @staticmethod
    def in_keys_for(
        model, observation_keys: Sequence[NestedKey] = ("observation",), action_key: NestedKey = "action"
    ) -> list[NestedKey]:
        """The keys :meth:`forward` takes, in order: ``[*observation_keys, action_key, *state_keys]``.

        A state key that is also an observation key is listed once, as an observation.

        Examples:
            >>> from torchrl_silp.models import UR5eReach
            >>> NextGoalOffsetQ.in_keys_for(UR5eReach(), ["desired_goal", "goal_offset"])
            ['desired_goal', 'goal_offset', 'action', 'joint_position', 'achieved_goal', 'obstacle']
        """
        if isinstance(observation_keys, str):
            observation_keys = [observation_keys]
        keys = [unravel_key(k) for k in observation_keys] + [unravel_key(action_key)]
        if len(set(keys)) != len(keys):
            raise ValueError(f"observation_keys and action_key must be distinct, got {keys}")
        return keys + [k for k in (unravel_key(s) for s in model.state_keys) if k not in keys]

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        if len(inputs) != len(self.in_keys):
            raise TypeError(f"NextGoalOffsetQ takes {len(self.in_keys)} tensors ({self.in_keys}), got {len(inputs)}")
        missing = [key for key, x in zip(self.in_keys, inputs) if x is None]
        if missing:
            raise KeyError(
                f"NextGoalOffsetQ lacks the inputs {missing}: the batch given to the critic must hold {self.in_keys}"
            )
        model = self.model
        action = inputs[self.num_mlp_inputs - 1]
        state = TensorDict(
            {key: inputs[i] for key, i in self._state_index.items()}, batch_size=action.shape[:-1]
        )
        # the model's unchecked pieces: a host-synced input check cannot run inside the critic's vmap
        next_config = model.next_config(state.get(model.config_key), action)
        offset = state.get(model.desired_goal_key) - model.achieved_goal(next_config)
        if not self.clearance:
            return self.mlp(*inputs[: self.num_mlp_inputs], offset)
        clip = self.clearance_clip
        # a reason the scene lacks (no table link) is +inf: it reads as the clip, with no gradient
        clearance = model.clearance(next_config, state.select(*model.scene_keys)).clamp(-clip, clip)
        return self.mlp(*inputs[: self.num_mlp_inputs], offset, clearance.to(offset.dtype))

    def __deepcopy__(self, memo):
        # share the (stateless) task model; copy everything else
        memo.setdefault(id(self.model), self.model)
        cls = type(self)
        out = cls.__new__(cls)
        memo[id(self)] = out
        for name, value in self.__dict__.items():
            out.__dict__[name] = copy.deepcopy(value, memo)
        return out

    def extra_repr(self) -> str:
        clearance = f", clearance_clip={self.clearance_clip}" if self.clearance else ""
        return f"model={type(self.model).__name__}, in_keys={self.in_keys}{clearance}"
