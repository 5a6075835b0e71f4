"""check_task_model refuses each broken rule of the TaskModel interface, naming the member and the rule."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_silp.models import TaskModel, UR5eReach
from torchrl_silp.models.check import TaskModelError, check_task_model


class PointReach(TaskModel):
    """A point in the unit square reaching a goal around one rectangle (xmin, xmax, ymin, ymax)."""

    config_dim, goal_dim = 2, 2
    scene_shapes = {"obstacle": (4,)}
    collision_reasons = ("obstacle", "workspace")
    action_scale = 0.05

    def __init__(self, **kwargs):
        super().__init__(success_distance=0.05, motion_resolution=0.01, **kwargs)
        self._limits()

    def _limits(self):
        self.config_low = torch.zeros(2, device=self.device, dtype=self.dtype)
        self.config_high = torch.ones(2, device=self.device, dtype=self.dtype)

    def to(self, device):
        super().to(device)
        self._limits()
        return self

    def achieved_goal(self, config):
        return config.clone()

    def clearance(self, config, scene):
        box = scene["obstacle"] if isinstance(scene, TensorDict) else scene
        lo, hi = box[..., 0::2], box[..., 1::2]
        outside = torch.maximum(lo - config, config - hi).clamp(min=0).norm(dim=-1)
        inside = torch.maximum(lo - config, config - hi).amax(-1).clamp(max=0)
        wall = torch.minimum(config, 1 - config).amin(-1)
        return torch.stack([outside + inside, wall], -1)

    def collision_flags(self, config, scene, margin=None):
        margin = margin or {}
        c = self.clearance(config, scene)
        hit = (c[..., 0] < margin.get("obstacle", 0.0)).to(torch.uint8)
        out = (c[..., 1] < margin.get("workspace", 0.0)).to(torch.uint8)
        return (hit + 2 * out).unsqueeze(-1), self.achieved_goal(config)

    def lipschitz(self):
        return {"obstacle": 2.0, "workspace": 1.0}

    def _start_x(self, n, generator):
        return 0.15 + 0.1 * torch.rand(n, generator=generator)

    def sample_tasks(self, n, generator=None):
        box = torch.tensor([0.4, 0.6, 0.2, 0.8]).expand(n, 4)
        start = torch.stack([self._start_x(n, generator), 0.2 + 0.6 * torch.rand(n, generator=generator)], -1)
        goal = torch.stack([0.9 - (start[:, 0] - 0.1), start[:, 1]], -1)
        return TensorDict(
            {"joint_position": start, "achieved_goal": start.clone(), "obstacle": box.clone(),
             "desired_goal": goal.clone(), "goal_joint_position": goal},
            batch_size=[n],
        )


def test_a_correct_model_passes():
    check_task_model(PointReach())
    check_task_model(UR5eReach())


def _refused(model, member: str, rule: str):
    with pytest.raises(TaskModelError, match=rule) as info:
        check_task_model(model)
    assert str(info.value).startswith(f"{type(model).__name__}.{member}:"), str(info.value)


def test_bool_collision_flags():
    class BoolFlags(PointReach):
        def collision_flags(self, config, scene, margin=None):
            flags, goal = super().collision_flags(config, scene, margin)
            return flags != 0, goal

    _refused(BoolFlags(), "collision_flags", "uint8 bit flags")


def test_lipschitz_missing_a_reason():
    class NoWallBound(PointReach):
        def lipschitz(self):
            return {"obstacle": 2.0}

    _refused(NoWallBound(), "lipschitz", r"one bound per collision reason \['obstacle', 'workspace'\]")


def test_base_initialiser_not_called():
    class NoSuper(PointReach):
        def __init__(self):
            self.config_low, self.config_high = torch.zeros(2), torch.ones(2)

    _refused(NoSuper(), "__init__", r"call super\(\).__init__")


def test_float_joint_limits():
    class FloatLimits(PointReach):
        def _limits(self):
            self.config_low, self.config_high = 0.0, 1.0

    _refused(FloatLimits(), "config_low", "must be a torch.Tensor of shape")


def test_starts_within_the_motion_margin():
    class StartsOnTheWall(PointReach):
        def _start_x(self, n, generator):
            return torch.full((n,), 0.004)  # 4 mm from the wall, inside the 5 mm margin of the motion check

    _refused(StartsOnTheWall(), "sample_tasks", "a start configuration collides with the motion check's margin")


def test_to_device_leaves_a_tensor_behind():
    class Unmoved(PointReach):
        def to(self, device):
            low = self.config_low
            super().to(device)
            self.config_low = low  # a limit put back from before the move stays where it was
            return self

    _refused(Unmoved(), "to", r"still on cpu after to\('meta'\): \['model.config_low'")


def test_the_base_to_moves_a_subclass_s_own_tensors():
    class OwnTensors(PointReach):
        def __init__(self):
            super().__init__()
            self.table = torch.zeros(3)
            self.parts = [torch.ones(2), (torch.ones(1), "name")]
            self.named = {"a": torch.ones(4), "k": 3}
            self.net = torch.nn.Linear(2, 2)

        to = TaskModel.to  # no override: the base moves what the subclass holds

    model = OwnTensors().to("meta")
    moved = [model.table, model.parts[0], model.parts[1][0], model.named["a"], model.net.weight,
             model.config_low, model.config_high]
    assert [t.device.type for t in moved] == ["meta"] * len(moved)
    assert model.parts[1][1] == "name" and model.named["k"] == 3 and model.device == torch.device("meta")
    check_task_model(OwnTensors())


def test_a_flag_the_clearance_does_not_explain():
    class WrongClearance(PointReach):
        def clearance(self, config, scene):
            return super().clearance(config, scene).abs()  # never negative, though the flags say collision

        def collision_flags(self, config, scene, margin=None):
            c = PointReach.clearance(self, config, scene)
            flags = (c[..., 0] < 0).to(torch.uint8) + 2 * (c[..., 1] < 0).to(torch.uint8)
            return flags.unsqueeze(-1), self.achieved_goal(config)

    _refused(WrongClearance(), "clearance", "must be negative exactly where collision_flags sets the bit")


def test_step_that_disagrees_with_transition():
    class Slipping(PointReach):
        def step(self, state, action):
            out = super().step(state, action)
            out[0].set(self.config_key, out[0].get(self.config_key) * 0.5)
            return out

    _refused(Slipping(), "step", "transition\\(\\)'s")


def test_a_bound_too_small_for_the_motion_check():
    class TinyBound(PointReach):
        action_scale = 0.4  # steps long enough to jump over part of the rectangle between two samples

        def lipschitz(self):
            return {"obstacle": 1e-6, "workspace": 1e-6}

        def sample_tasks(self, n, generator=None):
            tasks = super().sample_tasks(n, generator)
            tasks["obstacle"] = torch.tensor([0.3, 0.31, 0.0, 1.0]).expand(n, 4).clone()  # a thin wall
            return tasks

    model = TinyBound()
    model.motion_resolution = 0.2
    _refused(model, "lipschitz", "passes through a collision")


def _counting_checks(monkeypatch) -> list:
    from torchrl_silp.models import check

    checked = []
    real = check.check_task_model
    monkeypatch.setattr(check, "check_task_model", lambda model: checked.append(model) or real(model))
    return checked


def test_a_model_is_checked_once_until_its_public_state_changes(monkeypatch):
    from torchrl_silp import ReachEnv
    from torchrl_silp.data import DemoReplayBuffer
    from torchrl_silp.models.check import ensure_checked

    checked = _counting_checks(monkeypatch)
    model = PointReach()
    ReachEnv(model, num_envs=2)
    ReachEnv(model, num_envs=3)
    DemoReplayBuffer(model, capacity=10)
    ensure_checked(model)
    assert checked == [model]  # the envs, the buffer and the call share the one check
    model.success_distance = 0.02
    ensure_checked(model)
    ensure_checked(model)
    assert checked == [model, model]
    # a broken change is refused, though the model passed before
    model.config_low = model.config_low.double()
    with pytest.raises(TaskModelError, match="config_low: must have the model's dtype"):
        ReachEnv(model, num_envs=2)


def test_no_check_is_shared_between_models(monkeypatch):
    from torchrl_silp.models.check import ensure_checked

    checked = _counting_checks(monkeypatch)
    first, second = PointReach(), PointReach()
    ensure_checked(first)
    ensure_checked(second)  # built alike, but another object: what it passed is its own
    ensure_checked(first)
    assert checked == [first, second]


def test_a_model_whose_state_cannot_be_summarised_is_checked_every_time(monkeypatch):
    from torchrl_silp.models.check import ensure_checked

    class Opaque:
        __slots__ = ()  # no attributes to summarise, and an address in its repr

    checked = _counting_checks(monkeypatch)
    model = PointReach()
    model.helper = Opaque()
    ensure_checked(model)
    ensure_checked(model)
    assert checked == [model, model]
