"""UR5eReachGymEnv / ReachGymEnv: Gymnasium API, registration, seeding, and agreement with the TorchRL
env (step for step) and with the task model."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from tensordict import TensorDict

import torchrl_silp  # noqa: F401  (registers the id)
from torchrl_silp import CollisionHandling, CollisionReason, UR5eReach, UR5eReachEnv
from torchrl_silp.envs import ENV_ID, PANDA_ENV_ID, UR5eReachGymEnv
from torchrl_silp.envs.gym import ReachGymEnv


def state_of(obs: np.ndarray) -> TensorDict:
    """The named state behind a flat UR5e observation (joints, TCP, obstacle, goal)."""
    obs = torch.from_numpy(obs)
    return TensorDict(
        joint_position=obs[:3], achieved_goal=obs[3:6], obstacle=obs[6:12], desired_goal=obs[12:15], batch_size=[]
    )


def collision_type_of(torch_env) -> int:
    (handling,) = [t for t in torch_env.transform if isinstance(t, CollisionHandling)]
    return handling.collision_type


def run(env, seed, actions):
    """(reset obs, then (obs, reward, terminated, truncated, info) for each action)."""
    out = [env.reset(seed=seed)[0]]
    for a in actions:
        out.append(env.step(a))
    return out


@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_check_env_via_registered_id(render_mode):
    env = gym.make(ENV_ID, render_mode=render_mode)
    assert isinstance(env.unwrapped, UR5eReachGymEnv)
    assert env.spec.id == ENV_ID
    with warnings.catch_warnings():
        # check_env reports soft failures (infinite bounds, wrong dtypes, ...) as warnings
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    env.close()


def test_registration_is_idempotent():
    import importlib

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when an id is registered twice
        importlib.reload(torchrl_silp)
        importlib.reload(torchrl_silp)
    assert gym.spec(ENV_ID).entry_point == "torchrl_silp.envs.gym:UR5eReachGymEnv"
    assert gym.spec(PANDA_ENV_ID).entry_point == "torchrl_silp.envs.gym:PandaReachGymEnv"


def test_make_passes_kwargs():
    env = gym.make(ENV_ID, max_steps=3, collision_type=0)
    assert env.unwrapped.torch_env.max_steps == 3
    assert collision_type_of(env.unwrapped.torch_env) == 0
    env.reset(seed=0)
    results = [env.step(np.zeros(3, dtype=np.float32)) for _ in range(3)]
    # a zero action keeps a collision-free start: nothing ends before step 3
    assert [r[3] for r in results] == [False, False, True]
    assert not any(r[2] for r in results)


def test_spaces():
    env = UR5eReachGymEnv()
    assert env.observation_space.shape == (15,) and env.observation_space.dtype == np.float32
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
    np.testing.assert_array_equal(env.observation_space.low[:3], env.robot.joint_low.numpy())
    assert np.isfinite(env.observation_space.low).all() and np.isfinite(env.observation_space.high).all()


def test_same_seed_same_trajectory_and_different_seed_different_task():
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.5, 1.5, size=(30, 3)).astype(np.float32)
    a, b = UR5eReachGymEnv(), UR5eReachGymEnv()
    ra, rb = run(a, 7, actions), run(b, 7, actions)
    np.testing.assert_array_equal(ra[0], rb[0])
    for (oa, rwa, ta, tra, ia), (ob, rwb, tb, trb, ib) in zip(ra[1:], rb[1:]):
        np.testing.assert_array_equal(oa, ob)
        assert (rwa, ta, tra) == (rwb, tb, trb)
        assert ia.keys() == ib.keys()
        np.testing.assert_array_equal(ia.pop("goal_q"), ib.pop("goal_q"))
        assert ia == ib
    assert not np.array_equal(a.reset(seed=8)[0], ra[0])
    # a seeded reset then an unseeded one is reproducible too
    first = a.reset(seed=7)[0]
    second = a.reset()[0]
    np.testing.assert_array_equal(first, ra[0])
    np.testing.assert_array_equal(b.reset(seed=7)[0], first)
    np.testing.assert_array_equal(b.reset()[0], second)


def test_seed_gives_the_torch_env_task():
    env = UR5eReachGymEnv()
    for seed in (0, 3):
        obs, info = env.reset(seed=seed)
        td = UR5eReachEnv(seed=seed).reset()
        np.testing.assert_array_equal(obs, td["observation"].numpy())
        np.testing.assert_array_equal(info["goal_q"], td["goal_joint_position"].numpy())


@pytest.mark.parametrize("collision_type", [0, 1, 2])
def test_steps_match_the_torch_env_step_for_step(collision_type):
    # the Gymnasium twin and an unbatched UR5eReachEnv, same seed, same actions: same everything
    gym_env = UR5eReachGymEnv(collision_type=collision_type, max_steps=15)
    torch_env = UR5eReachEnv(seed=11, collision_type=collision_type, max_steps=15)
    rng = np.random.default_rng(2)
    obs, info = gym_env.reset(seed=11)
    td = torch_env.reset()
    seen = {"collision": 0, "reset": 0}
    for _ in range(60):
        np.testing.assert_array_equal(obs, td["observation"].numpy())
        action = rng.uniform(-1.2, 1.2, 3).astype(np.float32)
        obs, reward, terminated, truncated, info = gym_env.step(action)
        td["action"] = torch.from_numpy(np.clip(action, -1, 1))
        out = torch_env.step(td)
        nxt = out["next"]
        np.testing.assert_array_equal(obs, nxt["observation"].numpy())
        assert reward == nxt["reward"].item()
        assert (terminated, truncated) == (nxt["terminated"].item(), nxt["truncated"].item())
        assert info["collision"] == nxt["collision"].item() and info["discard"] == nxt["discard"].item()
        assert info["collision_reason"] == CollisionReason.names(int(nxt["collision_reason"].item()))
        seen["collision"] += info["collision"]
        if terminated or truncated:
            # both reset from the same generator state: the next task is the same too
            obs, info = gym_env.reset()
            td = torch_env.reset()
            seen["reset"] += 1
        else:
            td = nxt.clone()
    assert seen["collision"] > 0 and seen["reset"] > 0

@pytest.mark.parametrize("collision_type", [0, 2])
def test_step_follows_the_torch_model(model, collision_type):
    env = UR5eReachGymEnv(collision_type=collision_type)
    rng = np.random.default_rng(1)
    seen = {"collision": 0, "free": 0}
    for seed in range(4):
        obs, info = env.reset(seed=seed)
        goal_q = info["goal_q"]
        # goal_q is a configuration whose TCP is the goal
        np.testing.assert_allclose(model.robot.fk(torch.from_numpy(goal_q)).numpy(), obs[12:15], atol=1e-6)
        for _ in range(50):
            action = rng.uniform(-1, 1, 3).astype(np.float32)
            state, t_action = state_of(obs), torch.from_numpy(action)
            expected = model.transition(state, t_action)
            reward, collision, success, flags = (x.item() for x in model.outcome(state, expected))
            nxt, r, terminated, truncated, info = env.step(action)
            assert r == reward
            assert info["collision"] == collision and info["success"] == success
            assert info["collision_reason"] == CollisionReason.names(flags)
            assert info["collision_reason"] == [n for b, n in enumerate(model.collision_reasons) if flags >> b & 1]
            if collision and collision_type == 2:
                # type 2: the arm is put back to the state before the collision
                np.testing.assert_array_equal(nxt, obs)
                assert not terminated
            else:
                np.testing.assert_array_equal(nxt, model.observation(expected).numpy())
                assert terminated == (success or (collision and collision_type == 0))
            seen["collision" if collision else "free"] += 1
            obs = nxt
            if terminated or truncated:
                break
    # both branches were exercised
    assert seen["collision"] > 0 and seen["free"] > 0


def test_generic_twin_over_a_model():
    # ReachGymEnv over any task model: the UR5e model gives the UR5e twin's task and steps
    env = ReachGymEnv(UR5eReach(), max_steps=5, collision_type=1)
    ref = UR5eReachGymEnv(max_steps=5, collision_type=1)
    assert env.action_space == ref.action_space and env.observation_space.shape == (15,)
    np.testing.assert_array_equal(env.observation_space.low[:3], ref.observation_space.low[:3])
    assert np.isinf(env.observation_space.low[3:]).all()
    a, info_a = env.reset(seed=4)
    b, info_b = ref.reset(seed=4)
    np.testing.assert_array_equal(a, b)
    assert env.observation_space.contains(a)
    for action in np.random.default_rng(0).uniform(-1, 1, (5, 3)).astype(np.float32):
        out_a, out_b = env.step(action), ref.step(action)
        np.testing.assert_array_equal(out_a[0], out_b[0])
        assert out_a[1:4] == out_b[1:4]
    assert out_a[3]  # truncated after max_steps


def test_out_of_range_actions_are_clipped():
    a, b = UR5eReachGymEnv(), UR5eReachGymEnv()
    a.reset(seed=2)
    b.reset(seed=2)
    for big in ([5.0, -7.0, 0.5], [np.inf, -np.inf, -0.25]):
        clipped = np.clip(big, -1, 1).astype(np.float32)
        out_a, out_b = a.step(np.array(big)), b.step(clipped)
        np.testing.assert_array_equal(out_a[0], out_b[0])
        assert out_a[1] == out_b[1]


def test_bad_actions_raise():
    env = UR5eReachGymEnv()
    with pytest.raises(gym.error.ResetNeeded):
        env.step(np.zeros(3, dtype=np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(np.array([0.0, np.nan, 0.0], dtype=np.float32))
    with pytest.raises(ValueError, match="action"):
        env.step(np.zeros(4, dtype=np.float32))
    with pytest.raises(TypeError, match="action"):
        env.step(["a", "b", "c"])
    # a rejected action leaves the state untouched
    np.testing.assert_array_equal(env.step(np.zeros(3))[0], env.reset(seed=0)[0])


def test_bad_constructor_arguments_raise():
    with pytest.raises(ValueError, match="render_mode"):
        UR5eReachGymEnv(render_mode="human")
    with pytest.raises(ValueError, match="collision_type"):
        UR5eReachGymEnv(collision_type=3)
    with pytest.raises(ValueError, match="max_steps"):
        UR5eReachGymEnv(max_steps=0)
    with pytest.raises(ValueError, match="options"):
        UR5eReachGymEnv().reset(options={"goal": 1})


def test_render_rgb_array():
    env = UR5eReachGymEnv(render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    assert first.dtype == np.uint8 and first.shape == (480, 480, 3)
    assert len(np.unique(first.reshape(-1, 3), axis=0)) > 50  # not a blank canvas
    env.step(np.array([1.0, -1.0, 1.0], dtype=np.float32))
    assert not np.array_equal(env.render(), first)  # the picture follows the state


def test_render_without_mode_returns_none():
    env = UR5eReachGymEnv()
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None
