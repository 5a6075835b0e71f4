"""Gaussian-process-guided recovery from collisions (paper sec. 3.5), as a module run after the actor."""

from __future__ import annotations

import math
import warnings

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.envs.utils import ExplorationType, exploration_type

from torchrl_silp.choices import GP_EXPLORATION_MODES
from torchrl_silp.models.base import TaskModel
from torchrl_silp.validation import check_bool, check_choice, check_positive_float, check_positive_int

__all__ = [
    "GPGuidedExploration",
    "GP_EXPLORATION_MODES",
    "GP_STATE_KEYS",
    "matern52_kernel",
    "gp_posterior",
    "gp_negative_log_marginal_likelihood",
    "gp_nll_gradient",
    "fit_gp_hyperparameters",
]


# the module's per-env state: private root keys of the tensordict (see GPGuidedExploration)
HISTORY_CONFIG_KEY = "_gp_history_config"
HISTORY_REWARD_KEY = "_gp_history_reward"
HISTORY_COUNT_KEY = "_gp_history_count"
PREV_CONFIG_KEY = "_gp_prev_config"
PREV_ACTION_KEY = "_gp_prev_action"
GP_STATE_KEYS = (HISTORY_CONFIG_KEY, HISTORY_REWARD_KEY, HISTORY_COUNT_KEY, PREV_CONFIG_KEY, PREV_ACTION_KEY)

_SQRT5 = math.sqrt(5.0)
# bounds of the fitted hyper-parameters: keep the Gram matrix well conditioned in float32
_LOG_BOUNDS = {
    "lengthscale": (math.log(0.02), math.log(10.0)),
    "outputscale": (math.log(1e-3), math.log(1e3)),
    "noise": (math.log(1e-4), math.log(10.0)),
}


def _param(value, batch_shape: torch.Size, like: torch.Tensor) -> torch.Tensor:
    """A hyper-parameter (scalar or ``batch_shape`` tensor) as a ``(*batch_shape, 1, 1)`` tensor."""
    value = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    return value.expand(batch_shape).reshape(*batch_shape, 1, 1)


def _scaled_distance(x1: torch.Tensor, x2: torch.Tensor) -> torch.Tensor:
    # coordinate by coordinate, not cdist: cdist's matmul shortcut loses the
    # zeros of the diagonal to rounding in float32, and reducing a (..., n, m, 3)
    # difference over its short last dim is 4x slower on CPU
    d2 = None
    for c in range(x1.shape[-1]):
        g = (x1[..., :, c, None] - x2[..., None, :, c]).square()
        d2 = g if d2 is None else d2 + g
    return d2.sqrt()


def matern52_kernel(x1: torch.Tensor, x2: torch.Tensor, lengthscale=1.0, outputscale=1.0) -> torch.Tensor:
    r"""Matérn-5/2 covariance :math:`s^2 (1 + \sqrt5 r/\ell + 5r^2/(3\ell^2)) e^{-\sqrt5 r/\ell}`.

    Args:
        x1: ``(..., n, d)`` inputs.
        x2: ``(..., m, d)`` inputs (batch dims broadcast against ``x1``'s).
        lengthscale: ``ℓ``, a float or a tensor of the batch shape.
        outputscale: ``s²`` (the prior variance), a float or a tensor of the batch shape.

    Returns:
        ``(..., n, m)`` covariances.
    """
    batch = torch.broadcast_shapes(x1.shape[:-2], x2.shape[:-2])
    ls = _param(lengthscale, batch, x1)
    scale = _param(outputscale, batch, x1)
    r = _scaled_distance(x1, x2) / ls
    return scale * (1.0 + _SQRT5 * r + (5.0 / 3.0) * r.square()) * torch.exp(-_SQRT5 * r)


def _masked_system(train_x, train_y, mask, lengthscale, outputscale, noise):
    # Padded history rows become identity rows with y = 0: they add nothing to
    # the posterior or to the marginal likelihood, so histories of different
    # lengths share one batched Cholesky.
    n = train_x.shape[-2]
    batch = train_x.shape[:-2]
    eye = torch.eye(n, dtype=train_x.dtype, device=train_x.device)
    k = matern52_kernel(train_x, train_x, lengthscale, outputscale)
    ky = k + _param(noise, batch, train_x) * eye
    if mask is None:
        return ky, train_y, None
    pair = mask.unsqueeze(-1) & mask.unsqueeze(-2)
    ky = torch.where(pair, ky, eye)
    return ky, torch.where(mask, train_y, torch.zeros_like(train_y)), mask


