"""UR5eReachEnv: specs, task sampling, reward / termination / truncation, seeding, collision types."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_silp import CollisionReason, UR5eReachEnv
from torchrl_silp.geometry import in_box


@pytest.mark.parametrize("batch_size", [(), (1,), (64,), (2, 3)])
def test_check_env_specs(batch_size):
    env = UR5eReachEnv(batch_size=batch_size, seed=0)
    check_env_specs(env)


def test_num_envs_alias():
    assert UR5eReachEnv(num_envs=5).batch_size == (5,)
    assert UR5eReachEnv().batch_size == ()


def test_sampled_tasks_satisfy_paper_constraints():
    env = UR5eReachEnv(seed=0)
    t = env.sample_tasks(2000)
    centre = (t["obstacle"][:, 0::2] + t["obstacle"][:, 1::2]) / 2
    size = t["obstacle"][:, 1::2] - t["obstacle"][:, 0::2]
    d1 = (t["tcp"] - centre).norm(dim=-1)
    d2 = (t["tcp"] - t["goal"]).norm(dim=-1)
    d3 = (centre - t["goal"]).norm(dim=-1)
    assert (d2 > d1).all() and (d1 > d3).all()
    low, high = torch.tensor(env.WORKSPACE_LOW), torch.tensor(env.WORKSPACE_HIGH)
    for p in (t["tcp"], t["goal"]):
        assert ((p >= low) & (p <= high)).all()
    torch.testing.assert_close(size, torch.tensor(env.OBSTACLE_SIZE).expand_as(size))
    assert (centre[:, 0] >= 0.3).all() and (centre[:, 0] <= 0.7).all()
    assert (centre[:, 1] >= 0.1).all() and (centre[:, 1] <= 0.4).all()
    torch.testing.assert_close(centre[:, 2], torch.full((2000,), 0.15))
    # start and goal are collision-free configurations and the goal is their TCP
    assert not env.collides(t["q"], t["obstacle"]).any()
    assert not env.collides(t["goal_q"], t["obstacle"]).any()
    torch.testing.assert_close(env.robot.fk(t["goal_q"]), t["goal"])
    torch.testing.assert_close(env.robot.fk(t["q"]), t["tcp"])
    # the obstacle region is covered, not a corner of it
    assert centre[:, 0].max() - centre[:, 0].min() > 0.3


@pytest.mark.parametrize("task_branch", ["front", "any"])
def test_task_branch(task_branch):
    env = UR5eReachEnv(seed=0, task_branch=task_branch)
    t = env.sample_tasks(3000)
    flipped = []
    for q, tcp in ((t["q"], t["tcp"]), (t["goal_q"], t["goal"])):
        # the TCP in the frame rotated by the pan angle: x < 0 is behind the shoulder
        c, s = torch.cos(-q[:, 0]), torch.sin(-q[:, 0])
        flipped.append(c * tcp[:, 0] - s * tcp[:, 1] < 0)
    start_flipped, goal_flipped = flipped
    if task_branch == "front":
        assert not start_flipped.any() and not goal_flipped.any()
    else:
        # the flipped branch is a sizeable part of the task joint box
        assert 0.1 < start_flipped.float().mean() < 0.3
    # the shoulder-flipped pose (pan ~ pi, lift past vertical) is behind, the home-like one in front
    q = torch.tensor([[2.8, -3.0, 0.9], [0.3, -1.0, 0.9]])
    reach = UR5eReachEnv.reach_along_pan(q, env.robot.fk(q))
    assert reach[0] < 0 < reach[1]
    with pytest.raises(ValueError, match="task_branch"):
        UR5eReachEnv(task_branch="back")


def test_reset_observation_layout():
    env = UR5eReachEnv(num_envs=8, seed=1)
    td = env.reset()
    obs = td["observation"]
    torch.testing.assert_close(obs[:, 3:6], env.robot.fk(obs[:, :3]))
    torch.testing.assert_close(obs[:, 12:15], env.robot.fk(td["goal_q"]))
    assert obs.dtype == torch.float32 and obs.shape == (8, 15)


def step_with(env, action):
    td = env.reset() if not hasattr(env, "_last") else env._last
    td["action"] = action
    return env.step(td)


def _env_at(q, goal_q, obstacle, **kwargs):
    """An env whose single task is set by hand (the state lives inside the env)."""
    env = UR5eReachEnv(batch_size=(q.shape[0],), seed=0, **kwargs)
    td = env.reset()
    env._q.copy_(q)
    env._tcp.copy_(env.robot.fk(q))
    env._goal_q.copy_(goal_q)
    env._goal.copy_(env.robot.fk(goal_q))
    env._obstacle.copy_(obstacle)
    td["observation"] = env._observation()
    return env, td


FAR_BOX = torch.tensor([[5.0, 5.2, 5.0, 5.2, 5.0, 5.3]])
HOME = torch.tensor([[0.0, -math.pi / 2, math.pi / 2]])


def test_reward_success_terminates():
    goal_q = HOME + torch.tensor([[0.1, 0.0, 0.0]])
    env, td = _env_at(HOME, goal_q, FAR_BOX)
    td["action"] = torch.tensor([[0.8, 0.0, 0.0]])  # 0.1 rad: lands exactly on the goal
    out = env.step(td)["next"]
    assert out["reward"].item() == env.SUCCESS_REWARD
    assert out["success"].item() and out["terminated"].item() and out["done"].item()
    assert not out["truncated"].item() and not out["collision"].item()


def test_reward_is_minus_distance_otherwise():
    goal_q = HOME + torch.tensor([[0.5, 0.2, -0.2]])
    env, td = _env_at(HOME, goal_q, FAR_BOX)
    td["action"] = torch.tensor([[0.3, -0.2, 0.1]])
    out = env.step(td)["next"]
    tcp = env.robot.fk(HOME + 0.125 * td["action"])
    expected = -(tcp - env.robot.fk(goal_q)).norm()
    assert out["reward"].item() == pytest.approx(expected.item(), abs=1e-6)
    assert not out["done"].item()
    # the pure model functions agree with the step
    nxt = env.transition(td["observation"], td["action"])
    torch.testing.assert_close(nxt, out["observation"])
    torch.testing.assert_close(env.reward(td["observation"], nxt), out["reward"])


def test_truncation_at_max_steps():
    env, td = _env_at(HOME, HOME + 0.5, FAR_BOX, max_steps=7)
    for i in range(7):
        td["action"] = torch.zeros(1, 3)
        td = env.step(td)
        nxt = td["next"]
        assert nxt["truncated"].item() == (i == 6)
        assert not nxt["terminated"].item()
        td = nxt.clone()
    assert nxt["done"].item()


def test_actions_are_clipped():
    env, td = _env_at(HOME, HOME + 0.5, FAR_BOX)
    td["action"] = torch.tensor([[5.0, -3.0, 0.5]])
    out = env.step(td)["next"]
    torch.testing.assert_close(out["observation"][:, :3], HOME + 0.125 * torch.tensor([[1.0, -1.0, 0.5]]))


def _colliding_setup(collision_type):
    # the TCP right above the box's top face, then one step down into it
    env = UR5eReachEnv(batch_size=(1,), seed=0)
    q = HOME.clone()
    tcp = env.robot.fk(q)[0]
    box = torch.tensor([[tcp[0] - 0.1, tcp[0] + 0.1, tcp[1] - 0.1, tcp[1] + 0.1, 0.0, tcp[2].item() - 0.04]])
    env, td = _env_at(q, HOME + torch.tensor([[0.9, 0.0, 0.0]]), box, collision_type=collision_type)
    assert not env.collides(q, box).any()
    td["action"] = torch.tensor([[0.0, 1.0, 0.0]])  # shoulder lift lowers the arm
    return env, td


@pytest.mark.parametrize("collision_type", [0, 1, 2])
def test_collision_types(collision_type):
    env, td = _colliding_setup(collision_type)
    obs = td["observation"].clone()
    out = env.step(td)["next"]
    assert out["collision"].item()
    assert out["reward"].item() == env.COLLISION_REWARD
    assert out["collision_reason"].item() & CollisionReason.OBSTACLE
    if collision_type == 0:
        assert out["terminated"].item() and out["done"].item()
        torch.testing.assert_close(out["observation"], env.transition(obs, td["action"]))
        assert not out["discard"].item()
    else:
        # the arm is put back where it was and the episode goes on
        assert not out["done"].item()
        torch.testing.assert_close(out["observation"], obs)
        assert out["discard"].item() == (collision_type == 1)
        # and it can move on from there
        td2 = out.clone()
        td2["action"] = torch.tensor([[0.0, -1.0, 0.0]])
        assert not env.step(td2)["next", "collision"].item()


def test_workspace_exit_is_a_collision():
    env, td = _env_at(HOME, HOME + 0.3, FAR_BOX)
    # raise the TCP above z = 0.6 by lifting the shoulder
    q = HOME.clone()
    for _ in range(20):
        q = q + torch.tensor([[0.0, -0.125, 0.0]])
        if env.robot.fk(q)[0, 2] > 0.6:
            break
    flags = env.collision_flags(q, FAR_BOX)
    assert flags.item() & CollisionReason.WORKSPACE


@pytest.mark.parametrize("collision_type", [0, 2])
def test_workspace_exit_blocked(collision_type):
    # from HOME, lifting the shoulder moves the TCP up and back: walk to the step that leaves the workspace
    env, td = _env_at(HOME, HOME + 0.3, FAR_BOX, workspace_exit="block", collision_type=collision_type)
    lift = torch.tensor([[0.0, -1.0, 0.0]])
    for _ in range(40):
        inside = env.transition(td["observation"], lift)
        if not in_box(env.robot.fk(env._q + lift * env.ACTION_SCALE), env.workspace_low, env.workspace_high).item():
            break
        td["action"] = lift
        td = env.step(td)["next"].clone()
    else:
        pytest.fail("the shoulder lift never left the workspace")
    before = env._q.clone()
    td["action"] = lift
    out = env.step(td)["next"]
    # not taken: the arm stays, no collision, no termination, reward -distance
    assert torch.equal(env._q, before)
    assert not out["collision"].item() and not out["terminated"].item()
    dist = (env._tcp - env._goal).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(out["reward"], -dist)
    # the pure model agrees with the step
    torch.testing.assert_close(inside, out["observation"])
    torch.testing.assert_close(env.reward(td["observation"], inside), out["reward"])
    # the default still counts the exit as a collision
    strict, td2 = _env_at(before, HOME + 0.3, FAR_BOX, collision_type=collision_type)
    td2["action"] = lift
    assert strict.step(td2)["next", "collision"].item()
    with pytest.raises(ValueError, match="workspace_exit"):
        UR5eReachEnv(workspace_exit="clip")


def test_seeding_gives_identical_rollouts():
    def run(seed):
        env = UR5eReachEnv(num_envs=16, seed=seed)
        torch.manual_seed(123)
        return env.rollout(30, break_when_any_done=False)

    a, b, c = run(5), run(5), run(6)
    assert (a == b).all()
    assert not torch.equal(a["observation"], c["observation"])


def test_partial_reset_only_touches_masked_envs():
    env = UR5eReachEnv(num_envs=6, seed=0)
    td = env.reset()
    before = td["observation"].clone()
    mask = torch.tensor([True, False, True, False, False, False]).unsqueeze(-1)
    q_before = env.state["q"].clone()
    # as a collector does: the current tensordict plus the "_reset" mask
    td2 = env.reset(td.clone().set("_reset", mask))
    after = td2["observation"]
    changed = (env.state["q"] != q_before).any(-1)
    assert torch.equal(changed, mask.squeeze(-1))
    # a collector-style call holding only "_reset" changes the same envs' state only
    q_before = env.state["q"].clone()
    env.reset(TensorDict({"_reset": mask}, batch_size=[6]))
    assert torch.equal((env.state["q"] != q_before).any(-1), mask.squeeze(-1))
    torch.testing.assert_close(after[~mask.squeeze(-1)], before[~mask.squeeze(-1)])
    assert not torch.equal(after[mask.squeeze(-1)], before[mask.squeeze(-1)])


def test_collector_runs_with_auto_reset():
    from torchrl.collectors import Collector

    env = UR5eReachEnv(num_envs=8, seed=0, max_steps=10)
    collector = Collector(env, None, frames_per_batch=8 * 25, total_frames=8 * 50)
    batches = list(collector)
    collector.shutdown()
    data = batches[-1]
    assert data.batch_size == (8, 25)
    # episodes end every 10 steps at the latest, and start anew
    assert data["next", "done"].sum() >= 8 * 2
    assert (data["next", "truncated"] | data["next", "terminated"]).eq(data["next", "done"]).all()


def test_bad_arguments():
    with pytest.raises(ValueError, match="collision_type"):
        UR5eReachEnv(collision_type=3)
    with pytest.raises(ValueError, match="max_steps"):
        UR5eReachEnv(max_steps=0)
    with pytest.raises(ValueError, match="num_envs"):
        UR5eReachEnv(num_envs=0)
    with pytest.raises(ValueError, match="batch_size"):
        UR5eReachEnv(batch_size=(0,))
    with pytest.raises(ValueError, match="success_distance"):
        UR5eReachEnv(success_distance=-1.0)
    with pytest.raises(TypeError, match="dtype"):
        UR5eReachEnv(dtype=torch.int32)
    env = UR5eReachEnv(num_envs=2, seed=0)
    td = env.reset()
    td["action"] = torch.tensor([[float("nan"), 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="NaN"):
        env.step(td)
    td["action"] = torch.zeros(2, 4)
    with pytest.raises(ValueError, match="action"):
        env.step(td)
    with pytest.raises(ValueError, match="obs"):
        env.transition(torch.zeros(2, 14), torch.zeros(2, 3))


@pytest.mark.parametrize("workspace_exit", ["collision", "block"])
def test_transition_reward_is_transition_then_reward(workspace_exit):
    # states from rollouts (some near the table, the box, the workspace's edge) and large random actions
    env = UR5eReachEnv(num_envs=64, seed=3, workspace_exit=workspace_exit)
    obs = env.rollout(20, break_when_any_done=False)["observation"].reshape(-1, 15)
    action = torch.rand(obs.shape[0], 3, generator=torch.Generator().manual_seed(0)) * 2.4 - 1.2
    nxt, reward = env.transition_reward(obs, action)
    want = env.transition(obs, action)
    torch.testing.assert_close(nxt, want)
    torch.testing.assert_close(reward, env.reward(obs, want))
    # every outcome is exercised: collisions, successes are rare, plain -distance steps
    assert (reward == env.COLLISION_REWARD).any() and (reward < 0).any() and (reward > env.COLLISION_REWARD).any()
