"""One task at a time, as a robot runs a trained planner: the policy and the model's step fused and compiled."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp.compiling import compile_kwargs
from torchrl_silp.models.base import as_model
from torchrl_silp.validation import check_bool, check_positive_int

__all__ = ["SingleTaskRollout"]


class SingleTaskRollout:
    """Roll a policy out deterministically on one task, step by step, at robot rates.

    :func:`~torchrl_silp.eval.evaluate` runs a batch of tasks through a TorchRL env; with one
    task the env's and the TensorDict machinery's per-step overhead is the whole cost. Here
    one step (the observation transform, the policy's deterministic action and the model's
    :meth:`~torchrl_silp.models.TaskModel.step`, swept-motion check included) is one
    function, compiled with ``torch.compile`` on first use (``compile=False`` keeps it eager).
    An episode ends as in ``evaluate`` with ``collision_type=0``: at the first success, the
    first collision, or after ``max_steps``.

    Inside the compiled step the motion check samples as many configurations as a full action
    step needs, whatever the action (:meth:`~torchrl_silp.models.TaskModel.motion_collision_flags`),
    and the value checks (NaN, inverted boxes) are skipped: give it tasks that
    :meth:`~torchrl_silp.models.TaskModel.sample_tasks` or an env produced.

    The policy, the model and the transform are fixed at construction (read-only attributes):
    build another rollout for another policy. Their parameters may change in place (a
    ``load_state_dict``), which the compiled step reads on each call.

    Args:
        policy: a TensorDict module writing ``"action"`` (e.g. the trained actor).
        model: the :class:`~torchrl_silp.models.TaskModel` (or an env holding one).
        observation_transform: builds the policy's inputs from the named state (the model's
            :class:`~torchrl.envs.CatTensors` by default).
        max_steps: episode length.
        compile: compile the step (``torch.compile``, on the first call).
        guards: what dynamo checks before each compiled step
            (:func:`~torchrl_silp.compiling.compile_kwargs`): ``"inputs"``, the state only, or
            ``"all"``, also every attribute of the policy's and the transform's modules and the
            globals their code reads. A step of one task is small, and those checks are a large
            part of it. With ``"inputs"``, a module attribute changed after the first call (not a
            parameter) goes unseen: the step keeps the graph compiled before the change.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> def still(td):  # a policy that never moves
        ...     return td.set("action", torch.zeros(*td.batch_size, 3))
        >>> run = SingleTaskRollout(still, model, max_steps=5, compile=False)
        >>> out = run(model.sample_tasks(1, generator=torch.Generator().manual_seed(0))[0])
        >>> out["joint_position"].shape, bool(out["success"]), int(out["steps"])
        (torch.Size([6, 3]), False, 5)
    """

    def __init__(self, policy, model, *, observation_transform=None, max_steps: int = 50, compile: bool = True,
                 guards: str = "inputs"):
        if not callable(policy):
            raise TypeError(f"policy must be a TensorDict module or a callable td -> td, got {type(policy).__name__}")
        check_positive_int(max_steps, name="max_steps")
        check_bool(compile, name="compile")
        compiling = compile_kwargs(guards)  # refuses an unknown guards, compiled or not
        self._policy = policy
        self._model = as_model(model)
        self._observation_transform = (
            self._model.observation_transform() if observation_transform is None else observation_transform
        )
        self.max_steps = max_steps
        self._step = torch.compile(self._eager_step, dynamic=False, **compiling) if compile else self._eager_step

    @property
    def policy(self):
        return self._policy

    @property
    def model(self):
        return self._model

    @property
    def observation_transform(self):
        return self._observation_transform

    def _eager_step(self, state: TensorDictBase):
        inputs = self.observation_transform(state.clone(False))
        action = self.policy(inputs).get("action")
        nxt, reward, collision, success, _ = self.model.step(state, action)
        return nxt, action, reward, collision, success

    @torch.no_grad()
    def __call__(self, task: TensorDictBase) -> TensorDict:
        """Roll out on ``task`` (a TensorDict of one task, batch ``[]`` or ``[1]``, with the model's state keys).

        Returns:
            a TensorDict with ``joint_position`` ``[steps + 1, D]`` (the path, start included),
            ``action`` ``[steps, A]``, ``reward`` ``[steps]``, and ``success``, ``collision``
            (bool) and ``steps`` (int) of the episode.
        """
        if not isinstance(task, TensorDictBase):
            raise TypeError(f"task must be a TensorDict with the keys {self.model.state_keys}, got {type(task).__name__}")
        if task.batch_size.numel() != 1:
            raise ValueError(f"task must hold one task (batch [] or [1]), got batch {tuple(task.batch_size)}")
        missing = [k for k in self.model.state_keys if k not in task.keys()]
        if missing:
            raise KeyError(f"task lacks the keys {missing} (a state holds {self.model.state_keys})")
        state = task.select(*self.model.state_keys).reshape(1)
        path, actions, rewards = [state.get(self.model.config_key)], [], []
        success = collision = False
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            for _ in range(self.max_steps):  # over time: one task
                state, action, reward, hit, reached = self._step(state)
                path.append(state.get(self.model.config_key))
                actions.append(action)
                rewards.append(reward)
                collision, success = bool(hit), bool(reached)
                if collision or success:
                    break
        return TensorDict({
            self.model.config_key: torch.cat(path), "action": torch.cat(actions), "reward": torch.cat(rewards).reshape(-1),
            "success": torch.tensor(success), "collision": torch.tensor(collision), "steps": torch.tensor(len(actions)),
        })
