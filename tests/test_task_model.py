"""The TaskModel interface, for every task model in ``TASKS`` (tests/test_transforms.py).

f_s and f_r against the env's step, the swept motion check against dense exact
sampling (also as a hypothesis property over random-policy rollouts),
relabelling, the flat observation, and argument checking.
"""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torchrl.envs import TransformedEnv

from test_transforms import TASKS, make_env, random_rollout
from torchrl_silp import ReachEnv, TaskModel, UR5eReach


@pytest.fixture(scope="module", params=TASKS)
def model_factory(request):
    return request.param


@pytest.fixture(scope="module")
def rollout(model_factory):
    """A random-policy rollout of the bare env (no collision handling), batch ``[64, 20]``."""
    env = make_env(model_factory, (64,), seed=0, max_steps=20)
    td = random_rollout(env, 20)
    return env.base_env.model, td


def same_next_state(model, got, want):
    """The configuration exactly (f_s is elementwise); the achieved goal to rounding (FK and the
    collision kernel may compute it along different paths); the rest of the state exactly."""
    for key in model.state_keys:
        if key == model.achieved_goal_key:
            torch.testing.assert_close(got[key], want[key])
        else:
            assert torch.equal(got[key], want[key]), key


def dense_collides(model, config_from, config_to, scene, resolution):
    """Exact collision of samples at most ``resolution`` apart along each segment: bool ``(P,)``."""
    span = (config_to - config_from).abs().amax().item()
    n = max(math.ceil(span / resolution), 1) + 1
    t = torch.linspace(0, 1, n, dtype=config_from.dtype).view(n, 1, 1)
    samples = config_from + t * (config_to - config_from)  # (n, P, D)
    hit = model.collides(samples, scene.unsqueeze(0).expand(n, *scene.batch_size))
    return hit.any(0)


# ------------------------------------------------------------ f_s and f_r
def test_transition_and_reward_match_the_env_step(rollout):
    model, rollout_td = rollout
    assert isinstance(model, TaskModel)
    collided = False
    # step by step, with the batch the env stepped (the motion check samples a batch at its longest motion)
    for t in range(rollout_td.shape[1]):
        td = rollout_td[:, t]
        state = td.select(*model.state_keys)
        nxt = model.transition(state, td["action"])
        assert set(nxt.keys()) >= set(model.state_keys)
        same_next_state(model, nxt, td["next"])
        assert torch.equal(model.reward(state, nxt), td["next", "reward"])
        reward, collision, success, flags = model.outcome(state, nxt)
        for key, value in (("reward", reward), ("collision", collision), ("success", success),
                           ("collision_reason", flags)):
            assert torch.equal(value, td["next", key]), key
        # the env itself only reports collisions: the arm moves into the colliding state
        assert (collision == (flags != 0)).all()
        assert torch.equal(td["next", "terminated"], success)
        collided |= bool(collision.any())
    assert collided


def test_transition_of_one_state_matches_a_fresh_env(model_factory):
    # the same state and action handed to an unbatched env built afresh
    env = ReachEnv(model_factory(), seed=3)
    model = env.model
    td = env.reset()
    g = torch.Generator().manual_seed(0)
    for _ in range(10):
        td["action"] = torch.rand(model.action_dim, generator=g) * 2 - 1
        out = env.step(td.clone())["next"]
        want = model.transition(td.select(*model.state_keys), td["action"])
        same_next_state(model, out, want)
        assert torch.equal(out["reward"], model.reward(td, want))
        td = out.clone()


def test_step_is_transition_then_outcome(rollout):
    model, td = rollout
    td = td.reshape(-1)
    state = td.select(*model.state_keys)
    # larger-than-allowed actions are clipped the same way on both paths
    action = torch.rand(td.shape[0], model.action_dim, generator=torch.Generator().manual_seed(1)) * 2.4 - 1.2
    nxt, reward, collision, success, flags = model.step(state, action)
    want = model.transition(state, action)
    same_next_state(model, nxt, want)
    for got, exp in zip((reward, collision, success, flags), model.outcome(state, want)):
        assert torch.equal(got, exp)
    assert torch.equal(model.reward(state, want), reward)
    # the outcome is the paper's reward
    dist = (nxt[model.achieved_goal_key] - nxt[model.desired_goal_key]).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(reward[~collision & ~success], -dist[~collision & ~success])
    assert (reward[collision] == model.collision_reward).all()
    assert (reward[success] == model.success_reward).all()
    assert torch.equal(success, (dist < model.success_distance) & ~collision)
    assert collision.any() and (~collision).any()


def test_zero_action_stays(model_factory):
    model = model_factory()
    tasks = model.sample_tasks(16, torch.Generator().manual_seed(0))
    nxt, _, collision, _, _ = model.step(tasks, torch.zeros(16, model.action_dim))
    assert torch.equal(nxt[model.config_key], tasks[model.config_key])
    # sampled starts keep the motion margin: staying put is free
    assert not collision.any()


