"""An arm's sphere cover judged against an exact collision engine on its own collision geometry.

:func:`exact_collision_check` draws configurations over the joint limits and, for each,
boxes near the arm (centred on a random point of a random link's cover, sides of 1 to 30
cm), then asks FCL (``python-fcl``: the link's meshes or primitives as a BVH against an
exact box) and the cover (the link's spheres against the box's AABB, the test the task
models run) whether each link touches each box; and the same for every self-collision
pair the arm checks. A contact FCL finds and the cover misses is a *missed* contact (the
cover must have none); a cover contact FCL does not confirm is a *false alarm* (the price
of a conservative cover).

Examples:
    >>> from torchrl_silp.robots import UR5e
    >>> from torchrl_silp.robots.exact_check import exact_collision_check
    >>> report = exact_collision_check(UR5e(), configs=50, boxes_per_config=2, seed=0)
    >>> report["box"]["missed"], report["self"]["missed"]
    (0, 0)
"""

from __future__ import annotations

import numpy as np
import torch

from torchrl_silp.robots.self_collision import link_collision_objects

__all__ = ["exact_collision_check"]


def _rates(exact: np.ndarray, cover: np.ndarray) -> dict:
    contacts, flagged = int(exact.sum()), int(cover.sum())
    false_alarms = int((cover & ~exact).sum())
    return {
        "tests": int(exact.size),
        "contacts": contacts,
        "cover_contacts": flagged,
        "missed": int((exact & ~cover).sum()),
        "false_alarms": false_alarms,
        # of the cover's contacts, the share FCL does not confirm
        "false_alarm_rate": false_alarms / flagged if flagged else 0.0,
    }


def exact_collision_check(arm, *, configs: int = 2000, boxes_per_config: int = 4, seed: int = 0) -> dict:
    """Compare the cover with FCL on link-box and self contacts (see the module docstring).

    Args:
        arm: an :class:`~torchrl_silp.robots.base.ArmKinematics` (judged in float64 on the CPU, on a copy).
        configs: configurations drawn uniformly over the joint limits.
        boxes_per_config: boxes drawn near the arm at each.
        seed: of every draw.

    Returns:
        ``{"box": rates, "self": rates, "configs": n, "boxes_per_config": k}``, each ``rates`` a dict of
        ``tests`` (link-box or link-pair tests), ``contacts`` (FCL's), ``cover_contacts``, ``missed``,
        ``false_alarms`` and ``false_alarm_rate``.
    """
    import copy

    import fcl

    arm64 = copy.deepcopy(arm).to(device="cpu", dtype=torch.float64)
    rng = np.random.default_rng(seed)
    low, high = arm64.joint_low.numpy(), arm64.joint_high.numpy()
    q = torch.as_tensor(low + rng.random((configs, low.size)) * (high - low))
    rot, pos = arm64.frames(q)
    rot, pos = rot.numpy(), pos.numpy()
    centres = arm64.spheres_and_tcp(q)[0].numpy()  # (N, S, 3)
    radii = arm64.sphere_radii.numpy()
    names = np.asarray(arm64.sphere_link_names)
    links = list(dict.fromkeys(arm64.sphere_link_names))
    index = {n: i for i, n in enumerate(arm64.frame_names)}
    objects = link_collision_objects(arm64)
    request = fcl.CollisionRequest()

    def place(n: int, link: str):
        f = index[link]
        objects[link].setTransform(fcl.Transform(rot[n, f], pos[n, f]))

    # boxes: centred on a random sphere centre, moved by up to its radius plus 10 cm, sides 1-30 cm
    s = rng.integers(0, radii.size, (configs, boxes_per_config))
    offset = rng.uniform(-1, 1, (configs, boxes_per_config, 3)) * (radii[s][..., None] + 0.1)
    box_centre = np.take_along_axis(centres, s[..., None].repeat(3, -1), 1) + offset
    box_size = rng.uniform(0.01, 0.3, (configs, boxes_per_config, 3))
    exact_box = np.zeros((configs, boxes_per_config, len(links)), dtype=bool)
    cover_box = np.zeros_like(exact_box)
    for n in range(configs):  # a Python loop over FCL calls: this is a check, not a hot path
        for link in links:
            place(n, link)
        for b in range(boxes_per_config):
            lo, hi = box_centre[n, b] - box_size[n, b] / 2, box_centre[n, b] + box_size[n, b] / 2
            box = fcl.CollisionObject(fcl.Box(*box_size[n, b]), fcl.Transform(box_centre[n, b]))
            gap = np.linalg.norm(np.maximum(lo - centres[n], 0) + np.maximum(centres[n] - hi, 0), axis=-1)
            hit = gap < radii
            for k, link in enumerate(links):
                exact_box[n, b, k] = fcl.collide(objects[link], box, request, fcl.CollisionResult()) > 0
                cover_box[n, b, k] = bool(hit[names == link].any())

    a, b = arm64.self_pair_a.numpy(), arm64.self_pair_b.numpy()
    pairs = sorted({(names[i], names[j]) for i, j in zip(a, b)}, key=lambda p: (links.index(p[0]), links.index(p[1])))
    exact_self = np.zeros((configs, len(pairs)), dtype=bool)
    cover_self = np.zeros_like(exact_self)
    for k, (x, y) in enumerate(pairs):
        ix, iy = np.flatnonzero(names == x), np.flatnonzero(names == y)
        d = np.linalg.norm(centres[:, ix, None] - centres[:, None, iy], axis=-1)
        cover_self[:, k] = (d < radii[ix, None] + radii[None, iy]).reshape(configs, -1).any(-1)
    for n in range(configs):
        for link in links:
            place(n, link)
        for k, (x, y) in enumerate(pairs):
            exact_self[n, k] = fcl.collide(objects[x], objects[y], request, fcl.CollisionResult()) > 0
    return {"box": _rates(exact_box, cover_box), "self": _rates(exact_self, cover_self),
            "configs": configs, "boxes_per_config": boxes_per_config}
