"""GPGuidedExploration and its batched GP.

The GP against closed forms (numpy/scipy); the module against independent
recomputations through the task model and the env: its history in the
TensorDict over rollouts, resets on ``is_init``, the recovery's choice with and
without the collision mask, pass-through, two envs sharing one module, and a
two-process collector.
"""

import math
import warnings

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import cdist
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type
from torchrl.modules import Actor

from torchrl_silp import CollisionHandling, ReachEnv, UR5eReachEnv
from torchrl_silp.geometry import aabb_from_center
from torchrl_silp.models import UR5eReach
from torchrl_silp.modules.gp_exploration import (
    GP_STATE_KEYS,
    GPGuidedExploration,
    fit_gp_hyperparameters,
    gp_negative_log_marginal_likelihood,
    gp_nll_gradient,
    gp_posterior,
    matern52_kernel,
)

RANDOM = ExplorationType.RANDOM
# the module's per-env keys, by their documented names
CONFIG, REWARD, COUNT = "_gp_history_config", "_gp_history_reward", "_gp_history_count"
PREV_CONFIG, PREV_ACTION = "_gp_prev_config", "_gp_prev_action"
KEYS = (CONFIG, REWARD, COUNT, PREV_CONFIG, PREV_ACTION)


# small tensors: on a shared 2-core machine OpenMP threads only contend
pytestmark = pytest.mark.usefixtures("one_thread")


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


def test_state_keys_are_the_documented_ones():
    assert set(GP_STATE_KEYS) == set(KEYS)


# ------------------------------------------------------------- the module
def flags(value, b):
    return torch.as_tensor(value, dtype=torch.bool).expand(b).reshape(b, 1).clone()


def step_td(model, state, action, *, collision=False, is_init=False, carry=None):
    """The root tensordict a policy sees: the state, the actor's action, the flags and the carried keys."""
    b = action.shape[0]
    td = state.select(*model.state_keys).clone()
    td.update({"action": action.clone(), "collision": flags(collision, b), "is_init": flags(is_init, b)})
    if carry is not None:
        td.update(carry.select(*KEYS).clone())
    return td


def colliding_pairs(model, b, seed=0):
    """``b`` real (state, action) pairs whose step collides, found among random tasks and actions."""
    gen = torch.Generator().manual_seed(seed)
    tasks = model.sample_tasks(256, gen).select(*model.state_keys)
    actions = torch.rand(256, 16, 3, generator=gen) * 2 - 1
    collision = model.step(tasks.unsqueeze(1).expand(256, 16), actions)[2].squeeze(-1)
    rows, cols = collision.nonzero(as_tuple=True)
    assert rows.numel() >= b
    pick = torch.randperm(rows.numel(), generator=gen)[:b]
    return tasks[rows[pick]], actions[rows[pick], cols[pick]]


def collide_and_recover(model, module, state, bad_action):
    """First step of an episode with ``bad_action``, then the step after its collision (arm put back)."""
    with set_exploration_type(RANDOM):
        first = module(step_td(model, state, bad_action, is_init=True))
        out = module(step_td(model, state, bad_action, collision=True, carry=first))
    return first, out


def goal_reward(model, achieved, desired):
    dist = (achieved - desired).norm(dim=-1)
    return torch.where(dist < model.success_distance, torch.full_like(dist, model.success_reward), -dist)


def next_config(model, q, action):
    """q + 0.125 clip(a), clipped to the joint limits, written out."""
    moved = q + model.action_scale * action.clamp(-1, 1)
    return torch.minimum(torch.maximum(moved, model.config_low), model.config_high)


def candidates_collide(model, state, actions):
    """Whether each candidate step collides, by the env's own step (model.step)."""
    r, n = actions.shape[:2]
    return model.step(state.unsqueeze(1).expand(r, n), actions)[2].squeeze(-1)


