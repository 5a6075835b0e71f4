"""The MuJoCo twin and closed-loop transfer (torchrl_silp.sim): skipped without the ``sim`` extra."""

from __future__ import annotations

import json

import pytest
import torch
from omegaconf import OmegaConf

mujoco = pytest.importorskip("mujoco")

from torchrl_silp.sim import MujocoTwin  # noqa: E402
from torchrl_silp.sim.transfer import NOISE_LEVELS, Perception, run_transfer, scenario_tasks  # noqa: E402


def straight_policy(model, goal_q):
    """Drive along the straight joint-space segment to the goal configuration, one action unit at most per step."""

    def policy(td):
        d = (goal_q.to(td["joint_position"].dtype) - td["joint_position"]) / model.action_scale
        td["action"] = d / d.abs().amax(-1, keepdim=True).clamp(min=1)
        return td

    return policy


def kinematic_outcome(model, tasks, max_steps=50):
    """(success, collision) of the straight policy in the kinematic task model, step by step (model.step)."""
    state = model.state_at(tasks["joint_position"], tasks.select("obstacle"), tasks["desired_goal"])
    policy = straight_policy(model, tasks["goal_joint_position"])
    n = len(tasks)
    success, collision = torch.zeros(n, dtype=torch.bool), torch.zeros(n, dtype=torch.bool)
    for _ in range(max_steps):
        action = policy(state.clone())["action"]
        nxt, _, hit, reached, _ = model.step(state, action)
        active = ~(success | collision)
        collision |= hit.squeeze(-1) & active
        success |= reached.squeeze(-1) & active & ~collision
        state = nxt
    return success, collision


def test_twin_tcp_agrees_with_the_models_forward_kinematics(model):
    tasks = model.sample_tasks(64, torch.Generator().manual_seed(3))
    twin = MujocoTwin(model, n_envs=64)
    for key in ("joint_position", "goal_joint_position"):
        twin.reset(tasks[key], tasks["obstacle"])
        fk = model.robot.fk(tasks[key].double())
        assert (twin.tcp().double() - fk).abs().max() < 1e-5
        # the encoders read back what was set, and no task configuration touches anything
        torch.testing.assert_close(twin.config(), tasks[key].double(), atol=1e-12, rtol=0)
        assert not twin.colliding().any()


def test_slow_servo_zero_noise_run_reproduces_the_kinematic_outcome(model):
    tasks = torch.cat([scenario_tasks(model, "free", 8, seed=5), scenario_tasks(model, "block", 8, seed=5)])
    want_success, want_collision = kinematic_outcome(model, tasks)
    assert want_success[:8].all() and want_collision[8:].all()  # both outcomes are represented
    out = run_transfer(straight_policy(model, tasks["goal_joint_position"]), model, tasks,
                       perception=NOISE_LEVELS["none"], control_dt=0.5)
    assert torch.equal(out["success"], want_success) and torch.equal(out["collision"], want_collision)


def test_change_moves_the_box_during_the_episode(model):
    tasks = scenario_tasks(model, "change", 6, seed=2, speed=0.5, move_at_s=0.2)
    out = run_transfer(straight_policy(model, tasks["goal_joint_position"]), model, tasks, control_dt=0.1)
    track = out["box_track"][:, :, 0]  # [steps + 1, n, 3]
    start = tasks["obstacle"].view(-1, 3, 2).mean(-1).double()
    end = tasks["obstacle_end"].view(-1, 3, 2).mean(-1).double()
    torch.testing.assert_close(track[0], start, atol=1e-6, rtol=0)
    # the box has moved at 0.5 m/s from 0.2 s on: after k steps of 0.1 s it is min(0.5 (0.1 k - 0.2), |end - start|)
    # along the line from its start to its second place (the last tick of a step is at its end minus 1/10 step)
    for k in (3, 5):
        t = 0.1 * (k - 1) + 0.09
        moved = (track[k] - start).norm(dim=-1)
        want = torch.full((len(tasks),), max(0.5 * (t - 0.2), 0.0), dtype=torch.float64).minimum(
            (end - start).norm(dim=-1))
        torch.testing.assert_close(moved, want, atol=1e-6, rtol=0)
    assert (out["steps"] >= 5).all()  # the episodes were still running while it moved
    # the straight path it blocks: the scripted arm runs into it
    assert out["collision"].float().mean() > 0.5


def test_a_collision_is_never_a_success(model):
    # the box stands on each goal: the arm touches it at (or before) reaching the goal
    tasks = scenario_tasks(model, "free", 6, seed=7)
    half = torch.tensor(model.OBSTACLE_SIZE) / 2
    goal = tasks["desired_goal"]
    tasks.set("obstacle", torch.stack([goal - half, goal + half], -1).view(-1, 6))
    out = run_transfer(straight_policy(model, tasks["goal_joint_position"]), model, tasks, control_dt=0.1)
    assert out["collision"].all() and not out["success"].any()


