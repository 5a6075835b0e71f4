"""SILPLoss: the paper's eqs. 5-7 by hand with the task model, gradient routing, demo-free batches, SAC / DDPG / TD3."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import Actor, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import DDPGLoss, SACLoss, SoftUpdate, TD3Loss

from torchrl_silp import UR5eReachEnv
from torchrl_silp.objectives import SILPLoss

N = 8
IS_DEMO = [True, True, True, True, True, True, False, False]
STATE_KEYS = ("joint_position", "achieved_goal", "obstacle", "desired_goal")


class Critic(nn.Module):
    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(18, 32), nn.Tanh(), nn.Linear(32, 1))

    def forward(self, obs, act):
        return self.net(torch.cat([obs, act], -1))


def spec():
    return Bounded(-1.0, 1.0, (3,))


def ddpg_parts():
    actor = Actor(nn.Sequential(nn.Linear(15, 32), nn.Tanh(), nn.Linear(32, 3), nn.Tanh()), in_keys=["observation"])
    critic = ValueOperator(Critic(), in_keys=["observation", "action"])
    return actor, critic


def sac_actor():
    net = nn.Sequential(nn.Linear(15, 32), nn.Tanh(), nn.Linear(32, 6), NormalParamExtractor())
    return ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        spec=spec(),
    )


def make_loss(kind):
    torch.manual_seed(0)
    if kind == "ddpg":
        actor, critic = ddpg_parts()
        return DDPGLoss(actor, critic), actor
    if kind == "td3":
        actor, critic = ddpg_parts()
        return TD3Loss(actor, critic, action_spec=spec()), actor
    actor = sac_actor()
    return SACLoss(actor, ValueOperator(Critic(), in_keys=["observation", "action"]), action_spec=spec()), actor


def make_batch(model, seed=0, demos=IS_DEMO):
    """Transitions from sampled tasks: named state and flat observation at the root and under "next"."""
    gen = torch.Generator().manual_seed(seed)
    state = model.sample_tasks(N, gen).select(*STATE_KEYS)
    action = torch.rand(N, 3, generator=gen) * 2 - 1
    nxt, reward = model.step(state, action)[:2]
    # stored rewards the model could not produce: the filter must read them, not recompute them
    reward[1] = 5.0
    reward[2] = -50.0
    false = torch.zeros(N, 1, dtype=torch.bool)
    td = state.clone()
    td.update(dict(observation=model.observation(state), action=action, is_demo=torch.tensor(demos).unsqueeze(-1)))
    nxt.update(dict(observation=model.observation(nxt), reward=reward, done=false, terminated=false))
    td["next"] = nxt
    return td


# ------------------------------------------------------------- by hand
def hand_policy(actor, obs):
    """π(s) of one flat observation: the deterministic actor's output or the TanhNormal's deterministic sample."""
    td = TensorDict(observation=obs.unsqueeze(0), batch_size=[1])
    with torch.no_grad():
        if isinstance(actor, ProbabilisticActor):
            return actor.get_dist(td).deterministic_sample[0]
        return actor(td)["action"][0]


def hand_return(model, actor, r0, s1, k, gamma):
    """Eq. 7: r_0 + sum_j gamma^j f_r(s_j, pi(s_j)), one state ([1] TensorDict) at a time, f_s then f_r."""
    ret, state = float(r0), s1
    for j in range(1, k + 1):
        action = hand_policy(actor, model.observation(state)[0]).unsqueeze(0)
        nxt = model.transition(state, action)
        ret += gamma**j * float(model.reward(state, nxt))
        state = nxt
    return ret


def hand_q(loss, s, a):
    """min over the loss's Q ensemble (one member for DDPG) of Q(s, a), member by member."""
    name = "qvalue_network" if hasattr(loss, "qvalue_network") else "value_network"
    net, params = getattr(loss, name), getattr(loss, f"{name}_params").detach()
    members = [params[j] for j in range(params.batch_size[0])] if params.batch_dims else [params]
    values = []
    for p in members:
        with p.to_module(net), torch.no_grad():
            td = TensorDict(observation=s.unsqueeze(0), action=a.unsqueeze(0), batch_size=[1])
            values.append(float(net(td)["state_action_value"]))
    return min(values)


def hand_bc(model, loss, actor, data, filt, k, gamma, lambda2):
    total, passed, demos, returns = 0.0, [], 0, []
    for i in range(N):
        if not bool(data["is_demo"][i]):
            continue
        demos += 1
        s, a = data["observation"][i], data["action"][i]
        pi = hand_policy(actor, s)
        if filt == "reward":
            s0 = data.select(*STATE_KEYS)[i : i + 1]
            s1_demo = data["next"].select(*STATE_KEYS)[i : i + 1]
            r_demo = hand_return(model, actor, data["next", "reward"][i], s1_demo, k, gamma)
            s1 = model.transition(s0, pi.unsqueeze(0))
            r_pi = hand_return(model, actor, model.reward(s0, s1), s1, k, gamma)
            keep = r_demo > r_pi
            returns.append((r_demo, r_pi))
        else:
            keep = hand_q(loss, s, a) > hand_q(loss, s, pi)
        passed.append(keep)
        total += float(keep) * float(((pi - a) ** 2).sum())
    return lambda2 * total / demos, passed, returns


