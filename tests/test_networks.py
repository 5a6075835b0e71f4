"""NextGoalOffsetQ: its in_keys, the next-goal offset against the FK by hand, gradients by finite differences, TorchRL losses."""

import copy

import pytest
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, TanhModule, TanhNormal, ValueOperator
from torchrl.objectives import DDPGLoss, SACLoss, TD3Loss

from torchrl_silp import ReachEnv, UR5eReach, UR5eReachEnv
from torchrl_silp.modules.networks import NextGoalOffsetQ
from torchrl_silp.transforms import GoalRelative

STATE_KEYS = ["joint_position", "achieved_goal", "obstacle", "desired_goal"]


class Record(nn.Module):
    """An 'MLP' that keeps its inputs and returns a number computed from the offset only."""

    def __init__(self, weight=None):
        super().__init__()
        self.weight = weight
        self.inputs = None

    def forward(self, *inputs):
        self.inputs = inputs
        offset = inputs[-1]
        w = torch.ones_like(offset) if self.weight is None else self.weight.to(offset)
        return (offset * w).sum(-1, keepdim=True)


def next_goal_by_hand(robot, q, action, scale=0.125):
    """TCP of ``clip(q + scale * clip(a, -1, 1), joint limits)`` with the robot's own FK."""
    step = action.clamp(-1.0, 1.0) * scale
    q_next = torch.minimum(torch.maximum(q + step, robot.joint_low), robot.joint_high)
    return robot.fk(q_next)


def inputs_of(q_net, td):
    return [td[k] for k in q_net.in_keys]


# ----------------------------------------------------------------- in_keys
def test_in_keys(model):
    assert NextGoalOffsetQ.in_keys_for(model) == ["observation", "action", *STATE_KEYS]
    assert NextGoalOffsetQ.in_keys_for(model, "observation") == ["observation", "action", *STATE_KEYS]
    # a state key that is an observation key is listed once, as an observation
    keys = NextGoalOffsetQ.in_keys_for(model, ["obstacle", "goal_offset"], action_key="act")
    assert keys == ["obstacle", "goal_offset", "act", "joint_position", "achieved_goal", "desired_goal"]
    q_net = NextGoalOffsetQ(Record(), model, ["observation", "goal_offset"])
    assert q_net.in_keys == ["observation", "goal_offset", "action", *STATE_KEYS]
    assert q_net.num_mlp_inputs == 3
    with pytest.raises(ValueError, match="distinct"):
        NextGoalOffsetQ.in_keys_for(model, ["action"])
    with pytest.raises(TypeError, match="TaskModel"):
        NextGoalOffsetQ(Record(), object())
    with pytest.raises(TypeError, match="takes 6 tensors"):
        NextGoalOffsetQ(Record(), model)(torch.zeros(2, 15), torch.zeros(2, 3))


def test_model_is_shared_not_a_submodule(model):
    q_net = NextGoalOffsetQ(nn.Linear(21, 1), model)
    assert set(dict(q_net.named_parameters())) == {"mlp.weight", "mlp.bias"}
    assert set(q_net.state_dict()) == {"mlp.weight", "mlp.bias"}
    twin = copy.deepcopy(q_net)
    assert twin.model is model
    assert twin.mlp is not q_net.mlp and torch.equal(twin.mlp.weight, q_net.mlp.weight)
    assert twin.in_keys == q_net.in_keys


