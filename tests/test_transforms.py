"""The SILP+ transforms (CollisionHandling, GoalRelative, PerceptionNoise) on the reach envs.

Parametrised over :data:`TASKS` (task-model factories) so that further robot
tasks join by adding a line there; ``tests/test_task_model.py`` uses the same list.
"""

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_silp import CollisionHandling, GoalRelative, PandaReach, PerceptionNoise, ReachEnv, UR5eReach, UR5eReachEnv

#: task-model factories; add a robot task here and every model/transform test covers it
TASKS = [pytest.param(lambda: UR5eReach(), id="ur5e"), pytest.param(lambda: PandaReach(num_boxes=2), id="panda")]

#: transform factories, given the env's model (PerceptionNoise's default std names UR5e keys)
TRANSFORMS = [
    pytest.param(lambda model: CollisionHandling(0), id="collision0"),
    pytest.param(lambda model: CollisionHandling(1), id="collision1"),
    pytest.param(lambda model: CollisionHandling(2), id="collision2"),
    pytest.param(lambda model: GoalRelative(), id="goal_relative"),
    pytest.param(
        lambda model: PerceptionNoise() if isinstance(model, UR5eReach) else PerceptionNoise(_noise_std(model)),
        id="perception_noise",
    ),
]
BATCH_SIZES = [pytest.param((), id="bs()"), pytest.param((1,), id="bs1"), pytest.param((64,), id="bs64")]


def make_env(model_factory, bs, *transforms, seed: int = 0, max_steps: int = 50) -> TransformedEnv:
    """A seeded :class:`ReachEnv` over ``model_factory()`` with batch ``bs``, the transforms on top in order."""
    env = TransformedEnv(ReachEnv(model_factory(), batch_size=bs, seed=seed, max_steps=max_steps))
    for t in transforms:
        env.append_transform(t)
    return env


def random_rollout(env, steps: int, seed: int = 0):
    """``steps`` steps of uniform random actions, envs reset when done (actions from torch's global generator)."""
    torch.manual_seed(seed)
    return env.rollout(steps, break_when_any_done=False)


# ------------------------------------------------------------------ specs
@pytest.mark.parametrize("bs", BATCH_SIZES)
@pytest.mark.parametrize("transform", TRANSFORMS)
def test_check_env_specs_on_ur5e_reach_env(transform, bs):
    base = UR5eReachEnv(batch_size=bs, seed=0)
    env = TransformedEnv(base, transform(base.model))
    check_env_specs(env, seed=0)


@pytest.mark.parametrize("bs", BATCH_SIZES)
@pytest.mark.parametrize("transform", TRANSFORMS)
@pytest.mark.parametrize("model_factory", TASKS)
def test_check_env_specs_on_reach_env(model_factory, transform, bs):
    model = model_factory()
    env = TransformedEnv(ReachEnv(model, batch_size=bs), transform(model))
    check_env_specs(env, seed=0)


# -------------------------------------------------------- collision handling
def _collisions(td):
    hit = td["next", "collision"].squeeze(-1)
    assert hit.any(), "the rollout must hold collisions to check their handling"
    return hit


@pytest.mark.parametrize("model_factory", TASKS)
def test_collision_type_0_terminates(model_factory):
    env = make_env(model_factory, (64,), CollisionHandling(0))
    model = env.base_env.model
    td = random_rollout(env, 20)
    hit = _collisions(td)
    nxt = td["next"]
    assert nxt["terminated"][hit].all() and nxt["done"][hit].all() and not nxt["truncated"][hit].any()
    # nothing else ends an episode than success, a collision or the step limit
    ended = nxt["success"] | nxt["collision"] | (nxt["step_count"] >= env.base_env.max_steps)
    assert torch.equal(nxt["done"], ended)
    # the next state is the colliding one: the configuration moved
    want = model.transition(td.select(*model.state_keys), td["action"])
    assert torch.equal(nxt[model.config_key], want[model.config_key])
    torch.testing.assert_close(nxt[model.achieved_goal_key], want[model.achieved_goal_key])
    assert not nxt["discard"].any()


@pytest.mark.parametrize("collision_type", [1, 2])
@pytest.mark.parametrize("model_factory", TASKS)
def test_collision_types_1_2_put_the_arm_back(model_factory, collision_type):
    env = make_env(model_factory, (64,), CollisionHandling(collision_type))
    model = env.base_env.model
    td = random_rollout(env, 20)
    hit = _collisions(td)
    nxt = td["next"]
    for key in (model.config_key, model.achieved_goal_key):
        # put back where it was...
        assert torch.equal(nxt[key][hit], td[key][hit])
        # ... while free steps move on as the model says (the achieved goal to rounding: FK
        # and the collision kernel may compute it along different paths)
        want = model.transition(td.select(*model.state_keys), td["action"])[key]
        if key == model.config_key:
            assert torch.equal(nxt[key][~hit], want[~hit])
        else:
            torch.testing.assert_close(nxt[key][~hit], want[~hit])
    assert not nxt["terminated"][hit].any()
    assert torch.equal(nxt["terminated"], nxt["success"])
    # the next step starts from there (rows that do not end the episode)
    going_on = ~nxt["done"][:, :-1].squeeze(-1)
    for key in (model.config_key, model.achieved_goal_key, *model.scene_keys, model.desired_goal_key):
        assert torch.equal(td[key][:, 1:][going_on], nxt[key][:, :-1][going_on])
    # after a put-back, the next step starts from the pre-collision state
    again = hit[:, :-1] & going_on
    assert again.any()
    assert torch.equal(td[model.config_key][:, 1:][again], td[model.config_key][:, :-1][again])
    # type 1 flags the colliding transitions for the replay buffer to drop, type 2 keeps them
    if collision_type == 1:
        assert torch.equal(nxt["discard"].squeeze(-1), hit)
    else:
        assert not nxt["discard"].any()
    assert not td["discard"][:, 0].any()  # a reset never discards