@pytest.mark.parametrize("demo_rows", ["select", "mask"])
@pytest.mark.parametrize(
    "kind,filt,k",
    [("ddpg", "reward", 1), ("ddpg", "reward", 2), ("sac", "reward", 2), ("ddpg", "q", 1), ("sac", "q", 1)],
)
def test_bc_term_matches_hand_computation(model, kind, filt, k, demo_rows):
    rl_loss, actor = make_loss(kind)
    gamma = 0.9
    silp = SILPLoss(rl_loss, model, filter=filt, k=k, gamma=gamma, lambda1=0.5, lambda2=3.0, demo_rows=demo_rows)
    # a batch on which every case below sees demos both pass and fail the filter
    data = make_batch(model, seed=5)
    want, passed, returns = hand_bc(model, rl_loss, actor, data, filt, k, gamma, 3.0)
    loss_bc, meta = silp.bc_loss(data.clone())
    torch.testing.assert_close(loss_bc, torch.tensor(want), rtol=1e-5, atol=1e-6)
    mask = silp.bc_filter(data.clone())[: sum(IS_DEMO)]
    assert mask.tolist() == passed
    assert 0 < sum(passed) < len(passed), "the batch should exercise both filter outcomes"
    if filt == "reward":
        assert passed[1:3] == [True, False]  # stored +5 always wins, stored -50 always loses
        r_demo, r_pi = silp.lookahead_returns(data.clone())
        torch.testing.assert_close(r_demo[:6], torch.tensor([r[0] for r in returns]), rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(r_pi[:6], torch.tensor([r[1] for r in returns]), rtol=1e-5, atol=1e-5)
        # the look-ahead reads the stored reward and next state, not the flat observations
        moved = data.clone()
        moved["observation"] = torch.zeros_like(moved["observation"])
        moved["next", "observation"] = torch.zeros_like(moved["next", "observation"])
        pi = silp._policy_action(data)
        torch.testing.assert_close(silp.lookahead_returns(moved, pi)[0], r_demo)
    assert float(meta["num_demos"]) == sum(IS_DEMO)
    torch.testing.assert_close(meta["bc_filter_fraction"], torch.tensor(sum(passed) / len(passed)))


@settings(max_examples=15, deadline=None)
@given(demos=st.lists(st.booleans(), min_size=N, max_size=N).filter(any), seed=st.integers(0, 50))
def test_both_ways_to_the_demo_rows_give_the_hand_computed_term_and_the_same_actor_gradient(model, demos, seed):
    rl_loss, actor = make_loss("ddpg")
    data = make_batch(model, seed=seed, demos=demos)
    want, passed, _ = hand_bc(model, rl_loss, actor, data, "reward", 1, 0.9, 2.0)
    grads = {}
    for demo_rows in ("select", "mask"):
        silp = SILPLoss(rl_loss, model, filter="reward", gamma=0.9, lambda2=2.0, demo_rows=demo_rows)
        loss_bc, meta = silp.bc_loss(data.clone())
        torch.testing.assert_close(loss_bc, torch.tensor(want), rtol=1e-5, atol=1e-6)
        assert float(meta["num_demos"]) == sum(demos)
        torch.testing.assert_close(meta["bc_filter_fraction"], torch.tensor(sum(passed) / len(passed)))
        for p in rl_loss.actor_network_params.values(True, True):
            p.grad = None
        loss_bc.backward()
        grads[demo_rows] = [g.clone() for g in _grads(rl_loss.actor_network_params) if g is not None]
    assert len(grads["select"]) == len(grads["mask"]) > 0
    for a, b in zip(grads["select"], grads["mask"]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_reward_filter_discounts_with_the_wrapped_loss_gamma(model):
    rl_loss, actor = make_loss("ddpg")
    silp = SILPLoss(rl_loss, model, filter="reward", k=2)
    silp.make_value_estimator(gamma=0.5)
    data = make_batch(model, seed=5)
    r_demo, _ = silp.lookahead_returns(data.clone())
    for i in range(N):
        s1 = data["next"].select(*STATE_KEYS)[i : i + 1]
        want = hand_return(model, actor, data["next", "reward"][i], s1, 2, 0.5)
        assert r_demo[i].item() == pytest.approx(want, rel=1e-5, abs=1e-5)


def test_forward_scales_rl_terms_and_adds_bc(model):
    rl_loss, actor = make_loss("ddpg")
    silp = SILPLoss(rl_loss, model, filter="none", lambda1=0.25, lambda2=2.0)
    SoftUpdate(silp.rl_loss, tau=0.01)
    data = make_batch(model)
    ref = rl_loss(data.clone())
    out = silp(data.clone())
    for key in ("loss_actor", "loss_value"):
        torch.testing.assert_close(out[key], 0.25 * ref[key])
    # filter "none": every demo counts, so bc_mse is the unweighted mean and loss_bc = lambda2 * it
    errors = [float(((hand_policy(actor, data["observation"][i]) - data["action"][i]) ** 2).sum()) for i in range(6)]
    torch.testing.assert_close(out["bc_mse"], torch.tensor(sum(errors) / 6))
    torch.testing.assert_close(out["loss_bc"], 2.0 * out["bc_mse"])
    assert float(out["bc_filter_fraction"]) == 1.0
    for key in ("bc_mse", "bc_filter_fraction", "num_demos"):
        assert not out[key].requires_grad
    assert set(silp.out_keys) >= {"loss_bc", "loss_actor", "loss_value", "bc_mse"}
    in_keys = set(SILPLoss(rl_loss, model).in_keys)
    assert {"is_demo", ("next", "reward"), *STATE_KEYS, *[("next", k) for k in STATE_KEYS]} <= in_keys
    # the Q-filter reads the critic's inputs, not the named state
    assert "joint_position" not in set(SILPLoss(rl_loss, filter="q").in_keys)


def _grads(params):
    return [p.grad for p in params.values(True, True)]


@pytest.mark.parametrize("kind,filt", [("ddpg", "reward"), ("sac", "q"), ("td3", "q")])
def test_bc_gradient_reaches_actor_only(model, kind, filt):
    rl_loss, _ = make_loss(kind)
    silp = SILPLoss(rl_loss, model, filter=filt)
    data = make_batch(model)
    loss_bc, _ = silp.bc_loss(data)
    assert loss_bc > 0
    loss_bc.backward()
    actor_grads = _grads(rl_loss.actor_network_params)
    assert all(g is not None for g in actor_grads) and any(g.abs().sum() > 0 for g in actor_grads)
    critic = rl_loss.qvalue_network_params if kind != "ddpg" else rl_loss.value_network_params
    assert all(g is None or not g.any() for g in _grads(critic))
    if kind == "sac":
        assert rl_loss.log_alpha.grad is None


@pytest.mark.parametrize("demo_rows", ["select", "mask"])
@pytest.mark.parametrize("filt", ["reward", "q", "none"])
def test_demo_free_batch_gives_zero(model, filt, demo_rows):
    rl_loss, _ = make_loss("sac")
    silp = SILPLoss(rl_loss, model, filter=filt, demo_rows=demo_rows)
    SoftUpdate(silp.rl_loss, tau=0.01)
    data = make_batch(model, demos=[False] * N)
    out = silp(data)
    assert float(out["loss_bc"].detach()) == 0.0 and float(out["num_demos"]) == 0.0
    assert float(out["bc_filter_fraction"]) == 0.0 and float(out["bc_mse"]) == 0.0
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    assert torch.isfinite(total)
    total.backward()
    assert all(torch.isfinite(g).all() for g in _grads(rl_loss.actor_network_params) if g is not None)


@pytest.mark.parametrize("kind", ["sac", "ddpg", "td3"])
def test_one_optimisation_step(kind):
    env = UR5eReachEnv(num_envs=4, seed=1)
    rl_loss, _ = make_loss(kind)
    # the env holding the model works as well as the model
    silp = SILPLoss(rl_loss, env, filter="reward", lambda2=2.0)
    assert silp.model is env.model
    updater = SoftUpdate(silp.rl_loss, tau=0.5)
    optim = torch.optim.Adam(silp.parameters(), lr=1e-2)
    # every trainable tensor of the wrapped loss, nothing else (no target nets, no lambdas)
    assert {id(p) for p in silp.parameters()} == {id(p) for p in rl_loss.parameters()}
    with set_exploration_type(ExplorationType.RANDOM):
        data = env.rollout(4).reshape(-1)
    data["is_demo"] = torch.arange(16).unsqueeze(-1) % 2 == 0
    before = [p.detach().clone() for p in rl_loss.actor_network_params.values(True, True)]
    target = rl_loss.target_qvalue_network_params if kind != "ddpg" else rl_loss.target_value_network_params
    target_before = [p.clone() for p in target.values(True, True)]
    out = silp(data)
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    optim.zero_grad()
    total.backward()
    optim.step()
    updater.step()
    assert all(torch.isfinite(v).all() for v in out.values(True, True) if isinstance(v, torch.Tensor))
    after = list(rl_loss.actor_network_params.values(True, True))
    assert any(not torch.equal(b, a) for b, a in zip(before, after))
    assert any(not torch.equal(b, a) for b, a in zip(target_before, target.values(True, True)))
    assert float(out["num_demos"]) == 8


def test_soft_update_moves_targets_by_tau(model):
    rl_loss, _ = make_loss("ddpg")
    silp = SILPLoss(rl_loss, model, filter="reward")
    updater = SoftUpdate(silp.rl_loss, tau=0.25)
    # SoftUpdate on the wrapper finds no target parameters: they belong to the wrapped loss
    with pytest.raises(RuntimeError, match="target"):
        SoftUpdate(silp, tau=0.25)
    source = rl_loss.value_network_params.detach().clone()
    target = rl_loss.target_value_network_params
    with torch.no_grad():
        for p in rl_loss.value_network_params.values(True, True):
            p.add_(1.0)
    before = target.detach().clone()
    updater.step()
    for key, value in target.items(True, True):
        want = 0.75 * before[key] + 0.25 * (source[key] + 1.0)
        torch.testing.assert_close(value.detach(), want)


def test_gamma_defaults_to_wrapped_loss():
    rl_loss, _ = make_loss("ddpg")
    silp = SILPLoss(rl_loss, filter="none")
    assert float(silp.gamma) == pytest.approx(0.99)
    silp.make_value_estimator(gamma=0.5)
    assert float(silp.gamma) == pytest.approx(0.5)
    assert SILPLoss(rl_loss, filter="none", gamma=0.7).gamma == 0.7


def test_set_keys_forwards_and_rebuilds_in_keys(model):
    rl_loss, _ = make_loss("sac")
    silp = SILPLoss(rl_loss, model)
    silp.set_keys(is_demo="demo_flag", reward="r")
    assert "demo_flag" in silp.in_keys and ("next", "r") in silp.in_keys
    assert rl_loss.tensor_keys.reward == "r"
    with pytest.raises(ValueError, match="accepted"):
        silp.set_keys(nonsense="x")


def test_lambdas_are_schedulable(model):
    rl_loss, _ = make_loss("ddpg")
    silp = SILPLoss(rl_loss, model, filter="none")
    SoftUpdate(silp.rl_loss, tau=0.01)
    assert float(silp(make_batch(model))["loss_bc"].detach()) > 0.0
    silp.lambda2 = 0.0
    assert float(silp(make_batch(model))["loss_bc"].detach()) == 0.0


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(filter="reward"), "needs model"),
        (dict(filter="bogus"), "filter must be one of"),
        (dict(filter="none", k=0), "k must be"),
        (dict(filter="none", lambda1=-1.0), "lambda1"),
        (dict(filter="none", lambda2=float("nan")), "lambda2"),
        (dict(filter="none", gamma=1.5), "gamma"),
        (dict(filter="none", demo_rows="all"), "demo_rows must be one of"),
    ],
)
def test_bad_configuration_raises(kwargs, match):
    rl_loss, _ = make_loss("ddpg")
    with pytest.raises(ValueError, match=match):
        SILPLoss(rl_loss, **kwargs)


