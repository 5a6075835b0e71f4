"""UR5eReachEnv (ReachEnv over UR5eReach, CollisionHandling, CatTensors): specs, task sampling,
reward / termination / truncation, collision types, seeding, partial resets."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_silp import CollisionHandling, CollisionReason, ReachEnv, UR5eReach, UR5eReachEnv
from torchrl_silp.geometry import in_box


@pytest.mark.parametrize("batch_size", [(), (1,), (64,), (2, 3)])
def test_check_env_specs(batch_size):
    env = UR5eReachEnv(batch_size=batch_size, seed=0)
    check_env_specs(env)


def test_num_envs_alias_and_composition():
    assert UR5eReachEnv(num_envs=5).batch_size == (5,)
    assert UR5eReachEnv().batch_size == ()
    env = UR5eReachEnv(collision_type=1, seed=0)
    assert isinstance(env.base_env, ReachEnv) and isinstance(env.model, UR5eReach)
    assert env.model is env.base_env.model and env.collision_type == 1
    assert UR5eReachEnv(collision_type=None).collision_type is None
    assert not any(isinstance(t, CollisionHandling) for t in UR5eReachEnv(collision_type=None).transform)


def test_sampled_tasks_satisfy_paper_constraints():
    env = UR5eReachEnv(seed=0)
    model = env.model
    t = env.sample_tasks(2000)
    assert set(t.keys()) == {"joint_position", "achieved_goal", "obstacle", "desired_goal", "goal_joint_position"}
    centre = (t["obstacle"][:, 0::2] + t["obstacle"][:, 1::2]) / 2
    size = t["obstacle"][:, 1::2] - t["obstacle"][:, 0::2]
    d1 = (t["achieved_goal"] - centre).norm(dim=-1)
    d2 = (t["achieved_goal"] - t["desired_goal"]).norm(dim=-1)
    d3 = (centre - t["desired_goal"]).norm(dim=-1)
    assert (d2 > d1).all() and (d1 > d3).all()
    low, high = torch.tensor(UR5eReach.WORKSPACE_LOW), torch.tensor(UR5eReach.WORKSPACE_HIGH)
    for p in (t["achieved_goal"], t["desired_goal"]):
        assert ((p >= low) & (p <= high)).all()
    torch.testing.assert_close(size, torch.tensor(UR5eReach.OBSTACLE_SIZE).expand_as(size))
    assert (centre[:, 0] >= 0.3).all() and (centre[:, 0] <= 0.7).all()
    assert (centre[:, 1] >= 0.1).all() and (centre[:, 1] <= 0.4).all()
    torch.testing.assert_close(centre[:, 2], torch.full((2000,), 0.15))
    # start and goal are collision-free configurations and the goal is their TCP
    assert not model.collides(t["joint_position"], t["obstacle"]).any()
    assert not model.collides(t["goal_joint_position"], t["obstacle"]).any()
    # ... and keep the motion check's margin, so that every motion out of them can be judged
    margin = model.motion_margin()
    assert all(m > 0 for m in margin.values())
    for q in (t["joint_position"], t["goal_joint_position"]):
        assert (model.collision_flags(q, t["obstacle"], margin)[0] == 0).all()
    torch.testing.assert_close(model.robot.fk(t["goal_joint_position"]), t["desired_goal"])
    torch.testing.assert_close(model.robot.fk(t["joint_position"]), t["achieved_goal"])
    # the obstacle region is covered, not a corner of it
    assert centre[:, 0].max() - centre[:, 0].min() > 0.3


@pytest.mark.parametrize("task_branch", ["front", "any"])
def test_task_branch(task_branch):
    env = UR5eReachEnv(seed=0, task_branch=task_branch)
    t = env.sample_tasks(1500)
    flipped = []
    for q, tcp in ((t["joint_position"], t["achieved_goal"]), (t["goal_joint_position"], t["desired_goal"])):
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
    reach = UR5eReach.reach_along_pan(q, env.model.robot.fk(q))
    assert reach[0] < 0 < reach[1]
    with pytest.raises(ValueError, match="task_branch"):
        UR5eReachEnv(task_branch="back")


def test_reset_observation_layout():
    env = UR5eReachEnv(num_envs=8, seed=1)
    td = env.reset()
    obs = td["observation"]
    fk = env.model.robot.fk
    torch.testing.assert_close(obs[:, 3:6], fk(obs[:, :3]))
    torch.testing.assert_close(obs[:, 12:15], fk(td["goal_joint_position"]))
    assert obs.dtype == torch.float32 and obs.shape == (8, 15)
    # the flat observation is the named keys side by side
    for key, part in (("joint_position", obs[:, :3]), ("achieved_goal", obs[:, 3:6]), ("obstacle", obs[:, 6:12]),
                      ("desired_goal", obs[:, 12:15])):
        assert torch.equal(td[key], part)
    assert torch.equal(td["step_count"], torch.zeros(8, 1, dtype=torch.long))


FAR_BOX = torch.tensor([[5.0, 5.2, 5.0, 5.2, 5.0, 5.3]])
HOME = torch.tensor([[0.0, -math.pi / 2, math.pi / 2]])


def _env_at(q, goal_q, obstacle, **kwargs):
    """A UR5eReachEnv and a tensordict holding the task set by hand (the state lives in the tensordict)."""
    env = UR5eReachEnv(batch_size=(q.shape[0],), seed=0, **kwargs)
    td = env.reset()
    fk = env.model.robot.fk
    td.update(
        {
            "joint_position": q.clone(),
            "achieved_goal": fk(q),
            "obstacle": obstacle.expand(q.shape[0], 6).clone(),
            "desired_goal": fk(goal_q),
            "goal_joint_position": goal_q.clone(),
        }
    )
    td["observation"] = env.model.observation(td)
    return env, td


def test_reward_success_terminates():
    goal_q = HOME + torch.tensor([[0.1, 0.0, 0.0]])
    env, td = _env_at(HOME, goal_q, FAR_BOX)
    td["action"] = torch.tensor([[0.8, 0.0, 0.0]])  # 0.1 rad: lands exactly on the goal
    out = env.step(td)["next"]
    assert out["reward"].item() == env.model.success_reward == 1.0
    assert out["success"].item() and out["terminated"].item() and out["done"].item()
    assert not out["truncated"].item() and not out["collision"].item()


def test_reward_is_minus_distance_otherwise():
    goal_q = HOME + torch.tensor([[0.5, 0.2, -0.2]])
    env, td = _env_at(HOME, goal_q, FAR_BOX)
    td["action"] = torch.tensor([[0.3, -0.2, 0.1]])
    out = env.step(td)["next"]
    fk = env.model.robot.fk
    tcp = fk(HOME + 0.125 * td["action"])
    expected = -(tcp - fk(goal_q)).norm()
    assert out["reward"].item() == pytest.approx(expected.item(), abs=1e-6)
    assert not out["done"].item()
    torch.testing.assert_close(out["observation"][:, :3], HOME + 0.125 * td["action"])
    # the model's f_s and f_r agree with the step
    model = env.model
    nxt = model.transition(td, td["action"])
    torch.testing.assert_close(model.observation(nxt), out["observation"])
    torch.testing.assert_close(model.reward(td, nxt), out["reward"])


def test_truncation_at_max_steps():
    env, td = _env_at(HOME, HOME + 0.5, FAR_BOX, max_steps=7)
    for i in range(7):
        td["action"] = torch.zeros(1, 3)
        nxt = env.step(td)["next"]
        assert nxt["truncated"].item() == (i == 6)
        assert not nxt["terminated"].item()
        assert nxt["step_count"].item() == i + 1
        td = nxt.clone()
    assert nxt["done"].item()


def test_actions_are_clipped():
    env, td = _env_at(HOME, HOME + 0.5, FAR_BOX)
    td["action"] = torch.tensor([[5.0, -3.0, 0.5]])
    out = env.step(td)["next"]
    torch.testing.assert_close(out["observation"][:, :3], HOME + 0.125 * torch.tensor([[1.0, -1.0, 0.5]]))
    torch.testing.assert_close(out["joint_position"], HOME + 0.125 * torch.tensor([[1.0, -1.0, 0.5]]))


def _colliding_setup(collision_type):
    # the TCP right above the box's top face, then one step down into it
    tcp = UR5eReach().robot.fk(HOME)[0]
    box = torch.tensor([[tcp[0] - 0.1, tcp[0] + 0.1, tcp[1] - 0.1, tcp[1] + 0.1, 0.0, tcp[2].item() - 0.04]])
    env, td = _env_at(HOME, HOME + torch.tensor([[0.9, 0.0, 0.0]]), box, collision_type=collision_type)
    assert not env.model.collides(HOME, box).any()
    td["action"] = torch.tensor([[0.0, 1.0, 0.0]])  # shoulder lift lowers the arm
    return env, td


@pytest.mark.parametrize("collision_type", [0, 1, 2])
def test_collision_types(collision_type):
    env, td = _colliding_setup(collision_type)
    model = env.model
    obs = td["observation"].clone()
    out = env.step(td)["next"]
    assert out["collision"].item()
    assert out["reward"].item() == model.collision_reward == -10.0
    assert out["collision_reason"].item() & CollisionReason.OBSTACLE
    if collision_type == 0:
        assert out["terminated"].item() and out["done"].item()
        torch.testing.assert_close(out["observation"], model.observation(model.transition(td, td["action"])))
        assert not out["discard"].item()
    else:
        # the arm is put back where it was and the episode goes on
        assert not out["done"].item()
        torch.testing.assert_close(out["observation"], obs)
        assert torch.equal(out["joint_position"], td["joint_position"])
        assert torch.equal(out["achieved_goal"], td["achieved_goal"])
        assert out["discard"].item() == (collision_type == 1)
        # and it can move on from there
        td2 = out.clone()
        td2["action"] = torch.tensor([[0.0, -1.0, 0.0]])
        assert not env.step(td2)["next", "collision"].item()


def test_collision_covers_the_segment_not_only_its_end():
    # a 2 mm cube where a gripper sphere passes halfway through the step: both ends are free
    action = torch.tensor([[1.0, -1.0, 1.0]])
    model = UR5eReach()
    q_end = HOME + model.action_scale * action
    q_mid = (HOME + q_end) / 2
    ends = torch.cat([HOME, q_end])
    centres, radii = model.robot.link_spheres(q_mid[0])
    # per sphere: how far its centre halfway is from its centres at the ends, less its radius
    moved = [(centres - model.robot.link_spheres(q[0])[0]).norm(dim=-1) for q in (HOME, q_end)]
    gap = torch.minimum(*moved) - radii
    p = centres[gap.argmax()]
    cube = torch.stack([p - 0.001, p + 0.001], -1).reshape(1, 6)
    assert not model.collides(ends, cube.expand(2, 6)).any() and model.collides(q_mid, cube).all()
    for collision_type in (0, 2):
        env, td = _env_at(HOME, HOME + 0.5, cube, collision_type=collision_type)
        td["action"] = action
        out = env.step(td)["next"]
        assert out["collision"].item() and out["collision_reason"].item() == CollisionReason.OBSTACLE
        # a collision a check of the reached state alone would have let pass
        assert out["swept_collision"].item()
    # also without the margin: the samples in between are checked, not only the ends
    exact = UR5eReach(conservative=False)
    assert exact.motion_collision_flags(HOME, q_end, TensorDict(obstacle=cube, batch_size=[1]))[0].item()


def test_swept_collisions_are_the_collisions_whose_reached_state_is_free():
    model = UR5eReach()
    env = ReachEnv(model, num_envs=64, seed=5)
    torch.manual_seed(5)
    td = env.rollout(50, break_when_any_done=False)
    nxt = td["next"]
    end_collides = model.collides(nxt["joint_position"], nxt.select("obstacle"))
    collision, swept = nxt["collision"].squeeze(-1), nxt["swept_collision"].squeeze(-1)
    assert torch.equal(swept, collision & ~end_collides)
    assert swept.any() and (collision & ~swept).any()


def test_workspace_exit_is_a_collision():
    model = UR5eReach()
    # raise the TCP above z = 0.6 by lifting the shoulder
    q = HOME.clone()
    for _ in range(20):
        q = q + torch.tensor([[0.0, -0.125, 0.0]])
        if model.robot.fk(q)[0, 2] > 0.6:
            break
    flags, tcp = model.collision_flags(q, FAR_BOX)
    assert flags.item() & CollisionReason.WORKSPACE
    torch.testing.assert_close(tcp, model.robot.fk(q))


@pytest.mark.parametrize("collision_type", [0, 2])
def test_workspace_exit_blocked(collision_type):
    # from HOME, lifting the shoulder moves the TCP up and back: walk to the step that leaves the workspace
    env, td = _env_at(HOME, HOME + 0.3, FAR_BOX, workspace_exit="block", collision_type=collision_type)
    model = env.model
    lift = torch.tensor([[0.0, -1.0, 0.0]])
    for _ in range(40):
        q_next = td["joint_position"] + lift * model.action_scale
        if not in_box(model.robot.fk(q_next), model.workspace_low, model.workspace_high).item():
            break
        td["action"] = lift
        td = env.step(td)["next"].clone()
    else:
        pytest.fail("the shoulder lift never left the workspace")
    before = td["joint_position"].clone()
    td["action"] = lift
    out = env.step(td)["next"]
    # not taken: the arm stays, no collision, no termination, reward -distance
    assert torch.equal(out["joint_position"], before)
    assert not out["collision"].item() and not out["terminated"].item()
    dist = (out["achieved_goal"] - out["desired_goal"]).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(out["reward"], -dist)
    # the model agrees with the step
    inside = model.transition(td, lift)
    assert torch.equal(inside["joint_position"], before)
    torch.testing.assert_close(model.observation(inside), out["observation"])
    torch.testing.assert_close(model.reward(td, inside), out["reward"])
    # the default still counts the exit as a collision
    strict, td2 = _env_at(before, HOME + 0.3, FAR_BOX, collision_type=collision_type)
    td2["action"] = lift
    assert strict.step(td2)["next", "collision"].item()
    with pytest.raises(ValueError, match="workspace_exit"):
        UR5eReachEnv(workspace_exit="clip")


@pytest.mark.parametrize("workspace_exit", ["collision", "block"])
def test_model_step_is_transition_then_outcome(workspace_exit):
    # states from rollouts (some near the table, the box, the workspace's edge) and large random actions
    env = UR5eReachEnv(num_envs=64, seed=3, workspace_exit=workspace_exit)
    model = env.model
    torch.manual_seed(0)
    state = env.rollout(20, break_when_any_done=False).select(*model.state_keys).reshape(-1)
    action = torch.rand(state.shape[0], 3, generator=torch.Generator().manual_seed(0)) * 2.4 - 1.2
    nxt, reward, collision, success, flags = model.step(state, action)
    want = model.transition(state, action)
    for key in model.state_keys:
        assert torch.equal(nxt[key], want[key])
    for got, exp in zip((reward, collision, success, flags), model.outcome(state, want)):
        assert torch.equal(got, exp)
    # every outcome is exercised: collisions, plain -distance steps
    assert (reward == model.collision_reward).any() and (reward < 0).any() and (reward > model.collision_reward).any()


def test_seeding_gives_identical_rollouts():
    def run(seed):
        env = UR5eReachEnv(num_envs=8, seed=seed)
        torch.manual_seed(123)
        return env.rollout(20, break_when_any_done=False)

    a, b, c = run(5), run(5), run(6)
    assert (a == b).all()
    assert not torch.equal(a["observation"], c["observation"])


def test_partial_reset_only_touches_masked_envs():
    env = UR5eReachEnv(num_envs=6, seed=0)
    td = env.reset()
    before = td.clone()
    mask = torch.tensor([True, False, True, False, False, False]).unsqueeze(-1)
    # as a collector does: the current tensordict plus the "_reset" mask
    after = env.reset(td.clone().set("_reset", mask))
    rows = mask.squeeze(-1)
    for key in ("observation", "joint_position", "achieved_goal", "obstacle", "desired_goal", "goal_joint_position"):
        assert torch.equal(after[key][~rows], before[key][~rows]), key
        changed = (after[key] != before[key]).flatten(1).any(-1)
        assert torch.equal(changed, rows), key
    # a reset row is a fresh task
    torch.testing.assert_close(after["achieved_goal"], env.model.robot.fk(after["joint_position"]))
    assert not env.model.collides(after["joint_position"], after["obstacle"]).any()


def test_partial_resets_through_a_collector():
    from torchrl.collectors import Collector

    # type 0: collisions end episodes too, so envs end and restart at different steps
    env = UR5eReachEnv(num_envs=8, seed=0, max_steps=10, collision_type=0)
    collector = Collector(env, None, frames_per_batch=8 * 25, total_frames=8 * 50)
    batches = list(collector)
    collector.shutdown()
    data = batches[-1]
    assert data.batch_size == (8, 25)
    nxt = data["next"]
    # episodes end every 10 steps at the latest, and start anew
    assert nxt["done"].sum() >= 8 * 2
    assert (nxt["truncated"] | nxt["terminated"]).eq(nxt["done"]).all()
    done = nxt["done"][:, :-1].squeeze(-1)
    # some env restarts while another goes on: resets are partial
    assert (done.any(0) & ~done.all(0)).any()
    # an env that goes on starts its next step where the last one ended ...
    for key in ("joint_position", "achieved_goal", "obstacle", "desired_goal", "goal_joint_position"):
        assert torch.equal(data[key][:, 1:][~done], nxt[key][:, :-1][~done]), key
    assert torch.equal(data["step_count"][:, 1:][~done], nxt["step_count"][:, :-1][~done])
    # ... and one that ended starts a fresh task at step 0
    assert (data["step_count"][:, 1:][done] == 0).all()
    assert not torch.equal(data["obstacle"][:, 1:][done], nxt["obstacle"][:, :-1][done])
    torch.testing.assert_close(data["achieved_goal"], env.model.robot.fk(data["joint_position"]))


def test_bad_arguments():
    with pytest.raises(ValueError, match="collision_type"):
        UR5eReachEnv(collision_type=3)
    with pytest.raises(ValueError, match="max_steps"):
        UR5eReachEnv(max_steps=0)
    with pytest.raises(ValueError, match="num_envs"):
        UR5eReachEnv(num_envs=0)
    with pytest.raises(ValueError, match="batch_size"):
        UR5eReachEnv(batch_size=(0,))
    with pytest.raises(ValueError, match="num_envs or batch_size"):
        UR5eReachEnv(num_envs=2, batch_size=(2,))
    with pytest.raises(ValueError, match="success_distance"):
        UR5eReachEnv(success_distance=-1.0)
    with pytest.raises(ValueError, match="motion_resolution"):
        UR5eReachEnv(motion_resolution=0.0)
    with pytest.raises(TypeError, match="dtype"):
        UR5eReachEnv(dtype=torch.int32)
    with pytest.raises(TypeError, match="model"):
        ReachEnv("ur5e")
    env = UR5eReachEnv(num_envs=2, seed=0)
    td = env.reset()
    td["action"] = torch.tensor([[float("nan"), 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="NaN"):
        env.step(td)
    td["action"] = torch.zeros(2, 4)
    with pytest.raises(ValueError, match="action"):
        env.step(td)


def test_float64_env():
    env = UR5eReachEnv(num_envs=4, seed=0, dtype=torch.float64)
    check_env_specs(env)
    td = env.rollout(5)
    assert td["observation"].dtype == td["next", "reward"].dtype == td["action"].dtype == torch.float64


def test_stateless_step_reads_the_tensordict():
    # two envs, same state handed in: same result, whatever each env did before
    a, b = UR5eReachEnv(num_envs=4, seed=0), UR5eReachEnv(num_envs=4, seed=1)
    td = a.reset()
    b.rollout(3)
    td["action"] = torch.rand(4, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    out_a, out_b = a.step(td.clone())["next"], b.step(td.clone())["next"]
    assert (out_a == out_b).all()
    assert isinstance(out_a, TensorDict)


def test_table_contact_blocked():
    # walk the elbow down from a low pose until a step would put a sphere below the table
    model = UR5eReach(table_contact="block")
    strict = UR5eReach()
    q = torch.tensor([[0.5, -1.5, 1.5]])
    down = torch.tensor([[0.0, 0.0, 1.0]])
    state = model.state_at(q, TensorDict(obstacle=FAR_BOX.expand(1, 6).clone(), batch_size=[1]), model.robot.fk(q + 0.2))
    assert not model.collides(q, state.select("obstacle")).item()
    for _ in range(30):
        q_next = model.next_config(state["joint_position"], down)
        if strict.collision_flags(q_next, state.select("obstacle"))[0].item() & CollisionReason.TABLE:
            break
        state = model.transition(state, down)
    else:
        pytest.fail("lowering the elbow never reached the table")
    # the strict model counts the step as a collision; the blocking one stays where it is, free
    _, _, hit, _, flags = strict.step(state, down)
    assert hit.item() and flags.item() & CollisionReason.TABLE
    nxt, reward, hit, success, _ = model.step(state, down)
    assert torch.equal(nxt["joint_position"], state["joint_position"])
    assert not hit.item()
    dist = (state["achieved_goal"] - state["desired_goal"]).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(reward, -dist)
    with pytest.raises(ValueError, match="table_contact"):
        UR5eReach(table_contact="clip")