# ------------------------------------------------------- the motion check
def _segments(model, n=256, reach=0.6, seed=0):
    g = torch.Generator().manual_seed(seed)
    tasks = model.sample_tasks(n, g)
    q_from = tasks[model.config_key]
    step = (torch.rand(n, model.config_dim, generator=g, dtype=q_from.dtype) * 2 - 1) * reach
    q_to = torch.minimum(torch.maximum(q_from + step, model.config_low), model.config_high)
    return q_from, q_to, tasks.select(*model.scene_keys)


@pytest.mark.parametrize("coarsen", [None, 5], ids=["default", "coarse"])
def test_segment_collision_free_is_sound_at_4x_finer_sampling(model_factory, coarsen):
    model = model_factory()
    # coarse: 5x the model's resolution (0.05 rad for the UR5e), over longer segments (shorter with
    # more joints: the margin grows with the joints' sum of reaches, and both verdicts must occur)
    resolution = None if coarsen is None else coarsen * model.motion_resolution
    h = model.motion_resolution if resolution is None else resolution
    q_from, q_to, scene = _segments(model, reach=0.6 if resolution is None else 1.7 / model.config_dim**0.5)
    free = model.segment_collision_free(q_from, q_to, scene, resolution=resolution)
    assert free.dtype == torch.bool and free.shape == (q_from.shape[0],)
    # both verdicts occur, so the check below is not vacuous
    assert free.any() and (~free).any()
    # every segment sampled at the longest one's count: at least 4x finer than the check
    hit = dense_collides(model, q_from, q_to, scene, h / 4)
    # a segment the model passes has no colliding configuration at 4x finer exact sampling
    assert not (free & hit).any()
    # a segment with an exactly colliding sample is rejected
    assert hit.any() and (~free[hit]).all()
    # the batched motion check agrees segment by segment
    flags, goal = model.motion_collision_flags(q_from[:8], q_to[:8], scene[:8], resolution=resolution)
    for i in range(8):
        alone = model.segment_collision_free(q_from[i : i + 1], q_to[i : i + 1], scene[i : i + 1], resolution)
        one, _ = model.motion_collision_flags(q_from[i], q_to[i], scene[i], resolution)
        assert bool(alone) == bool(one == 0) == bool(free[i])
    torch.testing.assert_close(goal, model.achieved_goal(q_to[:8]))


def test_segment_with_a_colliding_configuration_is_rejected(model_factory):
    model = model_factory()
    q_from, q_to, scene = _segments(model, n=512, reach=1.0, seed=1)
    # put an exactly colliding configuration on segments: as an end, and in the middle
    bad_end = model.collides(q_to, scene)
    assert bad_end.any()
    assert not model.segment_collision_free(q_from[bad_end], q_to[bad_end], scene[bad_end]).any()
    assert not model.segment_collision_free(q_to[bad_end], q_from[bad_end], scene[bad_end]).any()
    # a segment through the colliding configuration, ending beyond it
    beyond = q_to[bad_end] + (q_to[bad_end] - q_from[bad_end])
    assert not model.segment_collision_free(q_from[bad_end], beyond, scene[bad_end]).any()


def test_segment_of_zero_length_is_the_configuration_check(model_factory):
    model = model_factory()
    q_from, _, scene = _segments(model, n=64)
    # sampled starts are free with the motion margin
    assert model.segment_collision_free(q_from, q_from, scene).all()
    assert model.segment_collision_free(q_from[:0], q_from[:0], scene[:0]).shape == (0,)
    flags, _ = model.collision_flags(q_from, scene, model.motion_margin())
    assert (flags == 0).all()


def test_non_conservative_check_is_plain_subdivision(model_factory):
    model = model_factory()
    model.conservative = False
    assert all(m == 0 for m in model.motion_margin().values())
    q_from, q_to, scene = _segments(model, n=64)
    free = model.segment_collision_free(q_from, q_to, scene)
    for i in range(q_from.shape[0]):
        hit = dense_collides(model, q_from[i : i + 1], q_to[i : i + 1], scene[i : i + 1], model.motion_resolution)
        assert bool(free[i]) == (not hit.item())


@pytest.mark.parametrize("factory", TASKS)
@settings(max_examples=4, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1))
def test_property_a_passed_step_never_collides_on_its_segment(factory, seed):
    """For random policies' steps: a step the env lets pass (no collision flag) never has a
    colliding configuration on its segment, sampled at 4x the check's resolution."""
    env = ReachEnv(factory(), batch_size=(32,), seed=seed, max_steps=20)
    model = env.model
    torch.manual_seed(seed)
    td = env.rollout(20, break_when_any_done=False).reshape(-1)
    passed = ~td["next", "collision"].squeeze(-1)
    assert passed.any() and (~passed).any()
    q_from, q_to = td[model.config_key][passed], td["next", model.config_key][passed]
    scene = td.select(*model.scene_keys)[passed]
    hit = dense_collides(model, q_from, q_to, scene, model.motion_resolution / 4)
    assert not hit.any(), f"{int(hit.sum())} passed steps collide between their samples"


