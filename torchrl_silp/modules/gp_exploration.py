"""Gaussian-process-guided recovery from collisions (paper sec. 3.5), as a module run after the actor."""

from __future__ import annotations

import math

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, exploration_type

__all__ = [
    "GPGuidedExploration",
    "GP_EXPLORATION_MODES",
    "matern52_kernel",
    "gp_posterior",
    "gp_negative_log_marginal_likelihood",
    "gp_nll_gradient",
    "fit_gp_hyperparameters",
]

GP_EXPLORATION_MODES = ("gp", "random")

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


class GPGuidedExploration(TensorDictModuleBase):
    """After a collision, choose the recovery action with a GP model of the episode's rewards.

    The paper's GP-guided exploration (sec. 3.5), as a module placed after
    the actor (``TensorDictSequential(actor, GPGuidedExploration(env))``),
    in the manner of :class:`~torchrl.modules.OrnsteinUhlenbeckProcessModule`.
    When the exploration type is ``RANDOM`` (or unset) and the env's previous
    step collided (the ``"collision"`` entry, which ``UR5eReachEnv`` declares
    as an observation so ``step_mdp`` carries it to the root), it

    1. fits a zero-mean GP with a Matérn-5/2 kernel to the episode so far:
       visited joint states ``q`` (3-D) -> rewards, collision states included;
    2. draws ``num_candidates`` actions uniform in ``[-1, 1]^3`` and their
       next configurations ``env.transition(obs, a)`` (``q + 0.125 a``,
       clipped to the joint limits);
    3. predicts each candidate's reward with the posterior mean, min-max
       scales the predictions to ``[0, 1]`` and normalises them to sum 1
       (uniform if all are equal); candidates that ``env.collides`` get
       probability 0 whenever one candidate is collision-free;
    4. samples one candidate and outputs its action.

    Otherwise the actor's action passes through untouched (and in
    ``DETERMINISTIC``/``MEAN``/``MODE`` exploration the module does nothing at
    all). ``mode="random"`` is the paper's no-GP ablation: a uniformly random
    collision-free candidate.

    All envs of the batch are handled at once: the collided envs' GPs share
    one batched Cholesky of ``[B, H, H]``, histories of different lengths
    padded with identity rows; no Python loop runs over the batch.

    Episode history: the module keeps, per env, a ring buffer of the last
    ``history_size`` visited states and their rewards (in non-persistent
    buffers, shaped on the first call and re-shaped if the batch changes).
    A policy module sees only the current step's root tensordict, so at each
    call it records the state the previous action led to: the current
    observation, or, after a collision (when the env put the arm back), the
    colliding configuration ``env.transition(prev_obs, prev_action)``; and its
    reward, recomputed as ``env.reward(prev_obs, that_state)`` because
    ``step_mdp`` drops ``("next", "reward")`` from the root (pass
    ``reward_key`` to read a root entry instead; this saves one
    ``env.reward`` evaluation of the batch per step). The first state of an
    episode is recorded with ``env.reward(obs, obs)``, the task's reward for
    being there. A row's history is cleared when ``"is_init"`` or ``"done"``
    is set, or when its goal or obstacle changed (a reset without an
    ``InitTracker``). Cost outside recoveries: one ``env.transition`` and one
    ``env.reward`` of the batch per call; a recovery adds the candidates'
    ``transition`` and ``collides`` (``R·n`` configurations) and the GP solve.

    Default hyper-parameters: ``ℓ = 0.3`` rad, a little more than the reach
    of one action (``0.125·√3 ≈ 0.22`` rad), so a recorded collision lowers
    the predictions of the candidates next to it, not of the whole
    neighbourhood; ``s² = 1``; ``σ² = 0.01`` (rewards are exact, the noise
    keeps revisited states well conditioned). With the zero prior mean,
    unvisited regions are predicted near 0, above the usual ``-distance``
    rewards, so the choice also leans towards unexplored directions.

    GP library: plain torch, not gpytorch, chosen by
    ``benchmarks/gp_exploration.py`` (fit + posterior mean of B GPs, 50
    history points, 64 candidates, float32, CPU, 1 thread; docs/results.md):

    ============================  ==========  =============
    B, hyper-parameters           torch (ms)  gpytorch (ms)
    ============================  ==========  =============
    1, fixed                      0.62        11.1
    64, fixed                     5.1         23.9
    1, fitted (10 Adam steps)     12.8        51.5
    64, fitted (10 Adam steps)    74.4        124
    ============================  ==========  =============

    Torch is 4.7-18x faster with fixed hyper-parameters (the default) and
    1.7-4x faster when fitting (with the closed-form gradient of
    :func:`gp_nll_gradient`; back-propagating through the Cholesky instead
    was slower than gpytorch at B=64). At 50 points the exact solve is all the
    work there is, and gpytorch's lazy-operator machinery, built for large n,
    is overhead; torch also adds no dependency.

    Args:
        env: the task model: needs ``transition(obs, action)``,
            ``reward(obs, next_obs)`` and ``collides(q3, obstacle)``
            (a :class:`~torchrl_silp.UR5eReachEnv`). Kept as a plain
            reference, not a sub-module.

    Keyword Args:
        mode: ``"gp"`` (default) or ``"random"``.
        num_candidates: candidate actions per recovery, ``>= 1`` (paper: n).
        history_size: ring-buffer length per env, ``>= 1`` (default 64; an episode of
            the paper's 50 steps fits).
        lengthscale, outputscale, noise: the Matérn-5/2 ``ℓ`` (rad), the
            prior variance ``s²`` and the noise ``σ²``, all ``> 0``.
        fit_hyperparameters: refine ``ℓ, s², σ²`` per env by ``fit_steps``
            Adam steps (rate ``fit_lr``) on the log marginal likelihood,
            starting from the values above, at every recovery.
        fit_steps, fit_lr: see ``fit_hyperparameters``.
        action_key, observation_key, collision_key, is_init_key, done_key:
            tensordict keys.
        reward_key: a root key holding the previous transition's reward, if
            the pipeline provides one; ``None`` (default) recomputes it.
        generator: a ``torch.Generator`` on the env's device for the candidate
            draws; the global one by default.

    Attributes:
        last_recovery: the last recovery step, for inspection and plots (None
            before the first): a TensorDict ``[R]`` of the collided envs'
            ``env_index`` and their ``candidate_action`` ``[R, n, 3]``,
            ``candidate_q`` ``[R, n, 3]``, ``collides`` ``[R, n]``,
            ``probability`` ``[R, n]`` and chosen ``action`` ``[R, 3]``.
        history: see the property.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictSequential
        >>> from torchrl.envs import InitTracker, TransformedEnv
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> from torchrl.modules import Actor
        >>> from torchrl_silp import UR5eReachEnv
        >>> from torchrl_silp.modules import GPGuidedExploration
        >>> base = UR5eReachEnv(num_envs=4, seed=0, collision_type=2)
        >>> env = TransformedEnv(base, InitTracker())
        >>> actor = Actor(torch.nn.Sequential(torch.nn.Linear(15, 3), torch.nn.Tanh()), in_keys=["observation"])
        >>> policy = TensorDictSequential(actor, GPGuidedExploration(base))
        >>> with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        ...     rollout = env.rollout(20, policy)
        >>> bool(rollout["action"].abs().max() <= 1)
        True
    """

    def __init__(
        self,
        env,
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
        observation_key: NestedKey = "observation",
        collision_key: NestedKey = "collision",
        is_init_key: NestedKey = "is_init",
        done_key: NestedKey = "done",
        reward_key: NestedKey | None = None,
        generator: torch.Generator | None = None,
    ):
        for name in ("transition", "reward", "collides"):
            if not callable(getattr(env, name, None)):
                raise TypeError(
                    f"env must have callable transition, reward and collides (a UR5eReachEnv); "
                    f"{type(env).__name__} lacks {name}"
                )
        if mode not in GP_EXPLORATION_MODES:
            raise ValueError(f"mode must be one of {GP_EXPLORATION_MODES}, got {mode!r}")
        counts = (("num_candidates", num_candidates), ("history_size", history_size), ("fit_steps", fit_steps))
        for name, value in counts:
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        scales = (("lengthscale", lengthscale), ("outputscale", outputscale), ("noise", noise), ("fit_lr", fit_lr))
        for name, value in scales:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not isinstance(fit_hyperparameters, bool):
            raise TypeError(f"fit_hyperparameters must be a bool, got {fit_hyperparameters!r}")
        super().__init__()
        # a plain reference: registering the env would move and save it with the policy
        self.__dict__["env"] = env
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
        self.observation_key = observation_key
        self.collision_key = collision_key
        self.is_init_key = is_init_key
        self.done_key = done_key
        self.reward_key = reward_key
        self.generator = generator
        self.last_recovery: TensorDict | None = None
        self.in_keys = [observation_key, action_key, collision_key, is_init_key]
        self.out_keys = [action_key]
        for name in ("_hist_q", "_hist_r", "_count", "_prev_obs", "_prev_action", "_has_prev"):
            self.register_buffer(name, None, persistent=False)

    # -------------------------------------------------------------- state
    def reset(self) -> None:
        """Forget every env's history (the next call starts new episodes)."""
        for name in ("_hist_q", "_hist_r", "_count", "_prev_obs", "_prev_action", "_has_prev"):
            setattr(self, name, None)

    def _ensure_state(self, m: int, obs: torch.Tensor, action: torch.Tensor) -> None:
        if self._count is not None and self._count.shape[0] == m and self._count.device == obs.device:
            return
        f = dict(dtype=obs.dtype, device=obs.device)
        self._hist_q = torch.zeros(m, self.history_size, 3, **f)
        self._hist_r = torch.zeros(m, self.history_size, **f)
        self._count = torch.zeros(m, dtype=torch.long, device=obs.device)
        self._prev_obs = torch.zeros_like(obs)
        self._prev_action = torch.zeros_like(action)
        self._has_prev = torch.zeros(m, dtype=torch.bool, device=obs.device)

    @property
    def history(self) -> TensorDict | None:
        """Per-env ring buffers: ``q`` ``[B, H, 3]``, ``reward`` ``[B, H]``, ``count`` ``[B]`` (pushes since the reset).

        Slot ``i`` of a row holds push ``i + H·j``; ``min(count, H)`` slots are valid.
        """
        if self._count is None:
            return None
        return TensorDict(
            q=self._hist_q, reward=self._hist_r, count=self._count, batch_size=self._count.shape
        )

    def _push(self, q: torch.Tensor, reward: torch.Tensor, new_episode: torch.Tensor) -> None:
        count = torch.where(new_episode, torch.zeros_like(self._count), self._count)
        slot = torch.nn.functional.one_hot(count % self.history_size, self.history_size).bool()
        self._hist_q = torch.where(slot.unsqueeze(-1), q.unsqueeze(-2), self._hist_q)
        self._hist_r = torch.where(slot, reward.unsqueeze(-1), self._hist_r)
        self._count = count + 1

    # ----------------------------------------------------------- recovery
    def candidate_probabilities(
        self,
        history_q: torch.Tensor,
        history_r: torch.Tensor,
        history_mask: torch.Tensor,
        q_next: torch.Tensor,
        collides: torch.Tensor,
    ) -> torch.Tensor:
        """Sampling probabilities ``(R, n)`` of the candidates ``q_next`` ``(R, n, 3)``.

        GP mode: posterior mean on the history, min-max scaled over the allowed
        candidates (collision-free ones when there are some, else all) and
        normalised; uniform over the allowed ones if their predictions are all
        equal. Random mode: uniform over the allowed candidates.

        Args:
            history_q, history_r, history_mask: ``(R, H, 3)``, ``(R, H)``, bool
                ``(R, H)``: the episodes' visited states, rewards, valid slots.
            q_next: ``(R, n, 3)`` candidate configurations.
            collides: bool ``(R, n)``: which candidates collide.
        """
        allowed = ~collides
        allowed = torch.where(allowed.any(-1, keepdim=True), allowed, torch.ones_like(allowed))
        uniform = allowed.to(q_next.dtype)
        if self.mode == "random":
            return uniform / uniform.sum(-1, keepdim=True)
        ls, scale, nz = self.lengthscale, self.outputscale, self.noise
        if self.fit_hyperparameters:
            ls, scale, nz = fit_gp_hyperparameters(
                history_q, history_r, lengthscale=ls, outputscale=scale, noise=nz,
                mask=history_mask, steps=self.fit_steps, lr=self.fit_lr,
            )
        mean, _ = gp_posterior(
            history_q, history_r, q_next, lengthscale=ls, outputscale=scale, noise=nz,
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

    def _recovery_actions(self, obs: torch.Tensor, rows: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        env, r, n = self.env, obs.shape[0], self.num_candidates
        actions = torch.rand(r, n, 3, generator=self.generator, dtype=obs.dtype, device=obs.device) * 2 - 1
        q_next = env.transition(obs.unsqueeze(-2).expand(r, n, obs.shape[-1]), actions)[..., :3]
        collides = env.collides(q_next, obs[:, None, 6:12])
        size = self.history_size
        valid = torch.arange(size, device=obs.device) < self._count[rows].clamp_max(size).unsqueeze(-1)
        probs = self.candidate_probabilities(self._hist_q[rows], self._hist_r[rows], valid, q_next, collides)
        pick = torch.multinomial(probs, 1, generator=self.generator).squeeze(-1)
        chosen = actions[torch.arange(r, device=obs.device), pick]
        self.last_recovery = TensorDict(
            env_index=rows, candidate_action=actions, candidate_q=q_next, collides=collides,
            probability=probs, action=chosen, batch_size=[r],
        )
        return chosen.to(dtype)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if exploration_type() not in (ExplorationType.RANDOM, None):
            return tensordict
        obs_in = tensordict.get(self.observation_key)
        action_in = tensordict.get(self.action_key)
        m = obs_in.shape[:-1].numel()
        obs = obs_in.reshape(m, obs_in.shape[-1])
        action = action_in.reshape(m, action_in.shape[-1])
        self._ensure_state(m, obs, action)

        def flag(key):
            value = tensordict.get(key, None)
            if value is None:
                return torch.zeros(m, dtype=torch.bool, device=obs.device)
            return value.reshape(m).to(torch.bool)

        new_episode = ~self._has_prev | flag(self.is_init_key) | flag(self.done_key)
        # a changed goal or obstacle is a reset the tensordict did not flag
        new_episode = new_episode | (obs[:, 6:] != self._prev_obs[:, 6:]).any(-1)
        collided = flag(self.collision_key) & ~new_episode

        with torch.no_grad():
            env = self.env
            prev = torch.where(new_episode.unsqueeze(-1), obs, self._prev_obs)
            # the state the last action led to: after a collision the env put
            # the arm back, so the colliding configuration is recomputed
            led_to = torch.where(
                collided.unsqueeze(-1), env.transition(self._prev_obs, self._prev_action).to(obs.dtype), obs
            )
            reward = tensordict.get(self.reward_key, None) if self.reward_key is not None else None
            if reward is None:
                reward = env.reward(prev, led_to)
            else:
                reward = torch.where(new_episode.unsqueeze(-1), env.reward(obs, obs), reward.reshape(m, 1))
            self._push(led_to[:, :3], reward.reshape(m).to(obs.dtype), new_episode)

            # one host sync decides whether any GP work is needed this step
            rows = collided.nonzero().squeeze(-1) if collided.any() else None
            chosen = None if rows is None else self._recovery_actions(obs[rows], rows, action.dtype)
        if rows is not None:
            # outside no_grad: the passed-through rows keep the actor's graph
            action = action.index_copy(0, rows, chosen)
            tensordict.set(self.action_key, action.reshape(action_in.shape))

        self._prev_obs = obs.detach().clone()
        self._prev_action = action.detach().to(obs.dtype).clone()
        self._has_prev = torch.ones_like(self._has_prev)
        return tensordict