def test_history_records_collision_state_and_recovers(model):
    state, bad = colliding_pairs(model, 4)
    module = GPGuidedExploration(model, generator=torch.Generator().manual_seed(0))
    first, out = collide_and_recover(model, module, state, bad)
    torch.testing.assert_close(first["action"], bad)  # no collision yet: pass-through
    assert first[COUNT].squeeze(-1).tolist() == [1] * 4
    assert out[COUNT].squeeze(-1).tolist() == [2] * 4
    assert out[CONFIG].shape == (4, 64, 3) and out[REWARD].shape == (4, 64) and out[COUNT].dtype == torch.long
    q = state["joint_position"]
    torch.testing.assert_close(out[CONFIG][:, 0], q)
    torch.testing.assert_close(out[REWARD][:, 0], goal_reward(model, state["achieved_goal"], state["desired_goal"]))
    # the colliding configuration, which the env did not keep, and its reward
    torch.testing.assert_close(out[CONFIG][:, 1], next_config(model, q, bad))
    assert (out[REWARD][:, 1] == model.collision_reward).all()
    assert (out[CONFIG][:, 2:] == 0).all() and (out[REWARD][:, 2:] == 0).all()
    # what the next call needs: this configuration and the action sent
    torch.testing.assert_close(out[PREV_CONFIG], q)
    torch.testing.assert_close(out[PREV_ACTION], out["action"])
    # a new action, one of the candidates, collision-free
    rec = module.last_recovery
    assert rec["env_index"].tolist() == [0, 1, 2, 3]
    assert not torch.equal(out["action"], bad)
    assert torch.equal(out["action"], rec["action"])
    assert ((rec["candidate_action"] == out["action"].unsqueeze(1)).all(-1)).any(-1).all()
    assert (~candidates_collide(model, state, rec["candidate_action"])).any(-1).all()
    assert not model.step(state, out["action"])[2].any()


def test_probabilities_follow_min_max_scaled_posterior_mean(model):
    state, bad = colliding_pairs(model, 3, seed=1)
    module = GPGuidedExploration(model, num_candidates=32, generator=torch.Generator().manual_seed(1))
    _, out = collide_and_recover(model, module, state, bad)
    rec = module.last_recovery
    cand_q = next_config(model, state["joint_position"].unsqueeze(1), rec["candidate_action"])
    torch.testing.assert_close(rec["candidate_config"], cand_q)
    collides = candidates_collide(model, state, rec["candidate_action"])
    for b in range(3):
        x = out[CONFIG][b, :2].double().numpy()
        y = out[REWARD][b, :2].double().numpy()
        mean, _ = np_posterior(x, y, cand_q[b].double().numpy(), 0.3, 1.0, 1e-2)
        free = ~collides[b].numpy()
        allowed = free if free.any() else np.ones_like(free)
        lo, hi = mean[allowed].min(), mean[allowed].max()
        want = np.where(allowed, (mean - lo) / (hi - lo), 0.0)
        want /= want.sum()
        np.testing.assert_allclose(rec["probability"][b].numpy(), want, rtol=1e-3, atol=1e-4)


def test_random_mode_is_uniform_over_free_candidates(model):
    state, bad = colliding_pairs(model, 4, seed=2)
    module = GPGuidedExploration(model, mode="random")
    collide_and_recover(model, module, state, bad)
    rec = module.last_recovery
    free = (~candidates_collide(model, state, rec["candidate_action"])).float()
    torch.testing.assert_close(rec["probability"], free / free.sum(-1, keepdim=True))