# --------------------------------------------------------------- relabelling
def test_relabel_sets_the_goal_and_the_reward_follows(rollout):
    model, td = rollout
    td = td.reshape(-1)
    state, nxt = td.select(*model.state_keys), td["next"].select(*model.state_keys)
    # relabel with the goal achieved at the end of the step (HER's "final"/"future" goals)
    goal = nxt[model.achieved_goal_key]
    s2, n2 = model.relabel(state, goal), model.relabel(nxt, goal)
    assert torch.equal(s2[model.desired_goal_key], goal) and torch.equal(n2[model.desired_goal_key], goal)
    for key in (model.config_key, model.achieved_goal_key, *model.scene_keys):
        assert torch.equal(s2[key], state[key])
    # a shallow copy: the original keeps its goal
    assert torch.equal(state[model.desired_goal_key], td[model.desired_goal_key])
    reward, collision, success, _ = model.outcome(s2, n2)
    assert torch.equal(collision, model.outcome(state, nxt)[1])  # the goal does not change the motion
    assert collision.any()
    assert (success == ~collision).all()
    assert (reward[~collision] == model.success_reward).all() and (reward[collision] == model.collision_reward).all()
    # any goal: the reward is recomputed from it
    other = torch.randn(model.goal_dim, generator=torch.Generator().manual_seed(0))
    reward = model.reward(model.relabel(state, other), model.relabel(nxt, other))
    want = torch.where(collision, torch.full_like(reward, model.collision_reward),
                       model.goal_reward(nxt[model.achieved_goal_key], other.expand_as(goal)))
    torch.testing.assert_close(reward, want)


# --------------------------------------------------------------- observation
def test_observation_is_the_cat_tensors_output(model_factory):
    model = model_factory()
    env = TransformedEnv(ReachEnv(model, batch_size=(8,), seed=0), model.observation_transform())
    td = random_rollout(env, 6)
    assert torch.equal(td["observation"], model.observation(td))
    assert torch.equal(td["next", "observation"], model.observation(td["next"]))
    size = sum(td[k].shape[-1] for k in model.observation_keys)
    assert td["observation"].shape == (8, 6, size)
    assert env.observation_spec["observation"].shape == (8, size)
    # the named keys stay (components read them)
    assert set(model.state_keys) <= set(td.keys())
    # state_at builds a state whose observation is the same
    state = model.state_at(td[model.config_key], td.select(*model.scene_keys), td[model.desired_goal_key])
    torch.testing.assert_close(model.observation(state), td["observation"])


# ---------------------------------------------------------------- bad input
def test_bad_input_names_the_parameter(model_factory):
    model = model_factory()
    tasks = model.sample_tasks(4, torch.Generator().manual_seed(0))
    a = model.action_dim
    with pytest.raises(ValueError, match="action"):
        model.transition(tasks, torch.zeros(4, a + 1))
    with pytest.raises(TypeError, match="action"):
        model.transition(tasks, [[0.0] * a] * 4)
    with pytest.raises(TypeError, match="action"):
        model.step(tasks, torch.zeros(4, a, dtype=torch.long))
    with pytest.raises(TypeError, match="state"):
        model.transition(tasks[model.config_key], torch.zeros(4, a))
    with pytest.raises(KeyError, match=model.desired_goal_key):
        model.step(tasks.exclude(model.desired_goal_key), torch.zeros(4, a))
    with pytest.raises(TypeError, match="next_state"):
        model.outcome(tasks, {"x": 1})
    with pytest.raises(ValueError, match="goal"):
        model.relabel(tasks, torch.zeros(model.goal_dim + 1))
    with pytest.raises(ValueError, match="config"):
        model.collides(torch.zeros(4, model.config_dim + 1), tasks.select(*model.scene_keys))
    with pytest.raises(ValueError, match="resolution"):
        model.segment_collision_free(tasks[model.config_key], tasks[model.config_key], tasks, resolution=0.0)
    with pytest.raises(TypeError, match="model"):
        ReachEnv(object())
    with pytest.raises(ValueError, match="motion_resolution"):
        type(model)(motion_resolution=-1.0)
    with pytest.raises(ValueError, match="success_distance"):
        type(model)(success_distance=0)


def test_a_margin_no_configuration_keeps_is_refused_not_looped_on():
    model = UR5eReach(motion_resolution=0.5)
    with pytest.raises(ValueError, match="motion_resolution"):
        model.sample_tasks(4, torch.Generator().manual_seed(0))