# ------------------------------------------------------------------ values
@pytest.mark.parametrize("batch", [(), (7,), (2, 5)])
def test_next_goal_offset_against_fk_by_hand(model, batch):
    gen = torch.Generator().manual_seed(0)
    n = max(1, int(torch.Size(batch).numel()))
    td = model.sample_tasks(n, gen).reshape(batch)
    # actions beyond [-1, 1] (clipped), and configurations at a joint limit pushed further (clipped)
    td["action"] = 3.0 * torch.rand(*batch, 3, generator=gen) - 1.5
    if n > 1:
        flat = td.view(-1)
        flat["joint_position"][0] = model.robot.joint_high - 0.01
        flat["action"][0] = torch.tensor([1.0, 0.5, 1.0])
        q_next = td["joint_position"] + 0.125 * td["action"].clamp(-1, 1)
        assert (q_next > model.robot.joint_high).any()  # the joint-limit clip is exercised
    # the observation the MLP reads is passed through untouched; the offset comes from the named keys
    td["observation"] = torch.randn(*batch, 15, generator=gen)
    record = Record()
    q_net = NextGoalOffsetQ(record, model)
    value = q_net(*inputs_of(q_net, td))
    expected = td["desired_goal"] - next_goal_by_hand(model.robot, td["joint_position"], td["action"])
    obs, action, offset = record.inputs
    assert obs is td["observation"] and action is td["action"]
    torch.testing.assert_close(offset, expected, atol=1e-6, rtol=0)
    torch.testing.assert_close(value, expected.sum(-1, keepdim=True), atol=1e-5, rtol=0)
    assert value.shape == (*batch, 1)


def test_several_observation_keys_through_value_operator(model):
    gen = torch.Generator().manual_seed(1)
    td = model.sample_tasks(6, gen)
    td["goal_offset"] = td["desired_goal"] - td["achieved_goal"]
    td["observation"] = model.observation(td)
    td["action"] = 2 * torch.rand(6, 3, generator=gen) - 1
    mlp = MLP(in_features=15 + 3 + 3 + 3, num_cells=[8], out_features=1)
    q_net = NextGoalOffsetQ(mlp, model, ["observation", "goal_offset"])
    critic = ValueOperator(q_net, in_keys=q_net.in_keys)
    out = critic(td.clone())["state_action_value"]
    offset = td["desired_goal"] - next_goal_by_hand(model.robot, td["joint_position"], td["action"])
    expected = mlp(torch.cat([td["observation"], td["goal_offset"], td["action"], offset], -1))
    torch.testing.assert_close(out, expected, atol=1e-6, rtol=0)


# --------------------------------------------------------------- gradients
def fk_jacobian_fd(robot, q, eps=1e-6):
    """d fk / d q ``(..., 3 xyz, 3 joints)`` by central differences (float64)."""
    cols = []
    for j in range(3):
        e = torch.zeros(3, dtype=q.dtype)
        e[j] = eps
        cols.append((robot.fk(q + e) - robot.fk(q - e)) / (2 * eps))
    return torch.stack(cols, -1)


def test_action_gradient_through_the_fk_against_finite_differences(model64):
    gen = torch.Generator().manual_seed(2)
    td = model64.sample_tasks(5, gen)
    td["observation"] = model64.observation(td)
    action = (1.6 * torch.rand(5, 3, generator=gen, dtype=torch.float64) - 0.8).requires_grad_()
    td["action"] = action
    w = torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64)
    q_net = NextGoalOffsetQ(Record(w), model64)  # Q = w . offset: all of dQ/da goes through the model
    value = q_net(*inputs_of(q_net, td))
    (grad,) = torch.autograd.grad(value.sum(), action)
    q_next = td["joint_position"] + 0.125 * action.detach()
    assert ((q_next > model64.robot.joint_low + 1e-3) & (q_next < model64.robot.joint_high - 1e-3)).all()
    J = fk_jacobian_fd(model64.robot, q_next)  # offset = goal - fk(q + 0.125 a)
    expected = -0.125 * torch.einsum("bij,i->bj", J, w)
    torch.testing.assert_close(grad, expected, atol=1e-7, rtol=1e-6)
    assert grad.abs().min() > 1e-4


