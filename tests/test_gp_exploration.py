"""GPGuidedExploration and its batched GP: closed form, bounds, collision-free choice, pass-through, resets."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import cdist
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp import UR5eReachEnv
from torchrl_silp.geometry import aabb_from_center
from torchrl_silp.modules import (
    GPGuidedExploration,
    fit_gp_hyperparameters,
    gp_negative_log_marginal_likelihood,
    gp_nll_gradient,
    gp_posterior,
    matern52_kernel,
)

RANDOM = ExplorationType.RANDOM


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # small tensors: on a shared 2-core machine OpenMP threads only contend
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def env():
    return UR5eReachEnv(num_envs=4, seed=0, collision_type=2)


# ------------------------------------------------------ closed form (numpy)
def np_matern52(a, b, ls, s2):
    r = cdist(a, b) / ls
    return s2 * (1 + math.sqrt(5) * r + 5 * r**2 / 3) * np.exp(-math.sqrt(5) * r)


def np_posterior(x, y, xs, ls, s2, noise):
    k = np_matern52(x, x, ls, s2) + noise * np.eye(len(x))
    kn = np_matern52(x, xs, ls, s2)  # (n, m)
    kinv = np.linalg.inv(k)
    mean = kn.T @ kinv @ y
    var = s2 - np.einsum("im,ij,jm->m", kn, kinv, kn)
    return mean, var


def np_nll(x, y, ls, s2, noise):
    k = np_matern52(x, x, ls, s2) + noise * np.eye(len(x))
    _, logdet = np.linalg.slogdet(k)
    return 0.5 * y @ np.linalg.solve(k, y) + 0.5 * logdet + 0.5 * len(x) * math.log(2 * math.pi)


def test_matern52_matches_closed_form():
    rng = np.random.default_rng(0)
    a, b = rng.uniform(-1, 1, (7, 3)), rng.uniform(-1, 1, (5, 3))
    got = matern52_kernel(torch.from_numpy(a), torch.from_numpy(b), 0.4, 2.0).numpy()
    np.testing.assert_allclose(got, np_matern52(a, b, 0.4, 2.0), rtol=1e-12, atol=1e-12)


def test_posterior_matches_closed_form_batched_and_padded():
    rng = np.random.default_rng(1)
    lengths, n, m = [12, 5, 1, 30], 30, 9
    ls = np.array([0.3, 0.5, 1.0, 0.2])
    s2 = np.array([1.0, 2.0, 0.5, 4.0])
    noise = np.array([1e-2, 1e-1, 1e-3, 5e-2])
    x = rng.uniform(-1, 1, (4, n, 3))
    y = rng.normal(size=(4, n))
    y[:, ::5] = -10.0
    xs = rng.uniform(-1, 1, (4, m, 3))
    mask = np.arange(n)[None] < np.array(lengths)[:, None]
    # garbage in the padding must not matter
    x[~mask] = 1e3
    y[~mask] = 1e3
    mean, var = gp_posterior(
        torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(xs),
        lengthscale=torch.from_numpy(ls), outputscale=torch.from_numpy(s2), noise=torch.from_numpy(noise),
        mask=torch.from_numpy(mask),
    )
    assert mean.dtype == torch.float64 and mean.shape == (4, m) and var.shape == (4, m)
    for b, length in enumerate(lengths):
        want_mean, want_var = np_posterior(x[b, :length], y[b, :length], xs[b], ls[b], s2[b], noise[b])
        np.testing.assert_allclose(mean[b].numpy(), want_mean, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(var[b].numpy(), want_var, rtol=1e-9, atol=1e-9)


def test_posterior_float32_close_to_float64():
    rng = np.random.default_rng(2)
    x, y, xs = rng.uniform(-1, 1, (50, 3)), rng.normal(size=50), rng.uniform(-1, 1, (64, 3))
    mean, var = gp_posterior(
        torch.tensor(x, dtype=torch.float32), torch.tensor(y, dtype=torch.float32),
        torch.tensor(xs, dtype=torch.float32), lengthscale=0.3, noise=1e-2,
    )
    want_mean, want_var = np_posterior(x, y, xs, 0.3, 1.0, 1e-2)
    assert mean.dtype == torch.float32
    np.testing.assert_allclose(mean.numpy(), want_mean, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(var.numpy(), want_var, rtol=1e-3, atol=1e-3)


def test_nll_and_its_closed_form_gradient():
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-1, 1, (3, 10, 3)), rng.normal(size=(3, 10))
    mask = np.arange(10)[None] < np.array([10, 6, 2])[:, None]
    logs = [torch.tensor(np.log(v), requires_grad=True) for v in ([0.3, 0.7, 1.2], [1.0, 2.0, 0.5], [0.01, 0.1, 0.05])]
    tx, ty, tm = torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(mask)
    nll = gp_negative_log_marginal_likelihood(
        tx, ty, lengthscale=logs[0].exp(), outputscale=logs[1].exp(), noise=logs[2].exp(), mask=tm
    )
    for b, length in enumerate((10, 6, 2)):
        want = np_nll(x[b, :length], y[b, :length], *(float(p[b].detach().exp()) for p in logs))
        assert float(nll[b].detach()) == pytest.approx(want, rel=1e-9)
    autograd = torch.autograd.grad(nll.sum(), logs)
    closed = gp_nll_gradient(
        tx, ty, lengthscale=logs[0].exp().detach(), outputscale=logs[1].exp().detach(),
        noise=logs[2].exp().detach(), mask=tm,
    )
    for a, c in zip(autograd, closed):
        torch.testing.assert_close(c, a, rtol=1e-8, atol=1e-10)


def test_fitting_lowers_the_nll():
    rng = np.random.default_rng(4)
    x = torch.from_numpy(rng.uniform(-1, 1, (2, 40, 3)))
    y = torch.sin(3 * x).sum(-1) + 0.05 * torch.from_numpy(rng.normal(size=(2, 40)))
    start = dict(lengthscale=3.0, outputscale=0.1, noise=0.5)
    before = gp_negative_log_marginal_likelihood(x, y, **start)
    ls, s2, noise = fit_gp_hyperparameters(x, y, steps=30, lr=0.1, **start)
    after = gp_negative_log_marginal_likelihood(x, y, lengthscale=ls, outputscale=s2, noise=noise)
    assert ls.shape == (2,) and (after < before - 1.0).all()


# ------------------------------------------------------------- the module
def obs_of(env, q, centre, goal_q):
    """Observations (B, 15) from joint angles, obstacle centres and goal joint angles."""
    box = aabb_from_center(centre, torch.tensor(env.OBSTACLE_SIZE).expand_as(centre))
    return torch.cat([q, env.robot.fk(q), box, env.robot.fk(goal_q)], -1)


def step_td(obs, action, *, collision=None, is_init=None):
    b = obs.shape[0]

    def flag(value):
        return torch.as_tensor(False if value is None else value, dtype=torch.bool).expand(b).reshape(b, 1).clone()

    return TensorDict(
        observation=obs, action=action.clone(), collision=flag(collision), is_init=flag(is_init), batch_size=[b]
    )


def colliding_pairs(env, b, seed=0):
    """``b`` real (obs, action) pairs whose next state collides, found among random tasks and actions."""
    gen = torch.Generator().manual_seed(seed)
    tasks = env.sample_tasks(256, generator=gen)
    obs = torch.cat([tasks["q"], tasks["tcp"], tasks["obstacle"], tasks["goal"]], -1)
    actions = torch.rand(256, 16, 3, generator=gen) * 2 - 1
    nxt = env.transition(obs.unsqueeze(1).expand(256, 16, 15), actions)
    hit = env.collides(nxt[..., :3], obs[:, None, 6:12])
    rows, cols = hit.nonzero(as_tuple=True)
    assert rows.numel() >= b
    pick = torch.randperm(rows.numel(), generator=gen)[:b]
    return obs[rows[pick]], actions[rows[pick], cols[pick]]


def test_history_records_collision_state_and_recovers(env):
    obs, bad_action = colliding_pairs(env, 4)
    module = GPGuidedExploration(env, generator=torch.Generator().manual_seed(0))
    with set_exploration_type(RANDOM):
        out = module(step_td(obs, bad_action, is_init=True))
        torch.testing.assert_close(out["action"], bad_action)  # no collision yet: pass-through
        # the env put the arm back: same observation, collision flagged
        out = module(step_td(obs, bad_action, collision=True))
    hist = module.history
    assert hist["count"].tolist() == [2, 2, 2, 2]
    torch.testing.assert_close(hist["q"][:, 0], obs[:, :3])
    torch.testing.assert_close(hist["reward"][:, 0], env.reward(obs, obs).squeeze(-1))
    collided_q = env.transition(obs, bad_action)[:, :3]
    torch.testing.assert_close(hist["q"][:, 1], collided_q)
    assert (hist["reward"][:, 1] == env.COLLISION_REWARD).all()
    # a new action, one of the candidates, collision-free
    rec = module.last_recovery
    assert rec["env_index"].tolist() == [0, 1, 2, 3]
    assert not torch.equal(out["action"], bad_action)
    assert torch.equal(out["action"], rec["action"])
    assert ((rec["candidate_action"] == out["action"].unsqueeze(1)).all(-1)).any(-1).all()
    assert not env.collides(env.transition(obs, out["action"])[:, :3], obs[:, 6:12]).any()


def test_probabilities_follow_min_max_scaled_posterior_mean(env):
    obs, bad_action = colliding_pairs(env, 3, seed=1)
    module = GPGuidedExploration(env, num_candidates=32, generator=torch.Generator().manual_seed(1))
    with set_exploration_type(RANDOM):
        module(step_td(obs, bad_action, is_init=True))
        module(step_td(obs, bad_action, collision=True))
    rec, hist = module.last_recovery, module.history
    for b in range(3):
        x = hist["q"][b, :2].double().numpy()
        y = hist["reward"][b, :2].double().numpy()
        mean, _ = np_posterior(x, y, rec["candidate_q"][b].double().numpy(), 0.3, 1.0, 1e-2)
        free = ~rec["collides"][b].numpy()
        allowed = free if free.any() else np.ones_like(free)
        lo, hi = mean[allowed].min(), mean[allowed].max()
        want = np.where(allowed, (mean - lo) / (hi - lo), 0.0)
        want /= want.sum()
        np.testing.assert_allclose(rec["probability"][b].numpy(), want, rtol=1e-3, atol=1e-4)


def test_random_mode_is_uniform_over_free_candidates(env):
    obs, bad_action = colliding_pairs(env, 4, seed=2)
    module = GPGuidedExploration(env, mode="random")
    with set_exploration_type(RANDOM):
        module(step_td(obs, bad_action, is_init=True))
        module(step_td(obs, bad_action, collision=True))
    rec = module.last_recovery
    free = (~rec["collides"]).float()
    torch.testing.assert_close(rec["probability"], free / free.sum(-1, keepdim=True))


def unit(low, high):
    return st.floats(low, high, allow_nan=False)


# start configurations from the task's joint box; the obstacle right next to the
# TCP, so that some candidates collide and some do not
LOW, HIGH = UR5eReachEnv.TASK_JOINT_LOW, UR5eReachEnv.TASK_JOINT_HIGH
state = st.tuples(*(unit(lo, hi) for lo, hi in zip(LOW, HIGH)), *(unit(-0.25, 0.25) for _ in range(3)))


@settings(max_examples=12, deadline=None)
@given(
    states=st.lists(state, min_size=1, max_size=6),
    actor_action=st.lists(unit(-3, 3), min_size=3, max_size=3),
    mode=st.sampled_from(["gp", "random"]),
    fit=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_never_out_of_bounds_nor_colliding_when_avoidable(states, actor_action, mode, fit, seed):
    s = torch.tensor(states, dtype=torch.float32)
    b, n = s.shape[0], 16
    env = UR5eReachEnv(num_envs=1, seed=0)
    q = s[:, :3]
    obs = obs_of(env, q, env.robot.fk(q) + s[:, 3:], q.flip(0))
    gen = torch.Generator().manual_seed(seed)
    module = GPGuidedExploration(env, mode=mode, num_candidates=n, fit_hyperparameters=fit, fit_steps=3, generator=gen)
    action = torch.tensor(actor_action).expand(b, 3)  # an actor may even leave [-1, 1]
    with set_exploration_type(RANDOM):
        module(step_td(obs, torch.rand(b, 3, generator=gen) * 2 - 1, is_init=True))
        for _ in range(4):  # collisions in a row: each a fresh recovery from the same state
            out = module(step_td(obs, action, collision=True))["action"]
            assert out.shape == (b, 3) and torch.isfinite(out).all()
            assert (out.abs() <= 1).all()
            rec = module.last_recovery
            assert rec["env_index"].tolist() == list(range(b))
            # the candidates' collisions recomputed independently of the module's mask
            cand_q = env.transition(obs.unsqueeze(1).expand(b, n, 15), rec["candidate_action"])[..., :3]
            avoidable = (~env.collides(cand_q, obs[:, None, 6:12])).any(-1)
            hit = env.collides(env.transition(obs, out)[:, :3], obs[:, 6:12])
            assert not (hit & avoidable).any()


def test_passes_actor_action_through(env):
    obs, bad_action = colliding_pairs(env, 4, seed=3)
    module = GPGuidedExploration(env)
    with set_exploration_type(RANDOM):
        module(step_td(obs, bad_action, is_init=True))
        # no collision: untouched, whatever the action (even out of bounds)
        wild = torch.full((4, 3), 7.0)
        assert torch.equal(module(step_td(obs, wild))["action"], wild)
        # a collision in only some envs changes only those
        out = module(step_td(obs, bad_action, collision=[True, False, True, False]))["action"]
    assert torch.equal(out[[1, 3]], bad_action[[1, 3]])
    assert not torch.equal(out[[0, 2]], bad_action[[0, 2]])
    assert module.last_recovery["env_index"].tolist() == [0, 2]
    count = module.history["count"].clone()
    for mode in (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN):
        with set_exploration_type(mode):
            out = module(step_td(obs, bad_action, collision=True))["action"]
        assert torch.equal(out, bad_action)
    assert torch.equal(module.history["count"], count)  # nothing recorded outside RANDOM


def test_resets_per_env_on_is_init_done_and_new_task(env):
    gen = torch.Generator().manual_seed(5)
    tasks = env.sample_tasks(3, generator=gen)
    obs = torch.cat([tasks["q"], tasks["tcp"], tasks["obstacle"], tasks["goal"]], -1)
    module = GPGuidedExploration(env)
    small = torch.full((3, 3), 0.1)
    with set_exploration_type(RANDOM):
        module(step_td(obs, small, is_init=True))
        for _ in range(3):
            obs = env.transition(obs, small)
            module(step_td(obs, small))
        assert module.history["count"].tolist() == [4, 4, 4]
        obs = env.transition(obs, small)
        module(step_td(obs, small, is_init=[False, True, False]))
        assert module.history["count"].tolist() == [5, 1, 5]
        torch.testing.assert_close(module.history["q"][1, 0], obs[1, :3])
        # a collision flag on the first step of an episode is not a recovery
        td = step_td(obs, small, is_init=[True, False, False], collision=[True, False, False])
        assert torch.equal(module(td)["action"], small)
        assert module.history["count"].tolist() == [1, 2, 6]
        # "done" and a changed task reset too
        td = step_td(obs, small)
        td["done"] = torch.tensor([[False], [False], [True]])
        module(td)
        assert module.history["count"].tolist() == [2, 3, 1]
        new_obs = obs.clone()
        new_obs[0, 12:15] += 0.1  # env 0 got a new goal without an is_init flag
        module(step_td(new_obs, small))
        assert module.history["count"].tolist() == [1, 4, 2]


def test_ring_buffer_keeps_the_latest_states(env):
    obs = env.reset()["observation"]
    module = GPGuidedExploration(env, history_size=3)
    a = torch.full((4, 3), 0.05)
    seen = [obs[:, :3]]
    with set_exploration_type(RANDOM):
        module(step_td(obs, a, is_init=True))
        for _ in range(4):
            obs = env.transition(obs, a)
            seen.append(obs[:, :3])
            module(step_td(obs, a))
    hist = module.history
    assert hist["count"].tolist() == [5] * 4
    # pushes 3 and 4 overwrote slots 0 and 1; push 2 is still in slot 2
    for slot, push in ((0, 3), (1, 4), (2, 2)):
        torch.testing.assert_close(hist["q"][:, slot], seen[push])


def test_in_a_rollout_it_replaces_only_post_collision_actions():
    base = UR5eReachEnv(num_envs=6, seed=0, collision_type=2)
    env = TransformedEnv(base, InitTracker())
    push = torch.tensor([1.0, 1.0, 1.0])  # a constant actor that runs into things and would stay stuck
    actor = TensorDictModule(lambda o: push.expand(*o.shape[:-1], 3).clone(), ["observation"], ["action"])
    policy = TensorDictSequential(actor, GPGuidedExploration(base, generator=torch.Generator().manual_seed(0)))
    with set_exploration_type(RANDOM), torch.no_grad():
        rollout = env.rollout(20, policy, break_when_any_done=False)
        stuck = env.rollout(20, actor, break_when_any_done=False)
    after_collision = rollout["collision"].squeeze(-1) & ~rollout["is_init"].squeeze(-1)
    assert after_collision.any()
    assert (rollout["action"][~after_collision] == push).all()
    assert (rollout["action"][after_collision] != push).any(-1).all()
    assert (rollout["action"].abs() <= 1).all()
    assert rollout["next", "collision"].sum() < stuck["next", "collision"].sum()


@pytest.mark.parametrize(
    "kwargs,error",
    [
        (dict(mode="greedy"), ValueError),
        (dict(num_candidates=0), ValueError),
        (dict(history_size=1.5), ValueError),
        (dict(lengthscale=0.0), ValueError),
        (dict(noise=-1e-3), ValueError),
        (dict(fit_hyperparameters="yes"), TypeError),
    ],
)
def test_bad_configuration_raises(env, kwargs, error):
    with pytest.raises(error):
        GPGuidedExploration(env, **kwargs)
    with pytest.raises(TypeError, match="collides"):
        GPGuidedExploration(object())