def test_a_value_of_the_wrong_kind_raises_a_type_error():
    rl_loss, _ = make_loss("ddpg")
    with pytest.raises(TypeError, match="k must be"):
        SILPLoss(rl_loss, filter="none", k=1.5)


def test_bad_model_and_loss_raise():
    rl_loss, _ = make_loss("ddpg")
    with pytest.raises(TypeError, match="TaskModel"):
        SILPLoss(rl_loss, object(), filter="reward")
    with pytest.raises(TypeError, match="LossModule"):
        SILPLoss(nn.Linear(2, 2), filter="none")


def test_compiled_loss_traces_once_for_batches_of_one_shape(model):
    """A compiled SILPLoss called on a second batch of the same shape runs the code traced on the first:
    nothing the first call sets (e.g. lazily built keys) makes dynamo compile again."""
    from torch._dynamo.testing import CompileCounter

    torch._dynamo.reset()
    loss, _ = make_loss("ddpg")
    silp = SILPLoss(loss, model, filter="none", lambda2=2.0, demo_rows="mask")
    silp.make_value_estimator(gamma=0.9)  # as a recipe does (DDPGLoss would make its default one on first use)
    counter = CompileCounter()  # dynamo's trace only: no inductor
    compiled = torch.compile(silp, backend=counter)
    first = compiled(make_batch(model, seed=0))
    traced = counter.frame_count
    second = compiled(make_batch(model, seed=1))
    assert traced > 0
    assert counter.frame_count == traced
    # the second call computed its own batch's term, not a replay of the first's
    eager = silp(make_batch(model, seed=1))
    torch.testing.assert_close(second["loss_bc"], eager["loss_bc"])
    assert not torch.equal(first["loss_bc"], second["loss_bc"])
