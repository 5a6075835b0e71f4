"""make_averaged_actor: AveragedModel on the recipes' TorchRL actors, the EMA against an independent computation."""

import copy
import io

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import InteractionType, NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torch.optim.swa_utils import AveragedModel
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhModule, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss

from torchrl_silp import UR5eReachEnv
from torchrl_silp.modules.averaging import make_averaged_actor

DECAY = 0.8
K = 6


@pytest.fixture(scope="module")
def env():
    return UR5eReachEnv(num_envs=4, seed=0)


def make_actor(kind, env):
    """The actors of ``recipes/builders.make_actor_critic`` (lazy MLPs, initialized by one forward)."""
    spec = env.action_spec_unbatched
    torch.manual_seed(0)
    if kind == "sac":
        net = nn.Sequential(
            MLP(num_cells=[32, 32], out_features=2 * spec.shape[-1], activation_class=nn.ReLU),
            NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4),
        )
        actor = ProbabilisticActor(
            TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
            in_keys=["loc", "scale"],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
            default_interaction_type=InteractionType.RANDOM,
            return_log_prob=False,
        )
    else:
        actor = TensorDictSequential(
            TensorDictModule(
                MLP(num_cells=[32, 32], out_features=spec.shape[-1], activation_class=nn.ReLU),
                in_keys=["observation"],
                out_keys=["param"],
            ),
            TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
        )
    with torch.no_grad():
        actor(env.fake_tensordict())
    return actor