def test_noise_changes_what_the_policy_sees_not_the_world(model):
    tasks = scenario_tasks(model, "free", 4, seed=1)
    seen = []

    def recording(td):
        seen.append(td["obstacle"].clone())
        return straight_policy(model, tasks["goal_joint_position"])(td)

    out = run_transfer(recording, model, tasks, perception=Perception(obstacle_noise=0.01, latency_steps=0), seed=0)
    true = tasks["obstacle"]
    err = torch.stack([s - true for s in seen])  # [steps, n, 6]
    # one shift per box and axis: its two bounds move together, by about 1 cm
    torch.testing.assert_close(err[..., 0::2], err[..., 1::2], atol=1e-6, rtol=0)
    assert 0.005 < err[..., 0::2].std() < 0.02
    torch.testing.assert_close(out["box_track"][-1, :, 0], true.view(-1, 3, 2).mean(-1).double(), atol=1e-6, rtol=0)


def test_bad_arguments_name_the_parameter(model):
    with pytest.raises(ValueError, match="obstacle_noise"):
        Perception(obstacle_noise=-0.1)
    with pytest.raises(TypeError, match="latency_steps"):
        Perception(latency_steps=1.5)
    with pytest.raises(ValueError, match="scenario"):
        scenario_tasks(model, "nope", 4, seed=0)
    tasks = scenario_tasks(model, "free", 2, seed=0)
    with pytest.raises(ValueError, match="control_dt"):
        run_transfer(straight_policy(model, tasks["goal_joint_position"]), model, tasks, control_dt=0)
    with pytest.raises(ValueError, match="n_envs"):
        MujocoTwin(model, n_envs=0)
    twin = MujocoTwin(model, n_envs=2)
    with pytest.raises(ValueError, match="obstacle"):
        twin.reset(tasks["joint_position"], torch.zeros(2, 6))  # a box of size 0


# ------------------------------------------------------------------ recipes/transfer.py


def compose(name: str, overrides: list[str]):
    from torchrl_silp.recipes.schema import load_config

    return load_config(name, overrides)


@pytest.fixture(scope="module")
def still_run(tmp_path_factory):
    """A run dir whose evaluated actor always outputs the action 0: its arm never moves."""
    from torchrl_silp.recipes import builders as utils

    root = tmp_path_factory.mktemp("still_run")
    cfg = compose("sac_silp", ["env.num_envs=4", "network.hidden_sizes=[16,16]", f"run_dir={root}"])
    model = utils.make_model(cfg, torch.device("cpu"))
    env = utils.make_env(cfg, model, torch.device("cpu"), seed=0)
    actor, critic = utils.make_actor_critic(cfg, model, env, "cpu")
    loss, _ = utils.make_loss(cfg, actor, critic, model, env)
    with torch.no_grad():
        for p in actor.parameters():
            p.zero_()  # the TanhNormal's location is 0: its deterministic action is tanh(0) = 0
    averaged = {f"module.{k}": v.clone() for k, v in actor.state_dict().items()}
    (root / "checkpoint").mkdir()
    torch.save({"loss": loss.state_dict(), "averaged_actor": averaged,
                "counters": {"frames": 0, "episodes": 0}}, root / "checkpoint" / "state.pt")
    OmegaConf.save(cfg, root / "config.yaml", resolve=True)
    return root


def test_transfer_recipe_runs_a_checkpoint_and_writes_its_results(still_run, tmp_path, capsys):
    from torchrl_silp.recipes import transfer

    out = tmp_path / "t.json"
    cfg = compose("transfer", [f"checkpoint={still_run}", "scenario=free", "noise=none", "n_tasks=3", "max_steps=4",
                               f"out={out}"])
    result = transfer.run(cfg)
    saved = json.loads(out.read_text())
    assert saved == json.loads(json.dumps(result))
    (row,) = saved["rows"]
    # the arm stays at its start, away from its goal and clear of the box: no success, no collision, every step
    assert row["scenario"] == "free" and row["n_tasks"] == 3 and row["success_rate"] == 0.0
    assert row["collision_rate"] == 0.0 and row["mean_steps"] == 4.0 and row["time_to_success_s"] is None
    assert saved["method"] == "sac_silp_plus_ext" and "free     none" in capsys.readouterr().out
    with pytest.raises(ValueError, match="scenario"):
        transfer.run(compose("transfer", [f"checkpoint={still_run}", "scenario=nope"]))
    with pytest.raises(FileNotFoundError, match="checkpoint"):
        transfer.run(compose("transfer", [f"checkpoint={tmp_path}"]))


def test_reaching_trials_repeat_free_then_blocked_scenarios(model):
    from torchrl_silp.sim import reaching_trials, scenario_tasks

    tasks = reaching_trials(model, n_free=2, n_block=3, trials=4, seed=7)
    assert tasks.batch_size == (20,) and tasks["scenario"].tolist() == [i for i in range(5) for _ in range(4)]
    free, block = scenario_tasks(model, "free", 2, seed=7), scenario_tasks(model, "block", 3, seed=8)
    for i, scenario in enumerate([*free.unbind(0), *block.unbind(0)]):
        for trial in tasks[4 * i:4 * i + 4].unbind(0):
            for key in ("joint_position", "desired_goal", "obstacle"):
                assert torch.equal(trial[key], scenario[key]), (i, key)
    with pytest.raises(ValueError, match="trials"):
        reaching_trials(model, trials=0)