def _cholesky(ky: torch.Tensor) -> torch.Tensor:
    chol, info = torch.linalg.cholesky_ex(ky)
    # a near-singular Gram matrix (repeated states, tiny noise) is retried
    # with growing jitter; the common case costs one factorisation
    jitter = ky.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1.0) * 1e-6
    eye = torch.eye(ky.shape[-1], dtype=ky.dtype, device=ky.device)
    for _ in range(3):
        bad = info != 0
        if not bad.any():
            break
        retry, info_retry = torch.linalg.cholesky_ex(ky + jitter[..., None, None] * eye)
        chol = torch.where(bad[..., None, None], retry, chol)
        info = torch.where(bad, info_retry, info)
        jitter = jitter * 100
    return chol


def gp_posterior(
    train_x: torch.Tensor,
    train_y: torch.Tensor,
    test_x: torch.Tensor,
    *,
    lengthscale=1.0,
    outputscale=1.0,
    noise=1e-2,
    mask: torch.Tensor | None = None,
    return_var: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    r"""Exact zero-mean GP regression with a Matérn-5/2 kernel, batched.

    :math:`\mu(x) = k_n(x)^T (K_n + \sigma^2 I)^{-1} y_n`,
    :math:`\sigma^2(x) = k(x, x) - k_n(x)^T (K_n + \sigma^2 I)^{-1} k_n(x)`
    (the paper's eq. in sec. 3.5), one GP per batch element, through one
    batched Cholesky factorisation.

    Args:
        train_x: ``(..., n, d)`` observed inputs.
        train_y: ``(..., n)`` observed outputs.
        test_x: ``(..., m, d)`` query inputs.
        lengthscale, outputscale, noise: ``ℓ``, ``s²``, ``σ²``: floats or
            tensors of the batch shape.
        mask: optional bool ``(..., n)``: which training rows are real (the rest is padding).
        return_var: also return the posterior variance of ``f``.

    Returns:
        ``(mean, var)``, each ``(..., m)`` (``var`` is None unless ``return_var``).

    Examples:
        >>> import torch
        >>> x = torch.tensor([[0.0], [1.0]])
        >>> mean, var = gp_posterior(x, torch.tensor([1.0, -1.0]), x, noise=1e-6)
        >>> torch.allclose(mean, torch.tensor([1.0, -1.0]), atol=1e-4)
        True
    """
    ky, y, mask = _masked_system(train_x, train_y, mask, lengthscale, outputscale, noise)
    chol = _cholesky(ky)
    alpha = torch.cholesky_solve(y.unsqueeze(-1), chol)  # (..., n, 1)
    k_star = matern52_kernel(train_x, test_x, lengthscale, outputscale)  # (..., n, m)
    if mask is not None:
        k_star = k_star * mask.unsqueeze(-1).to(k_star.dtype)
    mean = (k_star * alpha).sum(-2)
    if not return_var:
        return mean, None
    v = torch.linalg.solve_triangular(chol, k_star, upper=False)
    prior = _param(outputscale, train_x.shape[:-2], train_x).squeeze(-1)  # k(x, x) = s²
    var = (prior - v.square().sum(-2)).clamp_min(0.0)
    return mean, var


def gp_negative_log_marginal_likelihood(
    train_x: torch.Tensor,
    train_y: torch.Tensor,
    *,
    lengthscale=1.0,
    outputscale=1.0,
    noise=1e-2,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    r""":math:`\tfrac12 y^T K_y^{-1} y + \tfrac12 \log|K_y| + \tfrac n2 \log 2\pi` per batch element, ``(...)``.

    Padded rows (``mask`` False) do not count. Differentiable in the hyper-parameters.
    """
    ky, y, mask = _masked_system(train_x, train_y, mask, lengthscale, outputscale, noise)
    chol = _cholesky(ky)
    alpha = torch.cholesky_solve(y.unsqueeze(-1), chol).squeeze(-1)
    n = train_x.shape[-2] if mask is None else mask.sum(-1).to(train_x.dtype)
    log_det = chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    return 0.5 * (y * alpha).sum(-1) + log_det + 0.5 * n * math.log(2 * math.pi)


def gp_nll_gradient(
    train_x: torch.Tensor,
    train_y: torch.Tensor,
    *,
    lengthscale,
    outputscale,
    noise,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""Closed-form gradient of :func:`gp_negative_log_marginal_likelihood` w.r.t. the log hyper-parameters.

    :math:`\partial_\theta \mathrm{NLL} = \frac12 \mathrm{tr}((K_y^{-1} - \alpha\alpha^T)\,\partial_\theta K_y)`
    with :math:`\alpha = K_y^{-1} y`, for :math:`\theta = \log\ell, \log s^2, \log\sigma^2`:
    one Cholesky and one inverse per GP, 3-10x cheaper on CPU than
    back-propagating through the factorisation. Returns three tensors of the batch shape.
    """
    batch = train_x.shape[:-2]
    n = train_x.shape[-2]
    ls = _param(lengthscale, batch, train_x)
    scale = _param(outputscale, batch, train_x)
    nz = _param(noise, batch, train_x)
    r = _scaled_distance(train_x, train_x) / ls
    decay = torch.exp(-_SQRT5 * r)
    k = scale * (1.0 + _SQRT5 * r + (5.0 / 3.0) * r.square()) * decay
    eye = torch.eye(n, dtype=train_x.dtype, device=train_x.device)
    ky = k + nz * eye
    y = train_y
    if mask is not None:
        pair = mask.unsqueeze(-1) & mask.unsqueeze(-2)
        ky = torch.where(pair, ky, eye)
        y = torch.where(mask, train_y, torch.zeros_like(train_y))
    chol = _cholesky(ky)
    alpha = torch.cholesky_solve(y.unsqueeze(-1), chol)
    w = torch.cholesky_inverse(chol) - alpha * alpha.transpose(-1, -2)
    d_ls = scale * (5.0 / 3.0) * r.square() * (1.0 + _SQRT5 * r) * decay  # dk / dlog(l)
    d_noise = nz * eye
    if mask is not None:
        # padded rows are identity rows that no hyper-parameter touches
        d_ls, k, d_noise = (torch.where(pair, d, torch.zeros_like(d)) for d in (d_ls, k, d_noise))
    return tuple(0.5 * (w * d).sum((-1, -2)) for d in (d_ls, k, d_noise))


def fit_gp_hyperparameters(
    train_x: torch.Tensor,
    train_y: torch.Tensor,
    *,
    lengthscale=1.0,
    outputscale=1.0,
    noise=1e-2,
    mask: torch.Tensor | None = None,
    steps: int = 10,
    lr: float = 0.1,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A few Adam steps on the log marginal likelihood, every GP of the batch at once.

    Starts from the given values, optimises their logs with the closed-form
    gradient of :func:`gp_nll_gradient` (projected onto broad bounds that keep
    float32 Cholesky factorisations stable) and returns
    ``(lengthscale, outputscale, noise)``, each of the batch shape.
    """
    batch = train_x.shape[:-2]
    f = dict(dtype=train_x.dtype, device=train_x.device)
    bounds = [_LOG_BOUNDS[name] for name in ("lengthscale", "outputscale", "noise")]
    logs = [
        torch.as_tensor(v, **f).expand(batch).log().clamp(lo, hi).clone()
        for v, (lo, hi) in zip((lengthscale, outputscale, noise), bounds)
    ]
    optim = torch.optim.Adam(logs, lr=lr)
    x, y = train_x.detach(), train_y.detach()
    with torch.no_grad():
        for _ in range(steps):
            grads = gp_nll_gradient(
                x, y, lengthscale=logs[0].exp(), outputscale=logs[1].exp(), noise=logs[2].exp(), mask=mask
            )
            for p, g in zip(logs, grads):
                p.grad = g
            optim.step()
            for p, (lo, hi) in zip(logs, bounds):
                p.clamp_(lo, hi)
    return tuple(p.exp() for p in logs)


def _flat(value: torch.Tensor, batch: torch.Size, m: int) -> torch.Tensor:
    """``value`` ``(*batch, *rest)`` as ``(m, *rest)``."""
    return value.reshape(m, *value.shape[len(batch):])


class GPGuidedExploration(TensorDictModuleBase):
    """After a collision, choose the recovery action with a GP model of the episode's rewards.

    The paper's GP-guided exploration (sec. 3.5), as a module placed after the
    actor (``TensorDictSequential(actor, gp)``), in the manner of TorchRL's
    :class:`~torchrl.modules.OrnsteinUhlenbeckProcessModule`. It works on any
    :class:`~torchrl_silp.models.TaskModel` and reads only named keys: the
    model's state keys (:attr:`TaskModel.state_keys`: the configuration
    ``"joint_position"``, ``"achieved_goal"``, the scene keys, ``"desired_goal"``),
    the previous step's collision flag (``"collision"``, an observation of
    :class:`~torchrl_silp.envs.reach.ReachEnv` that ``step_mdp`` carries to the
    root), ``"is_init"`` (from :class:`~torchrl.envs.InitTracker`) and the
    action. When the exploration type is ``RANDOM`` (or unset) and the env's
    previous step collided, it

    1. fits a zero-mean GP with a Matérn-5/2 kernel to the episode so far:
       visited configurations -> rewards, the colliding configuration included;
    2. draws ``num_candidates`` actions uniform in ``[-1, 1]^A`` and their next
       states ``model.transition(state, a)``;
    3. predicts each candidate's reward with the posterior mean, min-max scales
       the predictions to ``[0, 1]`` and normalises them to sum 1 (uniform if all
       are equal). With ``mask_colliding_candidates=True`` (the default, ours)
       candidates whose motion collides (:meth:`TaskModel.motion_collision_flags`,
       the check the env applies to a step) get probability 0 whenever one of them
       is collision-free; with ``False`` (the paper's recovery) all candidates
       keep their GP probability and none is collision-checked;
    4. samples one candidate and outputs its action.

    Otherwise the actor's action passes through untouched, and in
    ``DETERMINISTIC``/``MEAN``/``MODE`` exploration the module does nothing at
    all. ``mode="random"`` is the paper's no-GP ablation: a uniformly random
    candidate (collision-free when masking).

    Per-env state lives in the TensorDict, not in the module, so one module
    serves any number of envs, batched envs and collector workers. It reads and
    writes five private root keys (batch shape ``B``, history ``H``, configuration
    size ``D``, action size ``A``):

    * ``"_gp_history_config"`` ``[B, H, D]`` and ``"_gp_history_reward"`` ``[B, H]``:
      a ring buffer of the episode's visited configurations and their rewards
      (push ``i`` in slot ``i mod H``; slots not yet written are zero);
    * ``"_gp_history_count"`` ``[B, 1]`` (long): pushes since the episode began;
    * ``"_gp_prev_config"`` ``[B, D]``, ``"_gp_prev_action"`` ``[B, A]``: the
      configuration the last call saw and the action it output.

    Absent keys (or a zero count) mean a fresh episode. The module writes the
    updated values back to the root; for them to reach the next step, append
    :meth:`make_tensordict_primer` to the env: its
    :class:`~torchrl.envs.TensorDictPrimer` declares them as observations, so
    the env copies them to ``"next"``, ``step_mdp`` brings them back to the root
    and batched envs and collectors carry them (as TorchRL's recurrent modules
    do). A row's history restarts where ``"is_init"`` is True; nothing else
    (goals, obstacles) is compared. TorchRL's collectors drop ``"_"`` keys from
    the batches they yield, so the histories stay out of replay buffers;
    :meth:`~torchrl.envs.EnvBase.rollout` keeps them (about ``4 (D + 1) H``
    bytes per frame in float32, twice with ``"next"``).

    Under a multi-process collector each worker holds its own copy of the
    policy, the (picklable) task model with it, and its envs' histories travel
    in their own TensorDicts.

    At each call the module records, per env, the state the previous action led
    to: the current one, or, after a collision (when the env put the arm back),
    the colliding one ``model.transition(prev_state, prev_action)``, where
    ``prev_state`` is the current state with the previous configuration; its
    reward is ``model.score`` of the env's collision flag and that state's
    achieved goal (``step_mdp`` drops ``("next", "reward")`` from the root, so it
    is recomputed; without a collision flag in the tensordict, from
    ``model.outcome(prev_state, that_state)``, the motion checked again). The first state
    of an episode is recorded with ``model.goal_reward(achieved, desired)``, the
    task's reward for being there. Cost outside recoveries: one transition of
    the batch per call; a recovery adds the candidates'
    transitions, their motion checks when masking (``R·n`` motions of up to one
    action each: the bulk of a recovery's cost) and the GP solve. All envs
    are handled at once: the collided envs' GPs share one batched Cholesky of
    ``[R, H, H]``, histories of different lengths padded with identity rows; no
    Python loop runs over the batch, and one host sync per call decides whether
    any env needs a recovery.

    Default hyper-parameters: ``ℓ = 0.3`` rad, a little more than the reach of
    one UR5e action (``0.125·√3 ≈ 0.22`` rad), so a recorded collision lowers
    the predictions of the candidates next to it, not of the whole
    neighbourhood; ``s² = 1``; ``σ² = 0.01`` (rewards are exact, the noise keeps
    revisited states well conditioned). With the zero prior mean, unvisited
    regions are predicted near 0, above the usual ``-distance`` rewards, so the
    choice also leans towards unexplored directions.

    The GP is plain torch (:func:`gp_posterior`, :func:`fit_gp_hyperparameters`),
    not gpytorch: ``benchmarks/gp_exploration.py`` times both on the work of one
    recovery (it prints both figures), and plain torch was faster at
    these sizes and adds no dependency.

    Args:
        model: the :class:`~torchrl_silp.models.TaskModel` the env steps (e.g.
            ``env.model`` of an env holding one). Kept as a plain
            reference, not a sub-module: ``.to()`` on the module does not move it.

    Keyword Args:
        mode: ``"gp"`` (default) or ``"random"``.
        num_candidates: candidate actions per recovery, ``>= 1`` (paper: n).
        history_size: ring-buffer length ``H`` per env, ``>= 1`` (default 64; an
            episode of 50 steps fits).
        lengthscale, outputscale, noise: the Matérn-5/2 ``ℓ`` (rad), the prior
            variance ``s²`` and the noise ``σ²``, all ``> 0``.
        fit_hyperparameters: refine ``ℓ, s², σ²`` per env by ``fit_steps`` Adam
            steps (rate ``fit_lr``) on the log marginal likelihood, starting from
            the values above, at every recovery.
        fit_steps, fit_lr: see ``fit_hyperparameters``.
        action_key, collision_key, is_init_key: tensordict keys.
        generator: a ``torch.Generator`` on the model's device for the candidate
            draws and the choice; the global one by default.
        mask_colliding_candidates: give colliding candidates probability 0 when a
            free one exists (default, ours); ``False`` is the paper's recovery.

    Attributes:
        last_recovery: for debugging and plots, the last call's recovery in this
            process (None before the first): a TensorDict ``[R]`` of the collided
            rows' ``env_index`` (into the flattened batch) and their
            ``candidate_action`` ``[R, n, A]``, ``candidate_config`` ``[R, n, D]``,
            ``probability`` ``[R, n]``, chosen ``action`` ``[R, A]`` and, when
            masking, ``collides`` ``[R, n]``.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictSequential
        >>> from torchrl.envs import Compose, InitTracker, TransformedEnv
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> from torchrl.modules import Actor
        >>> from torchrl_silp import CollisionHandling, ReachEnv, UR5eReach
        >>> from torchrl_silp.modules import GPGuidedExploration
        >>> model = UR5eReach()
        >>> gp = GPGuidedExploration(model, generator=torch.Generator().manual_seed(0))
        >>> env = TransformedEnv(ReachEnv(model, num_envs=4, seed=0), Compose(
        ...     CollisionHandling(2), model.observation_transform(), InitTracker(), gp.make_tensordict_primer()))
        >>> _ = torch.manual_seed(0)
        >>> actor = Actor(torch.nn.Sequential(torch.nn.Linear(15, 3), torch.nn.Tanh()), in_keys=["observation"])
        >>> policy = TensorDictSequential(actor, gp)
        >>> with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        ...     rollout = env.rollout(20, policy, break_when_any_done=False)
        >>> rollout["_gp_history_config"].shape
        torch.Size([4, 20, 64, 3])
        >>> bool((rollout["action"].abs() <= 1).all())
        True
    """

    def __init__(
        self,
        model: TaskModel,
        *,
        mode: str = "gp",
        num_candidates: int = 64,
        history_size: int = 64,
        lengthscale: float = 0.3,
        outputscale: float = 1.0,
        noise: float = 1e-2,
        fit_hyperparameters: bool = False,
        fit_steps: int = 10,
        fit_lr: float = 0.1,
        action_key: NestedKey = "action",
        collision_key: NestedKey = "collision",
        is_init_key: NestedKey = "is_init",
        generator: torch.Generator | None = None,
        mask_colliding_candidates: bool = True,
    ):
        if not isinstance(model, TaskModel):
            raise TypeError(f"model must be a torchrl_silp.models.TaskModel, got {type(model).__name__}")
        check_choice(mode, GP_EXPLORATION_MODES, name="mode")
        counts = (("num_candidates", num_candidates), ("history_size", history_size), ("fit_steps", fit_steps))
        for name, value in counts:
            check_positive_int(value, name=name)
        scales = (("lengthscale", lengthscale), ("outputscale", outputscale), ("noise", noise), ("fit_lr", fit_lr))
        for name, value in scales:
            check_positive_float(value, name=name)
        check_bool(fit_hyperparameters, name="fit_hyperparameters")
        check_bool(mask_colliding_candidates, name="mask_colliding_candidates")
        if generator is not None and not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
        super().__init__()
        # a plain reference: registering the model would move and save it with the policy
        self.__dict__["model"] = model
        self.mode = mode
        self.num_candidates = num_candidates
        self.history_size = history_size
        self.lengthscale = float(lengthscale)
        self.outputscale = float(outputscale)
        self.noise = float(noise)
        self.fit_hyperparameters = fit_hyperparameters
        self.fit_steps = fit_steps
        self.fit_lr = float(fit_lr)
        self.action_key = action_key
        self.collision_key = collision_key
        self.is_init_key = is_init_key
        self.generator = generator
        self.mask_colliding_candidates = mask_colliding_candidates
        self.last_recovery: TensorDict | None = None
        self._warned: set[str] = set()
        self.in_keys = [*model.state_keys, collision_key, is_init_key, action_key, *GP_STATE_KEYS]
        self.out_keys = [action_key, *GP_STATE_KEYS]

    # -------------------------------------------------------------- state
    def make_tensordict_primer(self) -> TensorDictPrimer:
        """The :class:`~torchrl.envs.TensorDictPrimer` declaring the module's per-env keys; append it to the env.

        Specs are unbatched and expanded to the env's batch (``expand_specs=True``);
        a reset fills the reset rows with zeros (a fresh episode).
        """
        model = self.model
        f = dict(dtype=model.dtype, device=model.device)
        return TensorDictPrimer(
            {
                HISTORY_CONFIG_KEY: Unbounded(shape=(self.history_size, model.config_dim), **f),
                HISTORY_REWARD_KEY: Unbounded(shape=(self.history_size,), **f),
                HISTORY_COUNT_KEY: Unbounded(shape=(1,), dtype=torch.long, device=model.device),
                PREV_CONFIG_KEY: Unbounded(shape=(model.config_dim,), **f),
                PREV_ACTION_KEY: Unbounded(shape=(model.action_dim,), **f),
            },
            expand_specs=True,
        )

    def _warn_once(self, what: str, message: str) -> None:
        if what not in self._warned:
            self._warned.add(what)
            warnings.warn(message, stacklevel=3)

    def _flag(self, tensordict: TensorDictBase, key: NestedKey, m: int, device) -> torch.Tensor | None:
        value = tensordict.get(key, None)
        if value is None:
            return None
        if value.numel() != m:
            raise ValueError(f"{key!r} must hold one flag per env ({m}), got shape {tuple(value.shape)}")
        return value.reshape(m).to(device=device, dtype=torch.bool)

    def _read_memory(self, tensordict, batch, m, like: torch.Tensor, action_dim: int):
        H, D = self.history_size, like.shape[-1]
        f = dict(dtype=like.dtype, device=like.device)
        shapes = {
            HISTORY_CONFIG_KEY: ((H, D), f),
            HISTORY_REWARD_KEY: ((H,), f),
            HISTORY_COUNT_KEY: ((1,), dict(dtype=torch.long, device=like.device)),
            PREV_CONFIG_KEY: ((D,), f),
            PREV_ACTION_KEY: ((action_dim,), f),
        }
        out, missing = {}, []
        for key, (shape, kw) in shapes.items():
            value = tensordict.get(key, None)
            if value is None:
                missing.append(key)
                value = torch.zeros(m, *shape, **kw)
            else:
                if tuple(value.shape) != (*batch, *shape):
                    raise ValueError(
                        f"{key!r} must have shape {(*batch, *shape)} (history_size={H}), got {tuple(value.shape)}: "
                        "was the primer made by a module with another history_size?"
                    )
                value = value.reshape(m, *shape).to(**kw)
            out[key] = value
        return out, missing

    # ----------------------------------------------------------- recovery
    def candidate_probabilities(
        self,
        history_config: torch.Tensor,
        history_reward: torch.Tensor,
        history_mask: torch.Tensor,
        candidate_config: torch.Tensor,
        collides: torch.Tensor,
    ) -> torch.Tensor:
        """Sampling probabilities ``(R, n)`` of the candidates ``candidate_config`` ``(R, n, D)``.

        GP mode: posterior mean on the history, min-max scaled over the allowed
        candidates and normalised; uniform over the allowed ones if their
        predictions are all equal. Random mode: uniform over the allowed
        candidates. Allowed: the collision-free ones when masking and there are
        some, else all.

        Args:
            history_config, history_reward, history_mask: ``(R, H, D)``, ``(R, H)``,
                bool ``(R, H)``: the episodes' visited configurations, rewards, valid slots.
            candidate_config: ``(R, n, D)`` candidate configurations.
            collides: bool ``(R, n)``: which candidates' motions collide.
        """
        allowed = torch.ones_like(collides)
        if self.mask_colliding_candidates:
            free = ~collides
            allowed = torch.where(free.any(-1, keepdim=True), free, allowed)
        uniform = allowed.to(candidate_config.dtype)
        if self.mode == "random":
            return uniform / uniform.sum(-1, keepdim=True)
        ls, scale, nz = self.lengthscale, self.outputscale, self.noise
        if self.fit_hyperparameters:
            ls, scale, nz = fit_gp_hyperparameters(
                history_config, history_reward, lengthscale=ls, outputscale=scale, noise=nz,
                mask=history_mask, steps=self.fit_steps, lr=self.fit_lr,
            )
        mean, _ = gp_posterior(
            history_config, history_reward, candidate_config, lengthscale=ls, outputscale=scale, noise=nz,
            mask=history_mask, return_var=False,
        )
        inf = torch.full_like(mean, math.inf)
        lo = torch.where(allowed, mean, inf).amin(-1, keepdim=True)
        hi = torch.where(allowed, mean, -inf).amax(-1, keepdim=True)
        span = hi - lo
        # equal predictions (or a failed solve) fall back to uniform
        flat = ~(span > 1e-6 * (hi.abs() + lo.abs() + 1.0)) | ~torch.isfinite(span)
        scaled = torch.where(allowed, (mean - lo) / torch.where(flat, torch.ones_like(span), span), 0.0)
        probs = torch.where(flat, uniform, scaled.clamp(0.0, 1.0))
        return probs / probs.sum(-1, keepdim=True)

    def _record(self, state: TensorDict, memory: dict, fresh: torch.Tensor, collided: torch.Tensor,
                collision_seen: bool):
        """Push the state the previous action led to, and its reward, into the ring buffers.

        ``collision_seen``: ``collided`` is the env's collision flag of the previous motion (else that
        motion is checked here)."""
        model, H = self.model, self.history_size
        ck, ak = model.config_key, model.achieved_goal_key
        config, achieved, desired = state.get(ck), state.get(ak), state.get(model.desired_goal_key)
        # a fresh row's "previous" configuration is its current one: a zero-length motion
        prev_config = torch.where(fresh.unsqueeze(-1), config, memory[PREV_CONFIG_KEY])
        prev_state = model.state_at(prev_config, state.select(*model.scene_keys), desired)
        # after a collision the env put the arm back: the colliding state is recomputed
        moved = model.transition(prev_state, memory[PREV_ACTION_KEY])
        hit = collided.unsqueeze(-1)
        led_to = state.clone(False)
        led_to.set(ck, torch.where(hit, moved.get(ck).to(config.dtype), config))
        led_to.set(ak, torch.where(hit, moved.get(ak).to(achieved.dtype), achieved))
        if collision_seen:
            # the env's flag is the motion check of this very motion: scored, not checked again
            reward = model.score(collided.unsqueeze(-1), led_to.get(ak), desired)[0]
        else:
            reward = model.outcome(prev_state, led_to)[0]
        reward = torch.where(fresh.unsqueeze(-1), model.goal_reward(achieved, desired), reward).squeeze(-1)

        count = torch.where(fresh, torch.zeros_like(memory[HISTORY_COUNT_KEY].squeeze(-1)),
                            memory[HISTORY_COUNT_KEY].squeeze(-1))
        keep = ~fresh
        hist_x = torch.where(keep[:, None, None], memory[HISTORY_CONFIG_KEY], 0.0)
        hist_r = torch.where(keep[:, None], memory[HISTORY_REWARD_KEY], 0.0)
        slot = torch.nn.functional.one_hot(count % H, H).bool()
        hist_x = torch.where(slot.unsqueeze(-1), led_to.get(ck).unsqueeze(-2).to(hist_x.dtype), hist_x)
        hist_r = torch.where(slot, reward.unsqueeze(-1).to(hist_r.dtype), hist_r)
        return hist_x, hist_r, count + 1

    def _recovery_actions(self, state, rows, hist_x, hist_r, count) -> torch.Tensor:
        model, r, n, H = self.model, rows.numel(), self.num_candidates, self.history_size
        sub = state[rows]
        config = sub.get(model.config_key)
        actions = torch.rand(
            r, n, model.action_dim, generator=self.generator, dtype=config.dtype, device=config.device
        ) * 2 - 1
        expanded = sub.unsqueeze(1).expand(r, n)
        candidate = model.transition(expanded, actions).get(model.config_key)
        if self.mask_colliding_candidates:
            flags, _ = model.motion_collision_flags(
                config.unsqueeze(1).expand_as(candidate), candidate, expanded.select(*model.scene_keys)
            )
            collides = flags.squeeze(-1) != 0
        else:
            # the paper's recovery does not look at the candidates' collisions: no check to pay for
            collides = torch.zeros(r, n, dtype=torch.bool, device=config.device)
        valid = torch.arange(H, device=config.device) < count[rows].clamp_max(H).unsqueeze(-1)
        probs = self.candidate_probabilities(hist_x[rows], hist_r[rows], valid, candidate, collides)
        pick = torch.multinomial(probs, 1, generator=self.generator).squeeze(-1)
        chosen = actions[torch.arange(r, device=config.device), pick]
        self.last_recovery = TensorDict(
            env_index=rows, candidate_action=actions, candidate_config=candidate, probability=probs,
            action=chosen, batch_size=[r],
        )
        if self.mask_colliding_candidates:
            self.last_recovery.set("collides", collides)
        return chosen

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if exploration_type() not in (ExplorationType.RANDOM, None):
            return tensordict
        model = self.model
        config_in = tensordict.get(model.config_key)
        batch = config_in.shape[:-1]
        m = batch.numel()
        device = config_in.device
        state = TensorDict({k: _flat(tensordict.get(k), batch, m) for k in model.state_keys}, batch_size=[m])
        action_in = tensordict.get(self.action_key)
        action = action_in.reshape(m, action_in.shape[-1])
        memory, missing = self._read_memory(tensordict, batch, m, state.get(model.config_key), model.action_dim)

        is_init = self._flag(tensordict, self.is_init_key, m, device)
        if is_init is None:
            self._warn_once(
                "is_init",
                f"GPGuidedExploration: no {self.is_init_key!r} in the tensordict, so episode starts are not seen "
                "(histories run across resets); add torchrl.envs.InitTracker() to the env.",
            )
            is_init = torch.zeros(m, dtype=torch.bool, device=device)
        if missing and not bool(is_init.all()):
            self._warn_once(
                "primer",
                f"GPGuidedExploration: {missing} missing from the tensordict outside an episode start: append "
                "gp.make_tensordict_primer() to the env, or every step looks like the first of an episode.",
            )
        collision = self._flag(tensordict, self.collision_key, m, device)
        collision_seen = collision is not None
        if not collision_seen:
            collision = torch.zeros(m, dtype=torch.bool, device=device)
        fresh = is_init | (memory[HISTORY_COUNT_KEY].squeeze(-1) == 0)
        collided = collision & ~fresh

        with torch.no_grad():
            hist_x, hist_r, count = self._record(state, memory, fresh, collided, collision_seen)
            # one host sync decides whether any GP work is needed this step
            rows = collided.nonzero().squeeze(-1) if bool(collided.any()) else None
            chosen = None if rows is None else self._recovery_actions(state, rows, hist_x, hist_r, count)
        if rows is not None:
            # outside no_grad: the passed-through rows keep the actor's graph
            action = action.index_copy(0, rows, chosen.to(action.dtype))
            tensordict.set(self.action_key, action.reshape(action_in.shape))

        H, D = self.history_size, config_in.shape[-1]
        tensordict.set(HISTORY_CONFIG_KEY, hist_x.reshape(*batch, H, D))
        tensordict.set(HISTORY_REWARD_KEY, hist_r.reshape(*batch, H))
        tensordict.set(HISTORY_COUNT_KEY, count.reshape(*batch, 1))
        tensordict.set(PREV_CONFIG_KEY, config_in.detach().clone())
        tensordict.set(PREV_ACTION_KEY, action.detach().to(config_in.dtype).reshape(*batch, -1).clone())
        return tensordict