def test_gradcheck_full_critic_float64(model64):
    gen = torch.Generator().manual_seed(3)
    td = model64.sample_tasks(3, gen)
    td["observation"] = model64.observation(td)
    torch.manual_seed(0)
    mlp = MLP(in_features=21, num_cells=[16], out_features=1, activation_class=nn.Tanh).double()
    q_net = NextGoalOffsetQ(mlp, model64)
    action = (1.6 * torch.rand(3, 3, generator=gen, dtype=torch.float64) - 0.8).requires_grad_()

    def q_of(a):
        td["action"] = a
        return q_net(*inputs_of(q_net, td))

    assert torch.autograd.gradcheck(q_of, (action,), eps=1e-6, atol=1e-7)


def test_clipped_action_components_get_no_gradient(model64):
    td = model64.sample_tasks(2, torch.Generator().manual_seed(4))
    td["observation"] = model64.observation(td)
    action = torch.tensor([[1.5, 0.2, -0.3], [0.1, -2.0, 0.4]], dtype=torch.float64, requires_grad=True)
    td["action"] = action
    q_net = NextGoalOffsetQ(Record(), model64)
    (grad,) = torch.autograd.grad(q_net(*inputs_of(q_net, td)).sum(), action)
    assert grad[0, 0] == 0 and grad[1, 1] == 0
    assert (grad[0, 1:] != 0).all() and grad[1, 0] != 0 and grad[1, 2] != 0


# ------------------------------------------------------- in TorchRL losses
def _env_and_actor(kind, model=None):
    if model is None:
        env = TransformedEnv(UR5eReachEnv(num_envs=4, seed=0), GoalRelative())
    else:
        env = TransformedEnv(ReachEnv(model, num_envs=4, seed=0), Compose(model.observation_transform(), GoalRelative()))
    spec = env.action_spec_unbatched
    keys = ["observation", "goal_offset"]
    if kind == "sac":
        actor = ProbabilisticActor(
            TensorDictSequential(
                TensorDictModule(MLP(num_cells=[16], out_features=6), in_keys=keys, out_keys=["param"]),
                TensorDictModule(NormalParamExtractor(), in_keys=["param"], out_keys=["loc", "scale"]),
            ),
            in_keys=["loc", "scale"],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
            return_log_prob=False,
        )
    else:
        actor = TensorDictSequential(
            TensorDictModule(MLP(num_cells=[16], out_features=3), in_keys=keys, out_keys=["param"]),
            TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
        )
    return env, actor


def _loss(kind, actor, critic, env):
    if kind == "sac":
        loss = SACLoss(actor_network=actor, qvalue_network=critic, num_qvalue_nets=2, loss_function="l2")
    elif kind == "ddpg":
        loss = DDPGLoss(actor_network=actor, value_network=critic, delay_actor=True, delay_value=True)
    else:
        loss = TD3Loss(actor_network=actor, qvalue_network=critic, action_spec=env.action_spec_unbatched)
    loss.make_value_estimator(gamma=0.99)
    return loss


@pytest.mark.parametrize("kind", ["sac", "ddpg", "td3"])
def test_losses_differentiate_through_the_model(kind):
    """SAC and TD3 run their Q-networks under vmap over stacked parameters: the model must work there.

    TorchRL's TD3Loss (0.14) gives its critic only the actor's in_keys (and the action), not the
    critic's own further inputs (DDPGLoss and SACLoss do): the state keys must be among the
    actor's in_keys for TD3.
    """
    torch.manual_seed(0)
    env, actor = _env_and_actor("sac" if kind == "sac" else "det")
    model = env.base_env.model
    q_net = NextGoalOffsetQ(MLP(num_cells=[16], out_features=1), model, ["observation", "goal_offset"])
    critic = ValueOperator(q_net, in_keys=q_net.in_keys)
    with torch.no_grad():
        data = env.rollout(6, actor).reshape(-1)
    critic(data.clone())
    if kind == "td3":
        with pytest.raises(KeyError, match="lacks the inputs"):
            _loss(kind, actor, critic, env)(data)
        actor.in_keys = [*actor.in_keys, *(k for k in model.state_keys if k not in actor.in_keys)]
    loss = _loss(kind, actor, critic, env)
    out = loss(data)
    actor_loss = out["loss_actor"]
    assert torch.isfinite(actor_loss) and torch.isfinite(out["loss_qvalue" if kind != "ddpg" else "loss_value"])
    actor_loss.backward()
    grads = [p.grad for p in loss.actor_network_params.values(True, True) if p.requires_grad]
    assert grads and all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


