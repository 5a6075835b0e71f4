"""The learned collision model of the paper's appendix B, and the planner edge check that asks it.

The paper's model M "predicts the collision probability given the robot's joints
configuration and obstacle's information" with "three hidden layers (512, 256 and 64
nodes each)", trained on 485k labelled configurations (90 % train, 10 % test). Here
the labels come from the task model's exact checker or from any other labeller (the
MuJoCo twin's contacts, :func:`torchrl_silp.sim.mujoco_labels`).
"""

from __future__ import annotations

import copy
import math

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.modules import MLP

from torchrl_silp.models.base import TaskModel, as_model
from torchrl_silp.validation import check_positive_int, check_probability

__all__ = ["CollisionNet", "collision_dataset", "train_collision_net", "classification_metrics", "roc_curve",
           "LearnedEdgeCheck", "with_learned_edges", "load_collision_net"]


class CollisionNet(nn.Module):
    """Collision logit of a configuration in a scene: an MLP over ``[config, scene...]``, standardised inputs.

    Args:
        in_features: the configuration's and the scene's flat sizes together.
        hidden_sizes: the paper's (512, 256, 64) by default.
        mean, std: the inputs' standardisation (from the training set), ``[in_features]``.
    """

    def __init__(self, in_features: int, hidden_sizes=(512, 256, 64), mean: torch.Tensor | None = None,
                 std: torch.Tensor | None = None):
        super().__init__()
        self.in_features = check_positive_int(in_features, name="in_features")
        self.hidden_sizes = tuple(int(h) for h in hidden_sizes)
        self.mlp = MLP(in_features=in_features, out_features=1, num_cells=list(self.hidden_sizes),
                       activation_class=nn.ReLU)
        self.register_buffer("mean", torch.zeros(in_features) if mean is None else mean.float().clone())
        self.register_buffer("std", torch.ones(in_features) if std is None else std.float().clamp(min=1e-6).clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits ``[...]`` of inputs ``[..., in_features]``."""
        return self.mlp((x - self.mean) / self.std).squeeze(-1)


def _features(model: TaskModel, config: torch.Tensor, scene: TensorDictBase) -> torch.Tensor:
    parts = [config] + [scene.get(k).reshape(*config.shape[:-1], -1).to(config.dtype) for k in model.scene_keys]
    return torch.cat(parts, -1)


def collision_dataset(model, n: int, generator: torch.Generator | None = None, labeller=None, n_scenes: int = 4096):
    """``(inputs [n, F], labels [n] bool, config [n, D], scene [n])``: configurations drawn uniformly in the
    box the model draws its tasks from (``TASK_JOINT_LOW`` / ``TASK_JOINT_HIGH``; its joint limits if it has
    none), each in one of ``n_scenes`` scenes of its task distribution, labelled by ``labeller(config, scene)``
    (the model's exact :meth:`~torchrl_silp.models.TaskModel.collides` by default: every collision reason)."""
    model = as_model(model)
    check_positive_int(n, name="n")
    check_positive_int(n_scenes, name="n_scenes")
    low = torch.as_tensor(getattr(model, "TASK_JOINT_LOW", model.config_low), dtype=model.dtype)
    high = torch.as_tensor(getattr(model, "TASK_JOINT_HIGH", model.config_high), dtype=model.dtype)
    u = torch.rand(n, low.shape[-1], generator=generator, dtype=low.dtype)
    config = low + u * (high - low)
    scenes = model.sample_tasks(min(n, n_scenes), generator).select(*model.scene_keys)
    scene = scenes[torch.randint(len(scenes), (n,), generator=generator)]
    labels = (model.collides if labeller is None else labeller)(config, scene)
    return _features(model, config, scene), labels.bool(), config, scene


def classification_metrics(prob: torch.Tensor, labels: torch.Tensor, threshold: float = 0.5) -> dict:
    """Accuracy, recall, precision and specificity at ``threshold`` (collision is the positive class)."""
    pred, y = prob > threshold, labels.bool()
    tp, tn = (pred & y).sum().item(), (~pred & ~y).sum().item()
    fp, fn = (pred & ~y).sum().item(), (~pred & y).sum().item()
    ratio = lambda a, b: a / b if b else float("nan")  # noqa: E731
    return {"accuracy": ratio(tp + tn, len(y)), "recall": ratio(tp, tp + fn), "precision": ratio(tp, tp + fp),
            "specificity": ratio(tn, tn + fp), "positives": int(y.sum()), "n": len(y), "threshold": threshold}


def roc_curve(prob: torch.Tensor, labels: torch.Tensor, points: int = 101) -> dict:
    """The ROC curve at ``points`` thresholds evenly spaced in [0, 1] and its area (trapezoids over all thresholds)."""
    y = labels.bool()
    thresholds = torch.linspace(0, 1, points, dtype=prob.dtype)
    pos, neg = max(int(y.sum()), 1), max(int((~y).sum()), 1)
    above = prob.unsqueeze(0) >= thresholds.unsqueeze(1)  # [T, n]
    tpr = (above & y).sum(1).double() / pos
    fpr = (above & ~y).sum(1).double() / neg
    # the exact area: the probability that a random positive outranks a random negative (ties count half)
    order = torch.argsort(prob)
    ranks = torch.empty_like(order, dtype=torch.float64)
    sorted_prob = prob[order]
    _, inverse, counts = torch.unique_consecutive(sorted_prob, return_inverse=True, return_counts=True)
    ends = torch.cumsum(counts, 0).double()
    mid = ends - (counts.double() - 1) / 2  # average 1-based rank of each tie group
    ranks[order] = mid[inverse]
    auc = (ranks[y].sum().item() - pos * (pos + 1) / 2) / (pos * neg)
    return {"thresholds": thresholds.tolist(), "tpr": tpr.tolist(), "fpr": fpr.tolist(), "auc": auc}


def train_collision_net(inputs: torch.Tensor, labels: torch.Tensor, *, epochs: int = 20, batch_size: int = 1024,
                        lr: float = 1e-3, test_fraction: float = 0.1, seed: int = 0, hidden_sizes=(512, 256, 64),
                        log=None) -> tuple[CollisionNet, dict]:
    """Train a :class:`CollisionNet` on ``(1 - test_fraction)`` of the data (Adam, binary cross-entropy) and
    evaluate it on the rest: ``(net, {"metrics", "roc", "train_n", "test_n", "epochs"})``."""
    check_probability(test_fraction, name="test_fraction")
    check_positive_int(epochs, name="epochs")
    check_positive_int(batch_size, name="batch_size")
    gen = torch.Generator().manual_seed(seed)
    n = len(labels)
    perm = torch.randperm(n, generator=gen)
    n_test = max(1, int(round(test_fraction * n)))
    test, train = perm[:n_test], perm[n_test:]
    x, y = inputs.float(), labels.float()
    torch.manual_seed(seed)
    net = CollisionNet(x.shape[-1], hidden_sizes, mean=x[train].mean(0), std=x[train].std(0))
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * math.ceil(len(train) / batch_size))
    for epoch in range(epochs):
        order = train[torch.randperm(len(train), generator=gen)]
        total = 0.0
        for lo in range(0, len(order), batch_size):
            idx = order[lo: lo + batch_size]
            loss = nn.functional.binary_cross_entropy_with_logits(net(x[idx]), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(idx)
        if log is not None:
            log(f"epoch {epoch + 1}/{epochs}: train loss {total / len(train):.4f}")
    with torch.no_grad():
        prob = torch.sigmoid(net(x[test]))
    return net, {"metrics": classification_metrics(prob, labels[test]), "roc": roc_curve(prob, labels[test]),
                 "train_n": len(train), "test_n": n_test, "epochs": epochs}


class LearnedEdgeCheck:
    """A task model's planner edge check (:attr:`~torchrl_silp.models.TaskModel.edge_check`) by a
    :class:`CollisionNet`: a sampled configuration collides where the net's probability exceeds ``threshold``.

    The net stands in for the exact test and its Lipschitz margin (``margin`` is not read); the sampling
    along segments stays the model's, as in the paper's planner.

    Args:
        net: the collision model, over ``[config, scene...]`` (the model's scene keys, flattened).
        threshold: the collision probability above which a configuration collides, in (0, 1).

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> check = LearnedEdgeCheck(CollisionNet(3 + 6), threshold=0.5)
        >>> task = model.sample_tasks(4, torch.Generator().manual_seed(0))
        >>> check(model, task["joint_position"], task.select("obstacle"), margin={}).shape
        torch.Size([4])
    """

    def __init__(self, net: CollisionNet, threshold: float = 0.5):
        if not isinstance(net, CollisionNet):
            raise TypeError(f"net must be a CollisionNet, got {type(net).__name__}")
        self.net = net
        self.threshold = check_probability(threshold, name="threshold")

    def to(self, device) -> "LearnedEdgeCheck":
        """Move the net to ``device`` (the task model's ``to`` calls it); returns the check."""
        self.net.to(device)
        return self

    def __call__(self, model: TaskModel, config: torch.Tensor, scene: TensorDictBase, margin) -> torch.Tensor:
        with torch.no_grad():
            prob = torch.sigmoid(self.net(_features(model, config, scene).float()))
        return prob > self.threshold


def with_learned_edges(model, net: CollisionNet, threshold: float = 0.5) -> TaskModel:
    """A shallow copy of the task model whose planner edge check (``segment_collision_free``) asks ``net``
    at ``threshold`` (:class:`LearnedEdgeCheck`), as the paper's planner does; the env's own step, the
    rewards and the demonstrations' checks stay exact. ``model`` itself is left as it is.

    Examples:
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> learned = with_learned_edges(model, CollisionNet(3 + 6))
        >>> type(learned) is UR5eReach, learned.edge_check.threshold, model.edge_check
        (True, 0.5, None)
    """
    model = as_model(model)
    check = LearnedEdgeCheck(net, threshold)
    out = copy.copy(model)
    out.edge_check = check
    return out


def load_collision_net(path) -> CollisionNet:
    """A :class:`CollisionNet` saved by ``recipes/collision_net.py`` (its state dict and sizes)."""
    saved = torch.load(path, map_location="cpu", weights_only=True)
    net = CollisionNet(int(saved["in_features"]), tuple(saved["hidden_sizes"]))
    net.load_state_dict(saved["state_dict"])
    return net.eval()