def test_collision_handling_rejects_bad_types():
    for bad in (3, -1, True, None, "2"):
        with pytest.raises(ValueError, match="collision_type"):
            CollisionHandling(bad)


def test_transform_without_model_says_so():
    # no model given and no parent env holding one
    for t in (CollisionHandling(2), GoalRelative(), PerceptionNoise()):
        with pytest.raises(RuntimeError, match="model"):
            t.model
    model = UR5eReach()
    assert GoalRelative(model=model).model is model


# ------------------------------------------------------------ goal relative
@pytest.mark.parametrize("model_factory", TASKS)
def test_goal_relative_is_desired_minus_achieved(model_factory):
    env = make_env(model_factory, (16,), CollisionHandling(2), GoalRelative())
    model = env.base_env.model
    td = random_rollout(env, 12)
    for sub in (td, td["next"]):
        assert torch.equal(sub["goal_offset"], sub[model.desired_goal_key] - sub[model.achieved_goal_key])
    reset = env.reset()
    assert torch.equal(reset["goal_offset"], reset[model.desired_goal_key] - reset[model.achieved_goal_key])
    # another key
    env2 = make_env(model_factory, (4,), GoalRelative(out_key="offset"))
    assert "offset" in env2.reset().keys() and "offset" in env2.observation_spec.keys()


# ---------------------------------------------------------- perception noise
def _noise_std(model):
    # the configuration and the first scene entry get noise, the goals none
    std = {model.config_key: 0.02}
    if model.scene_keys:
        std[model.scene_keys[0]] = 0.05
    return std


@pytest.mark.parametrize("model_factory", TASKS)
def test_perception_noise_changes_only_the_observation(model_factory):
    steps, bs = 20, (64,)
    clean = make_env(model_factory, bs, CollisionHandling(2), model_factory().observation_transform())
    model = clean.base_env.model
    std = _noise_std(model)
    noisy = make_env(
        model_factory, bs, CollisionHandling(2), PerceptionNoise(std, generator=torch.Generator().manual_seed(1))
    )
    # the noise has its own generator: the same seed gives the same actions, hence the same states
    a, b = random_rollout(clean, steps), random_rollout(noisy, steps)
    keys = [*model.state_keys, model.goal_config_key, "action", "collision", "done"]
    for key in keys:
        assert torch.equal(a[key], b[key]), key
        if key != "action":
            assert torch.equal(a["next", key], b["next", key]), key
    assert torch.equal(a["next", "reward"], b["next", "reward"])

    # the observation is the clean one plus noise on the keys of std, the other parts exact
    noise = torch.cat([b["observation"], b["next", "observation"]])
    noise = noise - torch.cat([a["observation"], a["next", "observation"]])
    start = 0
    for key in model.observation_keys:
        size = a[key].shape[-1]
        part = noise[..., start : start + size]
        start += size
        if key in std:
            # 2 * 20 * 64 * size samples: the empirical std is within a few percent of the requested one
            assert part.std().item() == pytest.approx(std[key], rel=0.08), key
            assert part.mean().abs().item() < 0.1 * std[key], key
        else:
            assert not part.any(), key
    assert start == a["observation"].shape[-1]


@pytest.mark.parametrize("model_factory", TASKS)
def test_perception_noise_without_cat_tensors_builds_the_observation(model_factory):
    env = make_env(model_factory, (8,), PerceptionNoise({}, generator=torch.Generator().manual_seed(0)))
    model = env.base_env.model
    td = random_rollout(env, 5)
    # std 0 everywhere: the observation is exactly the model's flat observation
    assert torch.equal(td["observation"], model.observation(td))
    assert torch.equal(td["next", "observation"], model.observation(td["next"]))


def test_perception_noise_bad_arguments():
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="std"):
            PerceptionNoise({"joint_position": bad})
    for bad in (True, "0.1"):
        with pytest.raises(TypeError, match="std"):
            PerceptionNoise({"joint_position": bad})
    env = TransformedEnv(ReachEnv(UR5eReach(), num_envs=2, seed=0), PerceptionNoise({"velocity": 0.1}))
    with pytest.raises(ValueError, match="velocity"):
        env.reset()
