"""The SILP+ objective: an actor-critic loss plus a filtered behaviour-cloning term (paper sec. 3.4)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import dispatch
from tensordict.utils import NestedKey, unravel_key
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import LossModule

from torchrl_silp.choices import BC_FILTERS, DEMO_ROWS
from torchrl_silp.models.base import as_model
from torchrl_silp.validation import check_choice, check_nonnegative_float, check_positive_int, check_probability

__all__ = ["SILPLoss", "BC_FILTERS", "DEMO_ROWS"]


_DIAGNOSTICS = ("bc_filter_fraction", "bc_mse", "num_demos")


class SILPLoss(LossModule):
    r"""Self-imitation learning by planning plus: an actor-critic loss and a filtered BC term.

    Wraps an actor-critic loss (:class:`~torchrl.objectives.SACLoss`,
    :class:`~torchrl.objectives.DDPGLoss`, :class:`~torchrl.objectives.TD3Loss`)
    and returns its ``loss_*`` terms, each scaled by ``lambda1``, plus

    .. math::
        \mathcal{L}_{bc} = \lambda_2 \frac{1}{N_D} \sum_{i \in D} R_{filter}(s_i, a_i)
            \lVert \pi(s_i) - a_i \rVert^2

    over the demonstrations of the batch (rows whose ``"is_demo"`` is True;
    ``N_D`` of them): the paper's eqs. 5-7, with the sum of eq. 5 taken as a
    mean so that ``lambda2`` does not depend on the batch size. A batch with
    no demonstration gives ``loss_bc == 0`` (no NaN). ``π(s)`` is the actor's
    deterministic action: the output of a deterministic actor (DDPG, TD3), the
    mode of a stochastic one (SAC's ``TanhNormal``), taken under
    ``ExplorationType.DETERMINISTIC``.

    The filter, ``filter=``:

    * ``"reward"`` (default, the paper's eqs. 6-7): keep a demonstration when
      ``R(s, a_demo) > R(s, π(s))``, where

      .. math::
          R(s_0, a_0) = r_0 + \gamma f_r(s_1, \pi(s_1)) + \dots + \gamma^k f_r(s_k, \pi(s_k))

      with ``f_s`` and ``f_r`` the task model's :meth:`~torchrl_silp.models.TaskModel.step`
      (transition and reward in one pass). For the demonstration, ``r_0`` and
      ``s_1`` are the stored ``("next", "reward")`` and next named state; for the
      policy, ``r_0 = f_r(s_0, π(s_0))`` and ``s_1 = f_s(s_0, π(s_0))``. The states
      are the model's named keys; the actor's inputs at ``s_j`` are built from them
      by ``observation_transform``. As in eq. 7 the look-ahead does not stop
      at terminal states, and both branches are treated alike. Needs ``model``.
    * ``"q"``: the Q-filter of SILP / Nair et al. 2018:
      ``Q(s, a_demo) > Q(s, π(s))`` with the wrapped loss's current critic
      (the minimum over the Q ensemble when there is one: SAC, TD3).
    * ``"none"``: every demonstration is imitated.

    The filter is a no-grad mask and the critic is never differentiated
    through, so ``loss_bc`` trains the actor parameters only.

    Target networks and optimisation: the wrapped loss keeps its parameters
    and target parameters; ``SILPLoss`` registers it as ``self.rl_loss``, so
    ``silp.parameters()`` are the wrapped loss's parameters (give them to the
    optimizer) and the target updater is built on the wrapped loss:
    ``SoftUpdate(silp.rl_loss, tau=...)`` (``SoftUpdate(silp)`` finds no
    target parameters). ``make_value_estimator`` and ``value_estimator`` are
    forwarded to the wrapped loss.

    Args:
        loss_module: the actor-critic loss to wrap; it must have an
            ``actor_network`` (and a ``qvalue_network`` or ``value_network``
            for ``filter="q"``) and a ``"mean"`` or ``"sum"`` reduction.
        model: the :class:`~torchrl_silp.models.TaskModel` of the task, for
            ``filter="reward"`` (an env holding one as ``.model`` works too). A
            plain reference: the model is no ``nn.Module``, so moving or saving the
            loss leaves it alone.

    Keyword Args:
        filter: ``"reward"``, ``"q"`` or ``"none"``.
        lambda1: weight of the wrapped loss's terms, ``>= 0``.
        lambda2: weight of the BC term, ``>= 0``.
        k: look-ahead steps of the reward filter, an int ``>= 1``.
        gamma: discount of the reward filter in ``[0, 1]``; ``None`` reads the
            wrapped loss's value estimator's ``gamma`` at each call (0.99 when
            it has none).
        observation_transform: builds the actor's inputs (``"observation"``, ...) from a
            named state during the look-ahead, as the env's transforms do; the model's
            :class:`~torchrl_silp.transforms.FlatCatTensors` by default.
        demo_rows: how the BC term finds the demonstration rows. ``"select"``
            (default) gathers them (``nonzero``: one host sync and a shape that
            depends on the data), so the actor and the filter run on those rows
            only. ``"mask"`` runs them on every row and zeroes the others: every
            shape is fixed by the batch's, as CUDA graphs (and a compiled update
            without a graph break) need, at ``batch / N_D`` times the term's work.
            Both give the same loss, gradients and diagnostics.

    Examples:
        >>> import torch
        >>> from torch import nn
        >>> from tensordict import TensorDict
        >>> from torchrl.modules import Actor, ValueOperator
        >>> from torchrl.objectives import DDPGLoss, SoftUpdate
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from torchrl_silp import CollisionHandling, ReachEnv, UR5eReach
        >>> model = UR5eReach()
        >>> env = TransformedEnv(ReachEnv(model, num_envs=8, seed=0), Compose(CollisionHandling(2), model.observation_transform()))
        >>> from torchrl_silp.objectives import SILPLoss
        >>> actor = Actor(nn.Sequential(nn.Linear(15, 3), nn.Tanh()), in_keys=["observation"])
        >>> class Critic(nn.Module):
        ...     def __init__(self):
        ...         super().__init__()
        ...         self.net = nn.Linear(18, 1)
        ...     def forward(self, obs, act):
        ...         return self.net(torch.cat([obs, act], -1))
        >>> critic = ValueOperator(Critic(), in_keys=["observation", "action"])
        >>> loss = SILPLoss(DDPGLoss(actor, critic), env.model, filter="reward", lambda2=2.0)
        >>> updater = SoftUpdate(loss.rl_loss, tau=0.005)
        >>> data = env.rollout(4).reshape(-1)
        >>> data["is_demo"] = torch.zeros(32, 1, dtype=torch.bool)
        >>> data["is_demo"][:8] = True
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_bc', 'loss_value']
        >>> int(out["num_demos"])
        8
        >>> sum(out[k] for k in ("loss_actor", "loss_bc", "loss_value")).backward()
        >>> updater.step()
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (set with :meth:`set_keys`).

        Attributes:
            is_demo: bool ``(..., 1)`` flag of the demonstration rows; a batch
                without it is refused (``KeyError``). Defaults to ``"is_demo"``.
            action: the stored (demonstrated) action; also forwarded to the
                wrapped loss. Defaults to ``"action"``.
            reward: the stored reward, read at ``("next", reward)``; also
                forwarded to the wrapped loss. Defaults to ``"reward"``.
            state_action_value: the critic's output key for the Q-filter; also
                forwarded to the wrapped loss. Defaults to ``"state_action_value"``.
        """

        is_demo: NestedKey = "is_demo"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        state_action_value: NestedKey = "state_action_value"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    _schedulable_buffers = frozenset({"lambda1", "lambda2"})

    def __init__(
        self,
        loss_module: LossModule,
        model=None,
        *,
        filter: str = "reward",
        lambda1: float = 1.0,
        lambda2: float = 1.0,
        k: int = 1,
        gamma: float | None = None,
        observation_transform=None,
        demo_rows: str = "select",
    ):
        if not isinstance(loss_module, LossModule):
            raise TypeError(f"loss_module must be a torchrl LossModule, got {type(loss_module).__name__}")
        if not hasattr(loss_module, "actor_network") or not hasattr(loss_module, "actor_network_params"):
            raise TypeError(
                f"loss_module must be an actor-critic loss with an actor_network (SACLoss, DDPGLoss, TD3Loss), "
                f"got {type(loss_module).__name__}"
            )
        if getattr(loss_module, "reduction", "mean") not in ("mean", "sum"):
            raise ValueError(
                f"loss_module.reduction must be 'mean' or 'sum' (the BC term is a scalar), "
                f"got {loss_module.reduction!r}"
            )
        check_choice(filter, BC_FILTERS, name="filter")
        check_choice(demo_rows, DEMO_ROWS, name="demo_rows")
        check_positive_int(k, name="k")  # look-ahead steps
        check_nonnegative_float(lambda1, name="lambda1")
        check_nonnegative_float(lambda2, name="lambda2")
        check_probability(gamma, name="gamma", closed=True, optional=True)
        if filter == "reward" and model is None:
            raise ValueError("filter='reward' needs model: the task model (a torchrl_silp.models.TaskModel)")
        if model is not None:
            model = as_model(model)
        if filter == "q" and self._critic_name(loss_module) is None:
            raise ValueError(
                f"filter='q' needs a loss with a qvalue_network or value_network, got {type(loss_module).__name__}"
            )
        super().__init__()
        self.rl_loss = loss_module
        self.model = model
        if observation_transform is None and model is not None:
            observation_transform = model.observation_transform()
        self.observation_transform = observation_transform
        self.filter = filter
        self.demo_rows = demo_rows
        self.k = k
        self._gamma = None if gamma is None else float(gamma)
        device = next(iter(loss_module.parameters()), torch.empty(0)).device
        self.register_buffer("lambda1", torch.tensor(float(lambda1), device=device))
        self.register_buffer("lambda2", torch.tensor(float(lambda2), device=device))
        self._refresh_keys()

    # ---------------------------------------------------------------- keys
    @staticmethod
    def _critic_name(loss_module) -> str | None:
        for name in ("qvalue_network", "value_network"):
            if hasattr(loss_module, name) and hasattr(loss_module, f"{name}_params"):
                return name
        return None

    def set_keys(self, **kwargs) -> None:
        """Set tensordict key names; keys the wrapped loss also accepts are forwarded to it.

        Keys of :class:`SILPLoss._AcceptedKeys` configure this loss; keys of the
        wrapped loss's ``_AcceptedKeys`` (``action``, ``reward``, ``done``, ...)
        are set on it as well.
        """
        own = self._AcceptedKeys.__dataclass_fields__
        theirs = self.rl_loss._AcceptedKeys.__dataclass_fields__
        unknown = [key for key in kwargs if key not in own and key not in theirs]
        if unknown:
            raise ValueError(f"{unknown} are not accepted keys; accepted: {sorted(set(own) | set(theirs))}")
        forwarded = {key: value for key, value in kwargs.items() if key in theirs}
        if forwarded:
            self.rl_loss.set_keys(**forwarded)
        mine = {key: value for key, value in kwargs.items() if key in own}
        if mine:
            super().set_keys(**mine)
        self._refresh_keys()

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # the value estimator belongs to the wrapped loss: only refresh in_keys
        self._refresh_keys()

    def _refresh_keys(self) -> None:
        # computed now rather than on first use: a first use inside a compiled call sets the attribute
        # dynamo guards on, and the next call would recompile the whole loss (~10 s on a CPU)
        self._in_keys = self._out_keys = None
        if "rl_loss" in self._modules:  # (LossModule.__init__ comes here before the wrapped loss is set)
            _ = self.in_keys, self.out_keys

    @property
    def in_keys(self):
        if self._in_keys is None:
            keys = self.tensor_keys
            own = [keys.is_demo, keys.action, *self.rl_loss.actor_network.in_keys]
            if self.filter == "reward":
                state = list(self.model.state_keys)
                own += [*state, *[("next", key) for key in state], ("next", keys.reward)]
            if self.filter == "q":
                own += list(getattr(self.rl_loss, self._critic_name(self.rl_loss)).in_keys)
            merged = {unravel_key(key) for key in (*self.rl_loss.in_keys, *own)}
            self._in_keys = sorted(merged, key=str)
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values

    @property
    def out_keys(self):
        if self._out_keys is None:
            self._out_keys = [*self.rl_loss.out_keys, "loss_bc", *_DIAGNOSTICS]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values

    # ---------------------------------------------------- value estimator
    def make_value_estimator(self, value_type=None, **hyperparams):
        """Forwarded to the wrapped loss (``gamma`` there is also the reward filter's default)."""
        self.rl_loss.make_value_estimator(value_type, **hyperparams)
        return self

    @property
    def value_estimator(self):
        return self.rl_loss.value_estimator

    @value_estimator.setter
    def value_estimator(self, value):
        # LossModule.__init__ assigns None before rl_loss exists
        if "rl_loss" in self._modules:
            self.rl_loss.value_estimator = value

    @property
    def gamma(self) -> float | torch.Tensor:
        """Discount of the reward filter: the given one, else the wrapped loss's (0.99 without one)."""
        if self._gamma is not None:
            return self._gamma
        try:
            gamma = getattr(self.rl_loss.value_estimator, "gamma", None)
        except (AttributeError, NotImplementedError):
            gamma = None
        if gamma is None:
            return 0.99
        return gamma.detach() if isinstance(gamma, torch.Tensor) else float(gamma)

    # ------------------------------------------------------------- pieces
    @property
    def _actor_action_key(self) -> NestedKey:
        # DDPGLoss has no "action" key of its own: its actor writes ours
        return getattr(self.rl_loss.tensor_keys, "action", self.tensor_keys.action)

    def _policy_action(self, td: TensorDictBase) -> torch.Tensor:
        """The actor's deterministic action ``π(s)`` on ``td``'s rows (differentiable w.r.t. the actor)."""
        rl = self.rl_loss
        actor = rl.actor_network
        td_in = td.select(*actor.in_keys, strict=False)
        with set_exploration_type(ExplorationType.DETERMINISTIC), rl.actor_network_params.to_module(
            actor, preserve_module_state=False
        ):
            td_out = actor(td_in)
        return td_out.get(self._actor_action_key)

    def _actor_inputs(self, state: TensorDictBase) -> TensorDictBase:
        return self.observation_transform(state.clone(False))

    def lookahead_returns(
        self, tensordict: TensorDictBase, policy_action: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The k-step model returns of eq. 7 for every row: ``(R(s, a), R(s, π(s)))``.

        ``R(s, a)`` starts from the stored ``("next", reward)`` and next state;
        ``R(s, π(s))`` from the model's step of the actor's deterministic action.
        Computed without gradient; both shaped like ``tensordict``'s batch.

        Args:
            tensordict: a batch with the keys of :attr:`in_keys`.
            policy_action: ``π(s)`` if already computed; computed otherwise.
        """
        if self.model is None:
            raise ValueError("lookahead_returns needs the model passed to SILPLoss")
        model, keys, shape = self.model, self.tensor_keys, tensordict.shape
        td = tensordict.reshape(-1)
        n = td.shape[0]
        with torch.no_grad():
            pi = self._policy_action(td) if policy_action is None else policy_action.detach().reshape(n, -1)
            s0 = td.select(*model.state_keys)
            r0_demo = td.get(("next", keys.reward)).reshape(n)
            s1_demo = td.get("next").select(*model.state_keys)
            s1_pi, r0_pi = model.step(s0, pi)[:2]
            # both branches advance together as one batch of 2N rows
            state = torch.cat([s1_demo, s1_pi.apply(lambda pi_, demo: pi_.to(demo.dtype), s1_demo)])
            ret = torch.cat([r0_demo, r0_pi.reshape(n).to(r0_demo.dtype)])
            gamma, discount = self.gamma, 1.0
            for _ in range(self.k):  # over the horizon, not the batch
                discount = discount * gamma
                action = self._policy_action(self._actor_inputs(state))
                state, reward = model.step(state, action)[:2]
                ret = ret + discount * reward.reshape(2 * n).to(ret.dtype)
        ret_demo, ret_pi = ret.split(n)
        return ret_demo.reshape(shape), ret_pi.reshape(shape)

    def _q_filter(self, td: TensorDictBase, pi: torch.Tensor) -> torch.Tensor:
        rl, n = self.rl_loss, td.shape[0]
        name = self._critic_name(rl)
        critic = getattr(rl, name)
        params = getattr(rl, f"{name}_params").detach()
        q_td = td.select(*critic.in_keys, strict=False)
        pi_td = q_td.clone(False)
        action_key = self._actor_action_key
        pi_td.set(action_key, pi.to(q_td.get(action_key).dtype))
        both = torch.cat([q_td, pi_td])

        def call(data, p):
            with p.to_module(critic, preserve_module_state=False):
                return critic(data)

        if params.batch_dims:  # a Q ensemble (SAC, TD3): pessimistic minimum
            values = torch.vmap(call, (None, 0), randomness="different")(both, params)
            values = values.get(rl.tensor_keys.state_action_value).reshape(params.batch_size[0], 2 * n).amin(0)
        else:
            values = call(both, params).get(rl.tensor_keys.state_action_value).reshape(2 * n)
        q_demo, q_pi = values.split(n)
        return q_demo > q_pi

    def bc_filter(self, tensordict: TensorDictBase, policy_action: torch.Tensor | None = None) -> torch.Tensor:
        """The filter mask ``R_filter`` (bool, ``tensordict``'s batch shape) of every row, demo or not.

        Args:
            tensordict: a batch with the keys of :attr:`in_keys`.
            policy_action: ``π(s)`` if already computed; computed otherwise.
        """
        shape = tensordict.shape
        td = tensordict.reshape(-1)
        with torch.no_grad():
            if self.filter == "none":
                return torch.ones(shape, dtype=torch.bool, device=td.get(self.tensor_keys.action).device)
            pi = self._policy_action(td) if policy_action is None else policy_action.detach().reshape(td.shape[0], -1)
            if self.filter == "reward":
                ret_demo, ret_pi = self.lookahead_returns(td, pi)
                mask = ret_demo > ret_pi
            else:
                mask = self._q_filter(td, pi)
        return mask.reshape(shape)

    def bc_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The filtered behaviour-cloning term and its diagnostics.

        Returns:
            ``(loss_bc, metadata)``: ``loss_bc = lambda2 · mean over demos of
            filter · ‖π(s) − a‖²`` (0 without demos) and the detached
            ``bc_filter_fraction`` (fraction of demos passing the filter),
            ``bc_mse`` (mean of ``‖π(s) − a‖²`` over demos, unfiltered, unweighted)
            and ``num_demos``, all float scalars.
        """
        keys = self.tensor_keys
        td = tensordict.reshape(-1)
        n = td.shape[0]
        a_demo = td.get(keys.action)
        is_demo = td.get(keys.is_demo, None)
        if is_demo is None:
            raise KeyError(
                f"the batch holds no {keys.is_demo!r} (the demonstration flag, True on demonstration rows): "
                "sample it from MixedReplay or set it, all False for a batch without demonstrations"
            )
        if is_demo.dtype != torch.bool:
            raise TypeError(f"{keys.is_demo!r} must be a bool tensor, got {is_demo.dtype}")
        is_demo = is_demo.reshape(n)
        if self.demo_rows == "select":
            # only the demo rows need the actor's action and the filter's look-ahead:
            # at our default N_D / (N_D + N_pi) = 1/4 (the paper does not state it) that is 4x less model work than
            # masking a full batch (one host sync for the row count)
            rows = is_demo.nonzero().squeeze(-1)
            if rows.numel() == 0:
                zero = torch.zeros((), dtype=a_demo.dtype, device=a_demo.device)
                return zero, {"bc_filter_fraction": zero, "bc_mse": zero, "num_demos": zero}
            demos = td[rows]
            pi = self._policy_action(demos)
            sq_err = (pi - demos.get(keys.action).detach()).pow(2).sum(-1)
            passed = self.bc_filter(demos, pi)
            num_demos = torch.tensor(float(rows.numel()), dtype=sq_err.dtype, device=sq_err.device)
        else:  # every row, the non-demo ones zeroed: no host sync, no shape that depends on the data
            pi = self._policy_action(td)
            sq_err = torch.where(is_demo, (pi - a_demo.detach()).pow(2).sum(-1), 0.0)
            passed = self.bc_filter(td, pi) & is_demo
            num_demos = is_demo.sum().to(sq_err.dtype)
        zero = torch.zeros((), dtype=sq_err.dtype, device=sq_err.device)
        denom = num_demos.clamp_min(1.0)
        loss_bc = self.lambda2.to(sq_err.dtype) * torch.where(passed, sq_err, zero).sum() / denom
        with torch.no_grad():
            metadata = {
                "bc_filter_fraction": passed.sum().to(sq_err.dtype) / denom,
                "bc_mse": sq_err.sum() / denom,
                "num_demos": num_demos,
            }
        return loss_bc, {key: value.detach() for key, value in metadata.items()}

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The wrapped loss's output, its ``loss_*`` terms scaled by ``lambda1``, plus ``loss_bc`` and diagnostics."""
        rl_out = self.rl_loss(tensordict)
        td_out = rl_out.copy()
        for key in rl_out.keys():
            if isinstance(key, str) and key.startswith("loss_"):
                td_out.set(key, self.lambda1.to(rl_out.get(key).dtype) * rl_out.get(key))
        loss_bc, metadata = self.bc_loss(tensordict)
        td_out.set("loss_bc", loss_bc)
        for key, value in metadata.items():
            td_out.set(key, value)
        return td_out
