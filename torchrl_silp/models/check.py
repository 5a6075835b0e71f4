"""``check_task_model``: the task-model twin of TorchRL's ``check_env_specs``.

A task model is a contract between the user and every SILP+ component (env, planner,
demo buffer, loss, exploration). A model that breaks it fails far from the cause, or
not at all (a bool collision flag is silently read as "no collision" by a bit test).
:func:`check_task_model` exercises every member of :class:`~torchrl_silp.models.TaskModel`
on a small batch and raises one :class:`TaskModelError` naming the member and the rule.
"""

from __future__ import annotations

import copy
import hashlib
import math
import types

import numpy as np
import torch
from tensordict import TensorDictBase

from torchrl_silp.models.base import TaskModel

__all__ = ["check_task_model", "TaskModelError", "ensure_checked"]


class TaskModelError(ValueError):
    """A task model breaks a rule of the :class:`~torchrl_silp.models.TaskModel` interface."""


def _fail(model, member: str, rule: str) -> None:
    raise TaskModelError(f"{type(model).__name__}.{member}: {rule}")


def _check_tensor(model, member: str, value, shape: tuple, *, floating: bool = True) -> None:
    if not isinstance(value, torch.Tensor):
        _fail(model, member, f"must be a torch.Tensor of shape {shape}, got {type(value).__name__}")
    if tuple(value.shape) != tuple(shape):
        _fail(model, member, f"must have shape {tuple(shape)}, got {tuple(value.shape)}")
    if floating and value.dtype != model.dtype:
        _fail(model, member, f"must have the model's dtype {model.dtype}, got {value.dtype}")
    if value.device != model.device:
        _fail(model, member, f"must be on the model's device {model.device}, got {value.device}")


def _call(model, member: str, fn, *args):
    """``fn(*args)``; an exception it raises becomes a :class:`TaskModelError` naming the member."""
    try:
        return fn(*args)
    except TaskModelError:
        raise
    except Exception as error:  # noqa: BLE001 - reported with the member it came from
        raise TaskModelError(f"{type(model).__name__}.{member}: raised {type(error).__name__}: {error}") from error