@pytest.mark.parametrize("mode", ["gp", "random"])
def test_mask_picks_only_free_candidates_and_the_papers_recovery_may_collide(model, mode):
    state, bad = colliding_pairs(model, 64, seed=6)
    for mask in (True, False):
        module = GPGuidedExploration(
            model, mode=mode, num_candidates=16, mask_colliding_candidates=mask,
            generator=torch.Generator().manual_seed(7),
        )
        _, out = collide_and_recover(model, module, state, bad)
        rec = module.last_recovery
        cand_hit = candidates_collide(model, state, rec["candidate_action"])
        avoidable = (~cand_hit).any(-1)
        assert cand_hit.any(-1).float().mean() > 0.3  # these states are next to obstacles
        hit = model.step(state, out["action"])[2].squeeze(-1)
        probability = rec["probability"]
        assert ("collides" in rec.keys()) == mask  # the paper's recovery checks no candidate
        if mask:
            assert torch.equal(rec["collides"], cand_hit)
            assert not (hit & avoidable).any()
            assert (probability[cand_hit & avoidable.unsqueeze(-1)] == 0).all()
        else:
            # the paper's recovery: the GP (or uniform) over all candidates, colliding ones included
            assert (probability[cand_hit] > 0).any()
            assert (hit & avoidable).any()
        torch.testing.assert_close(probability.sum(-1), torch.ones(64))


# start configurations from the task's joint box; the obstacle right next to the
# TCP, so that some candidates collide and some do not
def unit(low, high):
    return st.floats(low, high, allow_nan=False)


LOW, HIGH = UR5eReach.TASK_JOINT_LOW, UR5eReach.TASK_JOINT_HIGH
state_strategy = st.tuples(*(unit(lo, hi) for lo, hi in zip(LOW, HIGH)), *(unit(-0.25, 0.25) for _ in range(3)))
_MODEL = []


def shared_model():
    if not _MODEL:
        _MODEL.append(UR5eReach())
    return _MODEL[0]