def test_the_reaching_test_as_a_sweep_run_writes_each_scenarios_share_to_its_summary(still_run, tmp_path):
    from torchrl_silp.recipes import transfer

    run_dir = tmp_path / "table5_sac" / "seed0"
    cfg = compose("transfer", [f"checkpoint={still_run}", "scenario=reaching", "noise=paper", "trials=2",
                               "max_steps=3", f"run_dir={run_dir}", "seed=0", "resume=true"])
    result = transfer.run(cfg)
    saved = json.loads((run_dir / "summary.json").read_text())
    (row,) = saved["rows"]
    # ten scenarios of two trials; the still arm reaches none of its goals and hits no box it starts clear of
    assert row["scenario"] == "reaching" and row["n_tasks"] == 20 and row["scenario_success"] == [0.0] * 10
    assert row["collision_rate"] == 0.0 and saved == json.loads(json.dumps(result))


def test_mujoco_labels_are_the_twins_contacts_and_within_the_exact_checks(model):
    from torchrl_silp.models.learned_collision import collision_dataset
    from torchrl_silp.sim import mujoco_labels

    _, exact, config, scene = collision_dataset(model, 3000, torch.Generator().manual_seed(0), n_scenes=100)
    labels = mujoco_labels(model, config, scene, batch=1000)
    # the task model's sphere cover holds the URDF's primitives: what MuJoCo finds, the exact check finds too
    assert not (labels & ~exact).any() and labels.any() and (exact & ~labels).any()
    twin = MujocoTwin(model, n_envs=7)
    twin.reset(config[:7], scene["obstacle"][:7])
    assert torch.equal(twin.colliding(), labels[:7])


# ------------------------------------------------------------------ pick-and-place (Fig. 8)
def ik_policy(model):
    """Straight joint-space moves to the IK solution of the goal: an oracle that ignores the box. It solves
    once per goal, from the configuration it is first asked at."""
    from torchrl_silp.sim.pick_place import _ik

    solved = {}

    def policy(td):
        q, goal = td["joint_position"], td["desired_goal"]
        key = tuple(goal.flatten().tolist())
        if key not in solved:
            solved.clear()
            solved[key] = _ik(model, q, goal)
        d = (solved[key] - q) / model.action_scale
        td["action"] = d / d.abs().amax(-1, keepdim=True).clamp(min=1)
        return td

    return policy


def test_pick_and_place_stages_with_an_oracle_policy(model):
    from torchrl_silp.sim.pick_place import BASKET, STAGES, pick_place_tasks, run_pick_place

    tasks = pick_place_tasks(model, 3, seed=4)
    # the box moved out of the way: nothing stands between the oracle and the basket
    far = tasks["obstacle"].clone()
    far[:, 0:2] += 3.0
    tasks.set("obstacle", far)
    out = run_pick_place(ik_policy(model), model, tasks)
    # the oracle's straight joint paths may still touch the table, the cube or the basket on the way; every
    # trial without a collision goes through every stage: the weld lifts the cube and it rests in the basket
    clean = ~out["collision"]
    assert clean.any()
    for stage in STAGES:
        assert out[stage][clean].all(), stage
    assert not (out["place"] & out["collision"]).any()  # a trial that collided is never placed
    # a perception 10 cm off misses the cube: no grasp, nothing placed, and the stages never skip one
    off = run_pick_place(ik_policy(model), model, tasks[:2], perception=Perception(obstacle_noise=0.1), seed=1)
    assert not off["place"].all()
    for before, after in zip(STAGES, STAGES[1:]):
        assert not (off[after] & ~off[before]).any()
    assert BASKET == (0.15, 0.15, 0.10)  # the paper's basket


def test_replanning_prm_reaches_free_goals_and_the_recipe_takes_one_policy(model, still_run):
    pytest.importorskip("ompl")
    from torchrl_silp.sim.replan import ReplanningPRMPolicy

    tasks = scenario_tasks(model, "free", 3, seed=11)
    policy = ReplanningPRMPolicy(model, tasks["goal_joint_position"], budget_s=0.1, seed=0)
    out = run_transfer(policy, model, tasks, control_dt=0.1, max_steps=30)
    assert out["success"].sum() >= 2 and policy.plans >= 3
    from torchrl_silp.recipes import transfer

    with pytest.raises(ValueError, match="one of checkpoint .* and prm_budget_s"):
        transfer.run(compose("transfer", [f"checkpoint={still_run}", "prm_budget_s=0.1"]))
    with pytest.raises(ValueError, match="one of checkpoint .* and prm_budget_s"):
        transfer.run(compose("transfer", []))