def _positive_int(model, member: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        _fail(model, member, f"must be a positive int, got {value!r}")


def _tensors_of(obj, prefix: str, seen: set):
    """(attribute path, tensor) of every tensor an object holds in its attributes, lists, dicts and modules."""
    if id(obj) in seen:
        return
    seen.add(id(obj))
    if isinstance(obj, torch.Tensor):
        yield prefix, obj
    elif isinstance(obj, torch.nn.Module):
        for name, t in [*obj.named_parameters(recurse=True), *obj.named_buffers(recurse=True)]:
            yield f"{prefix}.{name}", t
        for name, value in vars(obj).items():
            if not name.startswith("_") and not isinstance(value, torch.nn.Module):
                yield from _tensors_of(value, f"{prefix}.{name}", seen)
    elif isinstance(obj, dict):
        for key, value in obj.items():
            yield from _tensors_of(value, f"{prefix}[{key!r}]", seen)
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            yield from _tensors_of(value, f"{prefix}[{i}]", seen)
    elif hasattr(obj, "__dict__") and not isinstance(obj, type) and type(obj).__module__.split(".")[0] not in (
        "torch", "builtins", "numpy"
    ):
        for name, value in vars(obj).items():
            yield from _tensors_of(value, f"{prefix}.{name}", seen)


def check_task_model(model: TaskModel, n: int = 32, seed: int = 0) -> None:
    """Exercise every member of a task model on ``n`` sampled tasks; raise :class:`TaskModelError` on a broken rule.

    Checks, in order: the base initialiser ran; the class constants (``config_dim``, ``goal_dim``,
    ``scene_shapes``, ``collision_reasons``, ``action_scale``); the joint limits (tensors of the
    model's dtype and device); ``lipschitz()`` (one finite positive bound per collision reason);
    ``sample_tasks`` (keys, shapes, dtypes, devices; starts and goals within the limits and free
    with the motion check's margin; achieved and desired goals those of the configurations);
    ``achieved_goal`` over any leading dims; ``collision_flags`` (uint8 flags ``(..., 1)`` with
    only the bits of ``collision_reasons``, a margin only adding flags) against ``clearance``
    (negative exactly where a reason's bit is set); ``relabel``; ``step`` equal to ``transition``
    then ``outcome`` (what :class:`~torchrl_silp.envs.ReachEnv` steps with); the motion check of
    random steps against a dense exact sampling of their segments (a step judged free never passes
    through a collision); and ``to(device)`` moving every tensor the model holds (checked on a copy
    moved to the ``meta`` device).

    Args:
        model: the task model.
        n: tasks to draw (and steps to try from them).
        seed: seed of the draws.

    Examples:
        >>> from torchrl_silp.models import UR5eReach, check_task_model
        >>> check_task_model(UR5eReach())
    """
    if not isinstance(model, TaskModel):
        raise TypeError(f"model must be a torchrl_silp.models.TaskModel, got {type(model).__name__}")
    for attribute in ("device", "dtype", "success_distance", "motion_resolution", "conservative"):
        if attribute not in vars(model):
            _fail(model, "__init__", f"TaskModel.__init__ did not run (no {attribute!r}): call super().__init__(...) "
                                     f"in {type(model).__name__}.__init__")
    # ------------------------------------------------------------- constants
    for member in ("config_dim", "goal_dim"):
        _positive_int(model, member, getattr(model, member, None))
    shapes = model.scene_shapes
    if not isinstance(shapes, dict) or not all(
        isinstance(k, str) and isinstance(v, tuple) and all(isinstance(d, int) and d > 0 for d in v)
        for k, v in shapes.items()
    ):
        _fail(model, "scene_shapes", f"must be a dict of key -> tuple of positive ints, got {shapes!r}")
    reasons = model.collision_reasons
    if (not isinstance(reasons, tuple) or not reasons or len(set(reasons)) != len(reasons)
            or not all(isinstance(r, str) for r in reasons)):
        _fail(model, "collision_reasons", f"must be a non-empty tuple of distinct names, got {reasons!r}")
    if len(reasons) > 8:
        _fail(model, "collision_reasons", f"at most 8 reasons fit the uint8 flags, got {len(reasons)}")
    scale = model.action_scale
    scale_value = scale if isinstance(scale, (int, float)) and not isinstance(scale, bool) else None
    if isinstance(scale, torch.Tensor):
        scale_value = float(scale.max()) if scale.numel() and bool((scale > 0).all()) else None
    if scale_value is None or not (math.isfinite(scale_value) and scale_value > 0):
        _fail(model, "action_scale", f"must be a positive finite number (joint step of one action unit), got {scale!r}")
    D, G = model.config_dim, model.goal_dim
    for member in ("config_low", "config_high"):
        _check_tensor(model, member, getattr(model, member, None), (D,))
    low, high = model.config_low, model.config_high
    if not bool(torch.isfinite(low).all() & torch.isfinite(high).all() & (low < high).all()):
        _fail(model, "config_low", "must be finite and below config_high on every joint")
    # ------------------------------------------------------------- lipschitz
    bounds = _call(model, "lipschitz", model.lipschitz)
    if not isinstance(bounds, dict) or set(bounds) != set(reasons):
        got = sorted(bounds) if isinstance(bounds, dict) else type(bounds).__name__
        _fail(model, "lipschitz", f"must return one bound per collision reason {sorted(reasons)}, got {got}")
    for reason, bound in bounds.items():
        if isinstance(bound, bool) or not isinstance(bound, (int, float)) or not (math.isfinite(bound) and bound > 0):
            _fail(model, "lipschitz", f"bound of {reason!r} must be a positive finite float (metres per radian), got {bound!r}")
    # ------------------------------------------------------------- tasks
    generator = torch.Generator(device=model.device).manual_seed(seed)
    tasks = _call(model, "sample_tasks", model.sample_tasks, n, generator)
    if not isinstance(tasks, TensorDictBase) or tuple(tasks.batch_size) != (n,):
        _fail(model, "sample_tasks", f"must return a TensorDict of batch size [{n}], got "
                                     f"{getattr(tasks, 'batch_size', type(tasks).__name__)}")
    wanted = {model.config_key: (n, D), model.achieved_goal_key: (n, G), model.desired_goal_key: (n, G),
              model.goal_config_key: (n, D), **{k: (n, *s) for k, s in shapes.items()}}
    for key, shape in wanted.items():
        if key not in tasks.keys():
            _fail(model, "sample_tasks", f"the tasks lack the key {key!r} (a task holds {sorted(wanted)})")
        _check_tensor(model, f"sample_tasks()[{key!r}]", tasks.get(key), shape)
    scene = tasks.select(*model.scene_keys)
    start, goal = tasks.get(model.config_key), tasks.get(model.goal_config_key)
    for name, q in (("start", start), ("goal", goal)):
        if not bool(((q >= low) & (q <= high)).all()):
            _fail(model, "sample_tasks", f"a {name} configuration lies outside [config_low, config_high]")
    # ------------------------------------------------------------- achieved goal
    achieved = _call(model, "achieved_goal", model.achieved_goal, start)
    _check_tensor(model, "achieved_goal", achieved, (n, G))
    two_dims = _call(model, "achieved_goal", model.achieved_goal, start.reshape(1, n, D))
    if tuple(two_dims.shape) != (1, n, G) or not torch.allclose(two_dims[0], achieved, atol=1e-6):
        _fail(model, "achieved_goal", "must map (..., config_dim) to (..., goal_dim) over any leading dims")
    atol = 1e-5 if model.dtype == torch.float32 else 1e-9
    if not torch.allclose(tasks.get(model.achieved_goal_key), achieved, atol=atol):
        _fail(model, "sample_tasks", "'achieved_goal' must be achieved_goal(joint_position)")
    if not torch.allclose(tasks.get(model.desired_goal_key), model.achieved_goal(goal), atol=atol):
        _fail(model, "sample_tasks", "'desired_goal' must be achieved_goal(goal_joint_position)")
    # ------------------------------------------------------------- collision flags
    flags, flag_goals = _call(model, "collision_flags", model.collision_flags, start, scene)
    if not isinstance(flags, torch.Tensor) or flags.dtype != torch.uint8:
        _fail(model, "collision_flags", "must return uint8 bit flags (bit k = collision_reasons[k]), got "
                                        f"{getattr(flags, 'dtype', type(flags).__name__)}")
    if tuple(flags.shape) != (n, 1):
        _fail(model, "collision_flags", f"flags must have shape (..., 1), got {tuple(flags.shape)} for {n} configurations")
    _check_tensor(model, "collision_flags (achieved goals)", flag_goals, (n, G))
    margin = _call(model, "motion_margin", model.motion_margin)
    for name, q in (("start", start), ("goal", goal)):
        if bool((_call(model, "collision_flags", model.collision_flags, q, scene, margin)[0] != 0).any()):
            _fail(model, "sample_tasks", f"a {name} configuration collides with the motion check's margin "
                                         f"{margin}: starts and goals must keep it, so that every motion out of them can be judged")
    # configurations spread over the joint box, near the tasks and anywhere: flags against clearance
    u = torch.rand(n, D, generator=generator, device=model.device, dtype=model.dtype)
    q = torch.cat([low + u * (high - low), start + 0.3 * (u - 0.5) * (high - low)]).clamp(low, high)
    qscene = torch.cat([scene, scene])
    flags, _ = _call(model, "collision_flags", model.collision_flags, q, qscene)
    if int(flags.max()) >= 2 ** len(reasons):
        _fail(model, "collision_flags", f"sets a bit beyond the {len(reasons)} collision_reasons")
    clearance = _call(model, "clearance", model.clearance, q, qscene)
    _check_tensor(model, "clearance", clearance, (2 * n, len(reasons)))
    bits = (flags.to(torch.int64) >> torch.arange(len(reasons), device=model.device)) & 1
    decided = clearance.abs() > 1e-5
    if bool(((bits == 1) != (clearance < 0))[decided].any()):
        row, col = (((bits == 1) != (clearance < 0)) & decided).nonzero()[0].tolist()
        _fail(model, "clearance", f"must be negative exactly where collision_flags sets the bit of {reasons[col]!r}; "
                                  f"configuration {row}: clearance {float(clearance[row, col]):.4g}, bit {int(bits[row, col])}")
    wide = {r: 0.05 for r in reasons}
    widened, _ = _call(model, "collision_flags", model.collision_flags, q, qscene, wide)
    if bool(((flags & ~widened) != 0).any()):
        _fail(model, "collision_flags", "a margin must only add collisions (a flag set without it stays set with it)")
    # ------------------------------------------------------------- relabel
    state = tasks.select(*model.state_keys)
    new_goal = model.achieved_goal(goal.flip(0))
    relabelled = _call(model, "relabel", model.relabel, state, new_goal)
    if not torch.equal(relabelled.get(model.desired_goal_key), new_goal.to(model.dtype)) or not torch.equal(
        relabelled.get(model.config_key), start
    ):
        _fail(model, "relabel", "must set the desired goal and keep the rest of the state")
    # ------------------------------------------------------------- step = transition, then outcome
    action = torch.rand(n, model.action_dim, generator=generator, device=model.device, dtype=model.dtype) * 2 - 1
    nxt, reward, collision, success, step_flags = _call(model, "step", model.step, state, action)
    moved = _call(model, "transition", model.transition, state, action)
    r2, c2, s2, f2 = _call(model, "outcome", model.outcome, state, moved)
    if not torch.allclose(nxt.get(model.config_key), moved.get(model.config_key), atol=atol):
        _fail(model, "step", "its next configuration must be transition()'s (ReachEnv steps with step, the planner with transition)")
    if not (torch.allclose(reward, r2, atol=atol) and torch.equal(collision, c2) and torch.equal(success, s2)
            and torch.equal(step_flags, f2)):
        _fail(model, "step", "its reward, collision, success and flags must be outcome(state, transition(state, action))'s")
    # ------------------------------------------------------------- the motion check against dense sampling
    to = moved.get(model.config_key)
    free = ~collision.squeeze(-1)
    # conservative=False is the paper's subdivision check, which may miss a graze between two samples by design
    if model.conservative and bool(free.any()):
        k = 16
        t = torch.linspace(0, 1, k * max(1, math.ceil(float((to - start).abs().amax()) / model.motion_resolution)) + 1,
                           dtype=model.dtype, device=model.device).view(-1, 1, 1)
        dense = start[free] + t * (to - start)[free]
        hit = model.collision_flags(dense, scene[free].unsqueeze(0).expand(dense.shape[0], int(free.sum())))[0] != 0
        if bool(hit.any()):
            _fail(model, "lipschitz", "a step judged free passes through a collision when its segment is sampled densely: "
                                      "a bound is too small, or collision_flags ignores its margin")
    # ------------------------------------------------------------- to(device)
    try:
        moved_model = copy.deepcopy(model).to("meta")
    except Exception as error:  # noqa: BLE001
        _fail(model, "to", f"moving a copy to the 'meta' device raised {type(error).__name__}: {error}")
    if moved_model is None:
        _fail(model, "to", "must return the model")
    stay = [path for path, t in _tensors_of(moved_model, "model", set()) if t.device.type != "meta"]
    if stay:
        _fail(model, "to", f"must move every tensor of the model; still on {model.device} after to('meta'): {stay[:4]}")


class _Opaque(Exception):
    """A value :func:`_fingerprint` cannot summarise."""


def _fingerprint(value, seen: frozenset = frozenset(), depth: int = 0):
    """A hashable summary of a value's content: numbers and strings as they are, tensors and arrays by their
    bytes, containers and objects by their public attributes. Raises :class:`_Opaque` where it cannot
    summarise (an object without attributes whose repr holds an address, a cycle, nesting deeper than 8)."""
    if value is None or isinstance(value, (bool, int, float, complex, str, bytes, torch.dtype, torch.device)):
        return value
    if isinstance(value, slice):
        return ("slice", value.start, value.stop, value.step)
    if id(value) in seen or depth > 8:
        raise _Opaque(type(value).__name__)
    inner = seen | {id(value)}
    if isinstance(value, torch.Tensor):
        value = value.detach()
        if value.device.type == "meta":
            return ("tensor", tuple(value.shape), value.dtype, "meta")
        data = value.to("cpu").contiguous().view(-1).view(torch.uint8).numpy().tobytes() if value.numel() else b""
        return ("tensor", tuple(value.shape), value.dtype, value.device.type, hashlib.sha1(data).hexdigest())
    if isinstance(value, np.ndarray):
        return ("array", value.shape, str(value.dtype), hashlib.sha1(np.ascontiguousarray(value).tobytes()).hexdigest())
    if isinstance(value, type):
        return ("class", value)
    if isinstance(value, (types.FunctionType, types.MethodType, types.BuiltinFunctionType)):
        return ("function", getattr(value, "__module__", None), getattr(value, "__qualname__", repr(value)))
    if isinstance(value, (list, tuple, set, frozenset)):
        items = [_fingerprint(v, inner, depth + 1) for v in value]
        if isinstance(value, (set, frozenset)):
            items = sorted(items, key=repr)
        return (type(value).__name__, *items)
    if isinstance(value, dict):
        return ("dict", *sorted(((repr(k), _fingerprint(v, inner, depth + 1)) for k, v in value.items()), key=repr))
    if isinstance(value, torch.nn.Module):
        state = {**dict(value.named_parameters()), **dict(value.named_buffers())}
        public = {k: v for k, v in vars(value).items() if not k.startswith("_") and k != "training"}
        return ("module", type(value), _fingerprint(state, inner, depth + 1), _fingerprint(public, inner, depth + 1))
    if hasattr(value, "__dict__"):
        public = {k: v for k, v in vars(value).items() if not k.startswith("_")}
        return ("object", type(value), _fingerprint(public, inner, depth + 1))
    text = repr(value)
    if " at 0x" in text:
        raise _Opaque(type(value).__name__)
    return ("repr", type(value), text)


def ensure_checked(model: TaskModel) -> None:
    """:func:`check_task_model` once per model and configuration: what :class:`~torchrl_silp.envs.ReachEnv`,
    :class:`~torchrl_silp.data.DemoReplayBuffer` and the recipes call on the model they are given.

    A model that passed keeps the configuration it passed with: its class and the content of its public
    attributes (numbers, strings, tensors by value, the robot's buffers, ...). It is not checked again
    while that content stays the same, and is checked again once its public state changes (a copy carries
    what its original passed with). Private attributes (``_name``) are taken to be caches of the public
    ones. A model whose state cannot be summarised is checked every time.

    Raises:
        TaskModelError: as :func:`check_task_model`.

    Examples:
        >>> from torchrl_silp.models import UR5eReach
        >>> from torchrl_silp.models.check import ensure_checked
        >>> model = UR5eReach()
        >>> ensure_checked(model)  # checked
        >>> ensure_checked(model)  # the same configuration: not checked again
        >>> model.success_distance = 0.02
        >>> ensure_checked(model)  # another configuration: checked
    """
    if not isinstance(model, TaskModel):
        raise TypeError(f"model must be a torchrl_silp.models.TaskModel, got {type(model).__name__}")
    try:
        key = (type(model), _fingerprint({k: v for k, v in vars(model).items() if not k.startswith("_")}))
    except _Opaque:
        key = None
    # kept on the model, not in a table of this module: the env, the demo buffer and the recipe share
    # one model object, and a table would outlive its models and be shared by every run in the process
    if key is not None and getattr(model, "_checked_configuration", None) == key:
        return
    check_task_model(model)
    if key is not None:
        model._checked_configuration = key