@settings(max_examples=12, deadline=None)
@given(
    states=st.lists(state_strategy, min_size=1, max_size=6),
    actor_action=st.lists(unit(-3, 3), min_size=3, max_size=3),
    mode=st.sampled_from(["gp", "random"]),
    fit=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_never_out_of_bounds_nor_colliding_when_avoidable(states, actor_action, mode, fit, seed):
    model = shared_model()
    s = torch.tensor(states, dtype=torch.float32)
    b, n = s.shape[0], 16
    q = s[:, :3]
    box = aabb_from_center(model.achieved_goal(q) + s[:, 3:], model.obstacle_size.expand(b, 3))
    state = model.state_at(q, TensorDict(obstacle=box, batch_size=[b]), model.achieved_goal(q.flip(0)))
    gen = torch.Generator().manual_seed(seed)
    module = GPGuidedExploration(
        model, mode=mode, num_candidates=n, fit_hyperparameters=fit, fit_steps=3, generator=gen
    )
    action = torch.tensor(actor_action).expand(b, 3)  # an actor may even leave [-1, 1]
    with set_exploration_type(RANDOM):
        td = module(step_td(model, state, torch.rand(b, 3, generator=gen) * 2 - 1, is_init=True))
        for _ in range(4):  # collisions in a row: each a fresh recovery from the same state
            td = module(step_td(model, state, action, collision=True, carry=td))
            out = td["action"]
            assert out.shape == (b, 3) and torch.isfinite(out).all()
            assert (out.abs() <= 1).all()
            rec = module.last_recovery
            assert rec["env_index"].tolist() == list(range(b))
            avoidable = (~candidates_collide(model, state, rec["candidate_action"])).any(-1)
            hit = model.step(state, out)[2].squeeze(-1)
            assert not (hit & avoidable).any()


def test_passes_actor_action_through(model):
    state, bad = colliding_pairs(model, 4, seed=3)
    module = GPGuidedExploration(model)
    with set_exploration_type(RANDOM):
        td = module(step_td(model, state, bad, is_init=True))
        # no collision: untouched, whatever the action (even out of bounds)
        wild = torch.full((4, 3), 7.0)
        td = module(step_td(model, state, wild, carry=td))
        assert torch.equal(td["action"], wild)
        # a collision in only some envs changes only those
        td = module(step_td(model, state, bad, collision=[True, False, True, False], carry=td))
    out = td["action"]
    assert torch.equal(out[[1, 3]], bad[[1, 3]])
    assert not torch.equal(out[[0, 2]], bad[[0, 2]])
    assert module.last_recovery["env_index"].tolist() == [0, 2]


@pytest.mark.parametrize("mode", [ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN])
def test_deterministic_exploration_does_nothing(model, mode):
    state, bad = colliding_pairs(model, 4, seed=3)
    module = GPGuidedExploration(model)
    with set_exploration_type(RANDOM):
        first = module(step_td(model, state, bad, is_init=True))
    td = step_td(model, state, bad, collision=True, carry=first)
    before = td.clone()
    with set_exploration_type(mode):
        out = module(td)
    assert torch.equal(out["action"], bad)
    assert set(out.keys()) == set(before.keys()) and (out == before).all()  # nothing recorded either


def test_resets_per_row_on_is_init_only(model):
    state = model.sample_tasks(3, torch.Generator().manual_seed(5)).select(*model.state_keys)
    module = GPGuidedExploration(model)
    small = torch.full((3, 3), 0.1)

    def counts(td):
        return td[COUNT].squeeze(-1).tolist()

    with set_exploration_type(RANDOM):
        td = module(step_td(model, state, small, is_init=True))
        for _ in range(3):
            state = model.transition(state, small)
            td = module(step_td(model, state, small, carry=td))
        assert counts(td) == [4, 4, 4]
        state = model.transition(state, small)
        td = module(step_td(model, state, small, is_init=[False, True, False], carry=td))
        assert counts(td) == [5, 1, 5]
        torch.testing.assert_close(td[CONFIG][1, 0], state["joint_position"][1])
        assert (td[CONFIG][1, 1:] == 0).all() and (td[REWARD][1, 1:] == 0).all()
        torch.testing.assert_close(td[CONFIG][[0, 2], 4], state["joint_position"][[0, 2]])
        # a collision flag on the first step of an episode is not a recovery
        first = [True, False, False]
        td = module(step_td(model, state, small, is_init=first, collision=first, carry=td))
        assert torch.equal(td["action"], small)
        assert counts(td) == [1, 2, 6]
        # only is_init resets: a new goal without the flag continues the history
        moved = state.clone()
        moved["desired_goal"][0] += 0.1
        td = module(step_td(model, moved, small, carry=td))
        assert counts(td) == [2, 3, 7]
        # a zero count (what the primer writes at a reset) starts afresh too
        td[COUNT][2] = 0
        td = module(step_td(model, state, small, carry=td))
        assert counts(td) == [3, 4, 1]


def check_history(data, model, history_size, names=None):
    """Check a trajectory batch ``[..., T]`` against an independent recomputation, step by step.

    At an episode start the history holds the state and its goal reward; at every
    other step one push more: the state the previous action led to (the colliding
    configuration after a collision, recomputed), with the reward the env gave for
    that step (``("next", "reward")`` one step earlier, and ``model.step`` again);
    the other slots are unchanged. Returns the number of pushes checked.
    """
    names = dict(zip(KEYS, KEYS)) if names is None else names
    T = data.shape[-1]
    data = data.reshape(-1, T)
    H = history_size
    q, a = data["joint_position"], data["action"]
    init, coll = data["is_init"].squeeze(-1), data["collision"].squeeze(-1)
    count = data[names[COUNT]].squeeze(-1)
    hx, hr = data[names[CONFIG]], data[names[REWARD]]
    assert hx.shape[-2:] == (H, model.config_dim) and hr.shape[-1] == H
    torch.testing.assert_close(data[names[PREV_CONFIG]], q)
    torch.testing.assert_close(data[names[PREV_ACTION]], a)
    checked = 0
    for t in range(T):
        new = init[:, t]
        if new.any():
            assert (count[new, t] == 1).all()
            torch.testing.assert_close(hx[new, t, 0], q[new, t])
            want = goal_reward(model, data["achieved_goal"][new, t], data["desired_goal"][new, t])
            torch.testing.assert_close(hr[new, t, 0], want)
            assert (hx[new, t, 1:] == 0).all() and (hr[new, t, 1:] == 0).all()
            checked += int(new.sum())
        go = ~new
        if t == 0 or not go.any():
            continue
        rows = go.nonzero().squeeze(-1)
        assert torch.equal(count[rows, t], count[rows, t - 1] + 1)
        slot = (count[rows, t] - 1) % H
        hit = coll[rows, t]
        # after a collision the env put the arm back
        assert torch.equal(q[rows[hit], t], q[rows[hit], t - 1])
        led = torch.where(hit.unsqueeze(-1), next_config(model, q[rows, t - 1], a[rows, t - 1]), q[rows, t])
        torch.testing.assert_close(hx[rows, t, slot], led)
        env_reward = data["next", "reward"][rows, t - 1].squeeze(-1)
        torch.testing.assert_close(hr[rows, t, slot], env_reward)
        prev = data[rows, t - 1].select(*model.state_keys)
        torch.testing.assert_close(hr[rows, t, slot], model.step(prev, a[rows, t - 1])[1].squeeze(-1))
        assert torch.equal(hr[rows, t, slot] == model.collision_reward, hit)
        other = torch.ones(rows.numel(), H, dtype=torch.bool)
        other[torch.arange(rows.numel()), slot] = False
        assert torch.equal(hx[rows, t][other], hx[rows, t - 1][other])
        assert torch.equal(hr[rows, t][other], hr[rows, t - 1][other])
        checked += rows.numel()
    return checked


PUSH = (1.0, 1.0, 1.0)  # a constant actor that runs into things and would stay stuck


def push_actor(out_key="action"):
    push = torch.tensor(PUSH)
    return TensorDictModule(lambda o: push.expand(*o.shape[:-1], 3).clone(), ["observation"], [out_key])


def with_gp_keys(env, module):
    return TransformedEnv(env, Compose(InitTracker(), module.make_tensordict_primer()))


def test_primer_declares_the_keys():
    base = UR5eReachEnv(num_envs=3, seed=0)
    module = GPGuidedExploration(base.model, history_size=8)
    env = with_gp_keys(base, module)
    check_env_specs(env, seed=0)
    spec = env.observation_spec
    assert spec[CONFIG].shape == (3, 8, 3) and spec[REWARD].shape == (3, 8) and spec[COUNT].shape == (3, 1)
    assert spec[PREV_CONFIG].shape == (3, 3) and spec[PREV_ACTION].shape == (3, 3)
    assert spec[COUNT].dtype == torch.long and spec[CONFIG].dtype == torch.float32
    td = env.reset()
    assert all((td[k] == 0).all() for k in KEYS)


@pytest.mark.parametrize("history_size", [64, 4])
def test_history_in_a_rollout_and_recoveries(history_size):
    base = UR5eReachEnv(num_envs=6, seed=0, collision_type=2, max_steps=10)
    module = GPGuidedExploration(base.model, history_size=history_size, generator=torch.Generator().manual_seed(0))
    env = with_gp_keys(base, module)
    actor = push_actor()
    with set_exploration_type(RANDOM), torch.no_grad():
        rollout = env.rollout(25, TensorDictSequential(actor, module), break_when_any_done=False)
        stuck = env.rollout(25, actor, break_when_any_done=False)
    # episodes ended and began inside the rollout (max_steps=10)
    assert rollout["is_init"][:, 1:].any()
    assert check_history(rollout, base.model, history_size) == 6 * 25
    if history_size == 4:
        assert (rollout[COUNT] > 4).any()  # the ring buffer wrapped
    after_collision = rollout["collision"].squeeze(-1) & ~rollout["is_init"].squeeze(-1)
    assert after_collision.any()
    push = torch.tensor(PUSH)
    assert (rollout["action"][~after_collision] == push).all()
    assert (rollout["action"][after_collision] != push).any(-1).all()
    assert (rollout["action"].abs() <= 1).all()
    assert rollout["next", "collision"].sum() < stuck["next", "collision"].sum()


def test_two_envs_share_one_module():
    envs = [
        UR5eReachEnv(num_envs=3, seed=1, collision_type=2, max_steps=8),
        UR5eReachEnv(batch_size=(2, 2), seed=2, collision_type=2, max_steps=8),
    ]
    module = GPGuidedExploration(envs[0].model, history_size=16, generator=torch.Generator().manual_seed(0))
    envs = [with_gp_keys(env, module) for env in envs]
    policy = TensorDictSequential(push_actor(), module)
    tds = [env.reset() for env in envs]
    steps = [[], []]
    with set_exploration_type(RANDOM), torch.no_grad():
        for _ in range(20):  # alternately, one step each
            for i, env in enumerate(envs):
                td, tds[i] = env.step_and_maybe_reset(policy(tds[i]))
                steps[i].append(td)
    for i, env in enumerate(envs):
        data = torch.stack(steps[i], dim=len(env.batch_size))
        assert data.shape == (*env.batch_size, 20)
        assert check_history(data, env.model, 16) == env.batch_size.numel() * 20
        after_collision = data["collision"] & ~data["is_init"]
        assert after_collision.any() and data["is_init"][..., 1:, :].any()


# ------------------------------------------------------- collector workers
COLLECTOR_H = 16
PUBLIC = {key: key.lstrip("_") for key in KEYS}  # collectors drop "_" keys from their output


def make_collector_env():
    base = UR5eReachEnv(num_envs=4, collision_type=2, max_steps=20)
    return with_gp_keys(base, GPGuidedExploration(base.model, history_size=COLLECTOR_H))


class _Push(torch.nn.Module):
    def forward(self, observation):
        return torch.tensor(PUSH).expand(*observation.shape[:-1], 3).clone()


class _Copy(torch.nn.Module):
    def forward(self, *values):
        return tuple(v.clone() for v in values)


def make_collector_policy():
    """The actor, the GP module, and public copies of what they wrote, for the test to read."""
    actor = TensorDictModule(_Push(), ["observation"], ["actor_action"])
    to_action = TensorDictModule(_Copy(), ["actor_action"], ["action"])
    gp = GPGuidedExploration(UR5eReach(), history_size=COLLECTOR_H, num_candidates=16)
    watch = TensorDictModule(_Copy(), list(KEYS), [PUBLIC[k] for k in KEYS])
    return TensorDictSequential(actor, to_action, gp, watch)


def test_multi_sync_collector_with_two_workers():
    from torchrl.collectors import MultiSyncCollector

    # one policy, pickled into each worker with its task model
    collector = MultiSyncCollector(
        [make_collector_env, make_collector_env], policy=make_collector_policy(),
        frames_per_batch=160, total_frames=320,
    )
    try:
        collector.set_seed(0)
        batches = [batch.clone() for batch in collector]
    finally:
        collector.shutdown()
    assert len(batches) == 2 and batches[0].shape == (2, 4, 20)
    data = torch.cat(batches, dim=-1)  # each env's steps in order, across the two batches
    assert not any(k in data.keys() for k in KEYS)
    # recoveries happened in both workers, and only after collisions
    after_collision = (data["collision"] & ~data["is_init"]).squeeze(-1)
    assert after_collision.flatten(1).any(-1).all()
    changed = (data["action"] != data["actor_action"]).any(-1)
    assert torch.equal(changed, after_collision)
    # the workers ran different tasks
    assert not torch.equal(data["desired_goal"][0], data["desired_goal"][1])
    model = UR5eReach()
    assert check_history(data, model, COLLECTOR_H, names=PUBLIC) == 2 * 4 * 40
    assert data["is_init"][..., 1:, :].any() and (data["gp_history_count"] > COLLECTOR_H).any()


# ------------------------------------------------------------ misuse
def test_warns_without_init_tracker_or_primer(model):
    state = model.sample_tasks(2, torch.Generator().manual_seed(0)).select(*model.state_keys)
    module = GPGuidedExploration(model)
    td = step_td(model, state, torch.zeros(2, 3))
    del td["is_init"]
    with set_exploration_type(RANDOM), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module(td)
    assert any("InitTracker" in str(w.message) for w in caught)
    module = GPGuidedExploration(model)
    with set_exploration_type(RANDOM):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            module(step_td(model, state, torch.zeros(2, 3), is_init=True))  # a first step needs no keys
        with pytest.warns(UserWarning, match="make_tensordict_primer"):
            module(step_td(model, state, torch.zeros(2, 3)))  # the keys were not carried


def test_keys_of_another_history_size_raise(model):
    state = model.sample_tasks(2, torch.Generator().manual_seed(0)).select(*model.state_keys)
    with set_exploration_type(RANDOM):
        td = GPGuidedExploration(model, history_size=8)(step_td(model, state, torch.zeros(2, 3), is_init=True))
        with pytest.raises(ValueError, match="history_size"):
            GPGuidedExploration(model, history_size=4)(step_td(model, state, torch.zeros(2, 3), carry=td))


@pytest.mark.parametrize(
    "kwargs,error",
    [
        (dict(mode="greedy"), ValueError),
        (dict(num_candidates=0), ValueError),
        (dict(history_size=1.5), TypeError),
        (dict(lengthscale=0.0), ValueError),
        (dict(noise=-1e-3), ValueError),
        (dict(fit_hyperparameters="yes"), TypeError),
        (dict(mask_colliding_candidates=1), TypeError),
        (dict(generator=0), TypeError),
    ],
)
def test_bad_configuration_raises(model, kwargs, error):
    with pytest.raises(error):
        GPGuidedExploration(model, **kwargs)


def test_model_must_be_a_task_model():
    with pytest.raises(TypeError, match="model"):
        GPGuidedExploration(object())
    with pytest.raises(TypeError, match="model"):
        GPGuidedExploration(UR5eReachEnv(num_envs=1))  # the env holds the model, it is not one


def test_recorded_rewards_are_the_envs_rewards_of_those_transitions(model):
    """In a rollout, each step's newest history entry holds the reward the env gave the transition into it
    (the collision penalty after a collision, -distance or the success reward otherwise)."""
    gp = GPGuidedExploration(model, generator=torch.Generator().manual_seed(0))
    env = TransformedEnv(ReachEnv(model, num_envs=16, seed=3), Compose(
        CollisionHandling(2), model.observation_transform(), InitTracker(), gp.make_tensordict_primer()))
    torch.manual_seed(0)
    actor = Actor(torch.nn.Sequential(torch.nn.Linear(15, 3), torch.nn.Tanh()), in_keys=["observation"])
    with set_exploration_type(RANDOM), torch.no_grad():
        rollout = env.rollout(30, TensorDictSequential(actor, gp), break_when_any_done=False)
    count = rollout[COUNT].squeeze(-1)  # [B, T]
    newest = rollout[REWARD].gather(-1, ((count - 1) % gp.history_size).unsqueeze(-1)).squeeze(-1)
    env_reward = rollout["next", "reward"].squeeze(-1)
    later = ~rollout["is_init"].squeeze(-1)[:, 1:]  # steps that record the previous transition
    torch.testing.assert_close(newest[:, 1:][later], env_reward[:, :-1][later])
    collided = rollout["next", "collision"].squeeze(-1)[:, :-1][later]
    assert collided.sum() >= 5  # the penalty path is exercised, not only -distance
