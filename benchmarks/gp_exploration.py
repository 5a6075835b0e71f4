"""GP fit + predict for the GP-guided exploration: plain torch vs gpytorch.

The work of one recovery step of :class:`~torchrl_silp.modules.GPGuidedExploration`:
``B`` independent GPs (one per collided env), each on ``H`` visited joint
states (3-D) -> rewards, queried at ``n`` candidate configurations
(posterior mean). Both implementations use a zero-mean Matérn-5/2 kernel,
the same hyper-parameters and float32, and are checked against each other
before timing. Figures (milliseconds per call, median of repeats):

* ``fixed``: fixed hyper-parameters: build the GP on the history, predict the
  candidates' posterior mean (gpytorch: a batched ``ExactGP`` built per call,
  since the history changes at every step, queried in ``eval`` mode);
* ``fitted``: as above after ``--fit-steps`` Adam steps on the exact marginal
  log-likelihood (gpytorch: ``ExactMarginalLogLikelihood``).

Then the whole module (torch only): one ``GPGuidedExploration`` call on a
tensordict of ``B`` UR5e envs that all collided, their ``H - 1`` earlier states
in the tensordict's history keys: recording the colliding state, drawing and
motion-checking the candidates, the GP and the choice.

Run::

    python benchmarks/gp_exploration.py              # B in {1, 64}, H = 50, n = 64
    python benchmarks/gp_exploration.py --threads 2 --reps 50
    python benchmarks/gp_exploration.py --device cuda
"""

from __future__ import annotations

import argparse
import importlib.util
import platform

import torch
from tensordict import TensorDict
from timing import median_ms  # benchmarks/timing.py, beside this script
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp.models import UR5eReach
from torchrl_silp.modules.gp_exploration import GPGuidedExploration, fit_gp_hyperparameters, gp_posterior

_has_gpytorch = importlib.util.find_spec("gpytorch") is not None

LENGTHSCALE, OUTPUTSCALE, NOISE = 0.3, 1.0, 1e-2


def make_data(b: int, h: int, n: int, seed: int = 0, device: str = "cpu"):
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(b, h, 3, generator=gen) * 2 - 1
    # a smooth reward landscape with a few "collisions" at -10
    y = -(x - 0.3).norm(dim=-1)
    y[:, ::7] = -10.0
    q = x[:, -1:, :] + 0.125 * (torch.rand(b, n, 3, generator=gen) * 2 - 1)
    return x.to(device), y.to(device), q.to(device)


def torch_predict(x, y, q, fit_steps: int = 0):
    ls, scale, noise = LENGTHSCALE, OUTPUTSCALE, NOISE
    if fit_steps:
        ls, scale, noise = fit_gp_hyperparameters(
            x, y, lengthscale=ls, outputscale=scale, noise=noise, steps=fit_steps, lr=0.1
        )
    with torch.no_grad():
        return gp_posterior(x, y, q, lengthscale=ls, outputscale=scale, noise=noise, return_var=False)[0]


def gpytorch_predict(x, y, q, fit_steps: int = 0):
    import gpytorch

    b = torch.Size([x.shape[0]])

    class BatchGP(gpytorch.models.ExactGP):
        def __init__(self, train_x, train_y, likelihood):
            super().__init__(train_x, train_y, likelihood)
            self.mean_module = gpytorch.means.ZeroMean(batch_shape=b)
            self.covar_module = gpytorch.kernels.ScaleKernel(
                gpytorch.kernels.MaternKernel(nu=2.5, batch_shape=b), batch_shape=b
            )

        def forward(self, x):
            return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))

    likelihood = gpytorch.likelihoods.GaussianLikelihood(
        batch_shape=b, noise_constraint=gpytorch.constraints.GreaterThan(1e-4)
    )
    model = BatchGP(x, y, likelihood).to(x.device)
    likelihood = likelihood.to(x.device)
    model.covar_module.base_kernel.lengthscale = LENGTHSCALE
    model.covar_module.outputscale = OUTPUTSCALE
    likelihood.noise = NOISE
    if fit_steps:
        model.train()
        likelihood.train()
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)
        optim = torch.optim.Adam(model.parameters(), lr=0.1)
        for _ in range(fit_steps):
            optim.zero_grad()
            (-mll(model(x), y)).sum().backward()
            optim.step()
    model.eval()
    likelihood.eval()
    # exact solves (gpytorch switches to CG above 800 points; 50 is far below)
    with torch.no_grad(), gpytorch.settings.fast_pred_var(False):
        return model(q).mean