# ---------------------------------------------------------------- clearance
def test_next_clearance_is_negative_exactly_where_the_next_configuration_collides(model):
    """The clearance input against the collision flags (the model's fused kernel, a separate implementation)."""
    gen = torch.Generator().manual_seed(3)
    td = model.sample_tasks(4096, gen)
    low, high = model.robot.joint_low, model.robot.joint_high
    td["joint_position"] = low + (high - low) * torch.rand(4096, 3, generator=gen)
    td["achieved_goal"] = model.robot.fk(td["joint_position"])
    td["action"] = 2 * torch.rand(4096, 3, generator=gen) - 1
    td["observation"] = torch.zeros(4096, 15)
    record = Record()
    q_net = NextGoalOffsetQ(record, model, clearance=True, clearance_clip=0.1)
    q_net(*inputs_of(q_net, td))
    _, _, offset, clearance = record.inputs
    assert clearance.shape == (4096, len(model.collision_reasons)) and clearance.abs().max() <= 0.1
    next_q = model.next_config(td["joint_position"], td["action"])
    flags = model.collision_flags(next_q, td.select("obstacle"))[0].squeeze(-1)
    for bit, reason in enumerate(model.collision_reasons):
        hit = (flags >> bit) & 1 == 1
        if reason in ("obstacle", "table", "self"):
            assert 0 < int(hit.sum()) < 4096, reason  # both sides of the test are exercised
        assert torch.equal(clearance[:, bit] < 0, hit), reason
    # the offset input is unchanged by the extra one
    plain = Record()
    q_plain = NextGoalOffsetQ(plain, model)
    q_plain(*inputs_of(q_plain, td))
    assert torch.equal(plain.inputs[-1], offset) and len(plain.inputs) == len(record.inputs) - 1


@pytest.mark.parametrize(("num_boxes", "compiled"), [(1, False), (3, False), (3, True)])
def test_next_clearance_gradient_reaches_the_actor_through_sac(num_boxes, compiled):
    """Inside SACLoss's vmap, eager and compiled: the one-box model's own clearance and the several-box one
    (ArmReach's), whose clearance must make no host-synced check nor change shape with the values. Compiled is
    traced whole (``fullgraph``) with its backward (``aot_eager``): what such a check or shape would break;
    inductor's code generation adds nothing to that, and its numerics are tests/test_recipe_builders.py's."""
    torch.manual_seed(0)
    env, actor = _env_and_actor("sac", UR5eReach(num_boxes=num_boxes))
    model = env.base_env.model
    q_net = NextGoalOffsetQ(MLP(num_cells=[16], out_features=1), model, ["observation", "goal_offset"], clearance=True)
    critic = ValueOperator(q_net, in_keys=q_net.in_keys)
    with torch.no_grad():
        data = env.rollout(6, actor).reshape(-1)
    critic(data.clone())  # the lazy MLP takes its input width
    loss = _loss("sac", actor, critic, env)
    forward = torch.compile(loss, fullgraph=True, backend="aot_eager") if compiled else loss
    out = forward(data)
    out["loss_actor"].backward()
    grads = [p.grad for p in loss.actor_network_params.values(True, True) if p.requires_grad]
    assert grads and all(g is not None and torch.isfinite(g).all() for g in grads)
    if compiled:
        return
    # the action's gradient through the clearance alone: an MLP reading only that input
    only = NextGoalOffsetQ(Record(), model, clearance=True)  # Record sums its last input: the clearance
    td = data[:64].clone()
    td["action"] = td["action"].detach().requires_grad_(True)
    only(*inputs_of(only, td)).sum().backward()
    assert torch.isfinite(td["action"].grad).all()
    assert td["action"].grad.abs().sum() > 0