def observations(n=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(observation=torch.randn(n, 15, generator=g), batch_size=[n])


def train_steps(actor, k=K, seed=1):
    """``k`` Adam steps on a regression of the (deterministic) action; the parameters after each, float64."""
    opt = torch.optim.Adam(actor.parameters(), lr=1e-2)
    target = torch.rand(16, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    snapshots = []
    for i in range(k):
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            action = actor(observations(seed=i))["action"]
        loss = (action - target).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        snapshots.append([p.detach().double().clone() for p in actor.parameters()])
        yield snapshots[-1]


def ema_closed_form(theta0, thetas, decay):
    """decay^k θ0 + (1 - decay) Σ_i decay^(k-i) θ_i, float64."""
    k = len(thetas)
    out = [decay**k * p for p in theta0]
    for i, theta in enumerate(thetas, start=1):
        out = [o + (1 - decay) * decay ** (k - i) * p for o, p in zip(out, theta)]
    return out


@pytest.mark.parametrize("kind", ["sac", "deterministic"])
def test_deep_copy_of_the_actor(kind, env):
    actor = make_actor(kind, env)
    averaged = make_averaged_actor(actor, DECAY)
    assert isinstance(averaged, AveragedModel)
    copy_ = averaged.module
    assert type(copy_) is type(actor) and copy_ is not actor
    assert copy_.in_keys == actor.in_keys and copy_.out_keys == actor.out_keys
    own = dict(actor.named_parameters())
    avg = dict(copy_.named_parameters())
    assert own.keys() == avg.keys() and len(own) == 6
    for name, p in own.items():
        assert torch.equal(p, avg[name]) and p.data_ptr() != avg[name].data_ptr()
        assert not avg[name].requires_grad
    for (name, b), (name2, b2) in zip(actor.named_buffers(), copy_.named_buffers()):
        assert name == name2 and torch.equal(b, b2) and b.data_ptr() != b2.data_ptr()
    assert int(averaged.n_averaged) == 1
    # the copy is independent of the actor
    with torch.no_grad():
        next(actor.parameters()).add_(1.0)
    assert not torch.equal(next(actor.parameters()), next(copy_.parameters()))


@pytest.mark.parametrize("kind", ["sac", "deterministic"])
def test_ema_after_k_optimiser_steps(kind, env):
    actor = make_actor(kind, env)
    theta0 = [p.detach().double().clone() for p in actor.parameters()]
    averaged = make_averaged_actor(actor, DECAY)
    # the hand-written EMA the training loop kept so far (recipes/loop.py), for comparison
    by_hand = TensorDict.from_module(actor).data.clone()
    thetas = []
    for theta in train_steps(actor):
        thetas.append(theta)
        averaged.update_parameters(actor)
        by_hand.lerp_(TensorDict.from_module(actor).data, 1.0 - DECAY)
    assert int(averaged.n_averaged) == K + 1
    expected = ema_closed_form(theta0, thetas, DECAY)
    got = list(averaged.module.parameters())
    assert len(got) == len(expected)
    for g, e, last in zip(got, expected, thetas[-1]):
        torch.testing.assert_close(g.double(), e, atol=2e-7, rtol=0)
        assert not torch.allclose(g.double(), last)  # an average, not the last parameters
    # bit for bit the recipes' former lerp_ EMA
    for g, h in zip(got, by_hand.values(True, True)):
        assert torch.equal(g, h)


@pytest.mark.parametrize("kind", ["sac", "deterministic"])
def test_averaged_module_runs_as_a_tensordict_module(kind, env):
    actor = make_actor(kind, env)
    averaged = make_averaged_actor(actor, DECAY)
    for _ in train_steps(actor, k=3):
        averaged.update_parameters(actor)
    td = env.reset()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        out = averaged.module(td.clone())
        # the same as the actor holding the averaged parameters
        twin = copy.deepcopy(actor)
        twin.load_state_dict(averaged.module.state_dict())
        expected = twin(td.clone())["action"]
        online = actor(td.clone())["action"]
        # AveragedModel.forward calls the copy too
        via_forward = averaged(td.clone())["action"]
    assert out["action"].shape == (4, 3)
    assert env.action_spec.is_in(out["action"])
    torch.testing.assert_close(out["action"], expected, atol=0, rtol=0)
    torch.testing.assert_close(via_forward, expected, atol=0, rtol=0)
    assert not torch.allclose(out["action"], online)
    # a rollout with the averaged actor
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(3, averaged.module)
    assert rollout["action"].shape == (4, 3, 3)


def test_checkpoint_round_trip(env):
    actor = make_actor("sac", env)
    averaged = make_averaged_actor(actor, DECAY)
    steps = train_steps(actor, k=4)
    for _ in range(2):
        next(steps)
        averaged.update_parameters(actor)
    buffer = io.BytesIO()
    torch.save({"actor": actor.state_dict(), "averaged": averaged.state_dict()}, buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)
    assert "n_averaged" in state["averaged"]
    fresh = make_actor("sac", env)
    fresh.load_state_dict(state["actor"])
    restored = make_averaged_actor(fresh, DECAY)
    restored.load_state_dict(state["averaged"])
    assert int(restored.n_averaged) == 3
    for a, b in zip(averaged.module.parameters(), restored.module.parameters()):
        assert torch.equal(a, b)
    # both continue identically
    next(steps)
    with torch.no_grad():
        for p, q in zip(fresh.parameters(), actor.parameters()):
            p.copy_(q)
    averaged.update_parameters(actor)
    restored.update_parameters(fresh)
    for a, b in zip(averaged.module.parameters(), restored.module.parameters()):
        assert torch.equal(a, b)


def test_follows_the_parameters_a_torchrl_loss_trains(env):
    """TorchRL losses keep the actor's own parameters (no copy): an optimiser over the loss's moves the actor."""
    actor = make_actor("sac", env)
    critic = ValueOperator(MLP(num_cells=[16], out_features=1), in_keys=["observation", "action"])
    with torch.no_grad():
        data = env.rollout(4, actor).reshape(-1)
        critic(data.clone())
    loss = SACLoss(actor_network=actor, qvalue_network=critic, num_qvalue_nets=2)
    loss.make_value_estimator(gamma=0.99)
    loss_params = list(loss.actor_network_params.values(True, True))
    assert {id(p) for p in loss_params} == {id(p) for p in actor.parameters()}
    theta0 = [p.detach().clone() for p in actor.parameters()]
    averaged = make_averaged_actor(actor, DECAY)
    opt = torch.optim.Adam(loss_params, lr=1e-2)
    loss(data)["loss_actor"].backward()
    opt.step()
    averaged.update_parameters(actor)
    for a, p0, p1 in zip(averaged.module.parameters(), theta0, actor.parameters()):
        assert not torch.equal(p0, p1)
        torch.testing.assert_close(a, DECAY * p0 + (1 - DECAY) * p1.detach(), atol=1e-7, rtol=0)


def test_errors(env):
    lazy = TensorDictModule(MLP(num_cells=[8], out_features=3), in_keys=["observation"], out_keys=["action"])
    with pytest.raises(RuntimeError, match="lazy"):
        make_averaged_actor(lazy, DECAY)
    actor = make_actor("deterministic", env)
    for bad in (0, 1, 1.5, -0.1, float("nan")):
        with pytest.raises(ValueError, match="decay"):
            make_averaged_actor(actor, bad)
    for bad in (True, "0.9"):  # not a number: a TypeError
        with pytest.raises(TypeError, match="decay"):
            make_averaged_actor(actor, bad)
    with pytest.raises(TypeError):
        make_averaged_actor(lambda td: td, DECAY)