def module_inputs(model: UR5eReach, b: int, h: int, seed: int = 0) -> TensorDict:
    """The root tensordict of ``b`` envs whose last step collided, ``h - 1`` states in their histories."""
    gen = torch.Generator(device=model.device).manual_seed(seed)
    f = dict(dtype=model.dtype, device=model.device)
    state = model.sample_tasks(b, gen).select(*model.state_keys)
    q = state.get(model.config_key)
    history = torch.zeros(b, h, model.config_dim, **f)
    history[:, : h - 1] = q.unsqueeze(1) + 0.125 * (torch.rand(b, h - 1, model.config_dim, generator=gen, **f) * 2 - 1)
    reward = torch.zeros(b, h, **f)
    reward[:, : h - 1] = -torch.rand(b, h - 1, generator=gen, **f)
    reward[:, : h - 1 : 7] = model.collision_reward
    action = torch.rand(b, model.action_dim, generator=gen, **f) * 2 - 1
    ones = torch.ones(b, 1, dtype=torch.bool, device=model.device)
    td = state.clone()
    td.update(
        {
            "action": action,
            "collision": ones,
            "is_init": ~ones,
            "_gp_history_config": history,
            "_gp_history_reward": reward,
            "_gp_history_count": torch.full((b, 1), h - 1, dtype=torch.long, device=model.device),
            "_gp_prev_config": q.clone(),
            "_gp_prev_action": action.clone(),
        }
    )
    return td


def module_step(module: GPGuidedExploration, td: TensorDict) -> TensorDict:
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        return module(td.clone())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--history", type=int, default=50)
    parser.add_argument("--candidates", type=int, default=64)
    parser.add_argument("--fit-steps", type=int, default=10)
    parser.add_argument("--reps", type=int, default=30)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    gp_version = "not installed"
    if _has_gpytorch:
        import gpytorch

        gp_version = gpytorch.__version__
    print(
        f"torch {torch.__version__}, gpytorch {gp_version}, "
        f"{args.device} ({platform.processor() or platform.machine()}), "
        f"{torch.get_num_threads()} thread(s); H={args.history} history points, n={args.candidates} candidates, "
        f"float32, median of {args.reps}"
    )
    print(f"{'B':>4} {'hyper-parameters':>18} {'torch ms':>10} {'gpytorch ms':>12} {'ratio':>7}")
    for b in args.batch:
        x, y, q = make_data(b, args.history, args.candidates, device=args.device)
        if _has_gpytorch:
            # same model, same numbers: a timing of two different computations would mean nothing
            torch.testing.assert_close(torch_predict(x, y, q), gpytorch_predict(x, y, q), rtol=1e-3, atol=1e-3)
        for label, steps in (("fixed", 0), (f"fitted ({args.fit_steps} steps)", args.fit_steps)):
            t_torch = median_ms(lambda: torch_predict(x, y, q, steps), args.reps, args.device)
            if _has_gpytorch:
                t_gp = median_ms(lambda: gpytorch_predict(x, y, q, steps), args.reps, args.device)
                print(f"{b:>4} {label:>18} {t_torch:>10.2f} {t_gp:>12.2f} {t_gp / t_torch:>6.1f}x")
            else:
                print(f"{b:>4} {label:>18} {t_torch:>10.2f} {'(pip install gpytorch)':>12}")

    model = UR5eReach(device=args.device)
    print(f"\nGPGuidedExploration, one call with B collided envs (history H={args.history}, n={args.candidates})")
    print(f"{'B':>4} {'hyper-parameters':>18} {'module ms':>10}")
    for b in args.batch:
        td = module_inputs(model, b, args.history)
        for label, fit in (("fixed", False), (f"fitted ({args.fit_steps} steps)", True)):
            module = GPGuidedExploration(
                model, num_candidates=args.candidates, history_size=args.history,
                fit_hyperparameters=fit, fit_steps=args.fit_steps,
            )
            out = module_step(module, td)
            assert module.last_recovery is not None and module.last_recovery.shape == (b,)
            assert (out["_gp_history_count"] == args.history).all()
            t_module = median_ms(lambda: module_step(module, td), args.reps, args.device)
            print(f"{b:>4} {label:>18} {t_module:>10.2f}")


if __name__ == "__main__":
    main()
