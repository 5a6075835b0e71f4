"""Self-collision link pairs found by sampling, the way MoveIt's setup assistant builds its allowed-collision matrix.

Every pair of links with collision geometry starts checked; a pair is dropped, for the
first of these reasons that holds (the names MoveIt's SRDF gives them in
``<disable_collisions reason>``):

- ``rigid``: no moving joint lies between the two links (they never move apart);
- ``adjacent``: a joint connects them, links without geometry in between collapsed;
- ``default``: their collision geometry touches at the home configuration (a
  collision-free pose of the real arm);
- ``always``: it touches in at least ``always_fraction`` of the sampled configurations
  (uniform over the joint limits);
- ``never``: it touches in none of them.

As in MoveIt, contact is judged on the URDF's own collision geometry (meshes and
primitives, by FCL through ``python-fcl``), not on the sphere covers: covers are
conservative, and a pair whose covers overlap although its meshes never touch (a flat
base under the upper arm's housing) would otherwise block every configuration. Only the
configurations where a pair's covers overlap are tested exactly (a cover holds its
geometry, so elsewhere the geometry cannot touch). The kept pairs are then checked on the
covers by the arm's self test.

Examples:
    >>> from torchrl_silp.robots import UR5e
    >>> from torchrl_silp.robots.self_collision import find_self_collision_pairs
    >>> acm = find_self_collision_pairs(UR5e(), samples=2000)
    >>> ("base_link", "shoulder_link") in acm.dropped["adjacent"]
    True
    >>> sorted(acm.dropped) == sorted(acm.REASONS)
    True
"""

from __future__ import annotations

import copy
import itertools
from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = ["SelfCollisionMatrix", "find_self_collision_pairs", "link_collision_objects"]


@dataclass
class SelfCollisionMatrix:
    """The link pairs a self-collision test checks, and those it drops with their reasons.

    Attributes:
        kept: link pairs ``(a, b)`` checked, ``a`` before ``b`` in the arm's frame order.
        dropped: reason -> link pairs (see the module docstring for the reasons).
        contact_fraction: link pair -> share of the sampled configurations where its geometry touches.
        samples: configurations sampled.
    """

    REASONS = ("rigid", "adjacent", "default", "always", "never")
    kept: list[tuple[str, str]] = field(default_factory=list)
    dropped: dict[str, list[tuple[str, str]]] = field(default_factory=dict)
    contact_fraction: dict[tuple[str, str], float] = field(default_factory=dict)
    samples: int = 0

    def summary(self) -> str:
        """One line: pairs kept and dropped per reason."""
        parts = ", ".join(f"{len(self.dropped.get(r, []))} {r}" for r in self.REASONS)
        return f"{len(self.kept)} link pairs checked; dropped: {parts}"


def _adjacent_pairs(arm, links: list[str]) -> set[frozenset]:
    parent = {j.child: j.parent for j in arm.description.joints}
    with_geometry = set(links)
    pairs = set()
    for link in links:
        up = parent.get(link)
        while up is not None and up not in with_geometry:
            up = parent.get(up)
        if up is not None:
            pairs.add(frozenset((link, up)))
    return pairs


def _link_overlaps(arm, q: torch.Tensor, links: list[str], pairs: list[tuple[str, str]]) -> torch.Tensor:
    """Bool ``(N, P)``: whether the covers of each link pair overlap at each configuration (float64)."""
    centres, _ = arm.spheres_and_tcp(q)
    r = arm.sphere_radii.double()
    names = np.asarray(arm.sphere_link_names)
    out = []
    for a, b in pairs:
        ia = torch.as_tensor(np.flatnonzero(names == a), device=q.device)
        ib = torch.as_tensor(np.flatnonzero(names == b), device=q.device)
        d = torch.cdist(centres[:, ia].double(), centres[:, ib].double())
        out.append((d < r[ia, None] + r[None, ib]).flatten(1).any(-1))
    return torch.stack(out, -1) if out else torch.zeros(q.shape[0], 0, dtype=torch.bool, device=q.device)


def link_collision_objects(arm) -> dict:
    """One ``fcl.CollisionObject`` per link with collision geometry: its elements' meshes in the link frame, as one BVH."""
    import fcl
    import trimesh

    out = {}
    for link in dict.fromkeys(arm.sphere_link_names):
        meshes = [p.trimesh() for p in arm.primitives if p.link == link]
        mesh = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
        bvh = fcl.BVHModel()
        bvh.beginModel(len(mesh.vertices), len(mesh.faces))
        bvh.addSubModel(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32))
        bvh.endModel()
        out[link] = fcl.CollisionObject(bvh, fcl.Transform())
    return out


def _exact_contacts(arm64, q: torch.Tensor, pairs, cover_overlap: torch.Tensor, objects: dict) -> torch.Tensor:
    """Bool ``(N, P)``: whether each pair's collision geometry touches, tested where its covers overlap."""
    import fcl

    out = torch.zeros_like(cover_overlap)
    rows, cols = cover_overlap.nonzero(as_tuple=True)
    if rows.numel() == 0:
        return out
    rot, pos = arm64.frames(q)
    index = {n: i for i, n in enumerate(arm64.frame_names)}
    request = fcl.CollisionRequest()
    rot, pos = rot.numpy(), pos.numpy()
    for n, p in zip(rows.tolist(), cols.tolist()):  # construction time only: a few thousand FCL calls
        a, b = pairs[p]
        for link in (a, b):
            objects[link].setTransform(fcl.Transform(rot[n, index[link]], pos[n, index[link]]))
        out[n, p] = fcl.collide(objects[a], objects[b], request, fcl.CollisionResult()) > 0
    return out


def find_self_collision_pairs(arm, *, home=None, samples: int = 10_000, always_fraction: float = 0.95,
                              seed: int = 0, chunk: int = 2048) -> SelfCollisionMatrix:
    """Sort the arm's link pairs into kept and dropped (see the module docstring).

    Args:
        arm: an :class:`~torchrl_silp.robots.base.ArmKinematics`.
        home: the home configuration ``(D,)``; default the arm's ``HOME``, else every joint at 0
            clipped into its limits.
        samples: configurations drawn uniformly over the joint limits.
        always_fraction: a pair overlapping in at least this share of the samples is ``always``.
        seed: of the sampling.
        chunk: configurations evaluated at once.
    """
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples must be a positive int, got {samples!r}")
    if not 0 < always_fraction <= 1:
        raise ValueError(f"always_fraction must be in (0, 1], got {always_fraction!r}")
    order = {n: i for i, n in enumerate(arm.frame_names)}
    links = sorted(set(arm.sphere_link_names), key=order.__getitem__)
    body = dict(zip(arm.frame_names, arm.frame_body))
    adjacent = _adjacent_pairs(arm, links)
    low, high = arm.joint_low.double().cpu(), arm.joint_high.double().cpu()
    if home is None:
        home = arm.HOME if arm.HOME is not None else torch.zeros_like(low).clamp(low, high)
    home = torch.as_tensor(home, dtype=torch.float64).reshape(1, -1)

    acm = SelfCollisionMatrix(dropped={r: [] for r in SelfCollisionMatrix.REASONS}, samples=samples)
    candidates = []
    for a, b in itertools.combinations(links, 2):
        if body[a] == body[b]:
            acm.dropped["rigid"].append((a, b))
        elif frozenset((a, b)) in adjacent:
            acm.dropped["adjacent"].append((a, b))
        else:
            candidates.append((a, b))
    arm64 = arm
    if arm.dtype != torch.float64 or arm.device.type != "cpu":
        # the overlaps are judged in float64 on the CPU, on a copy: the arm itself is left as it is
        arm64 = copy.deepcopy(arm).to(device="cpu", dtype=torch.float64)
    objects = link_collision_objects(arm64)
    at_home = _exact_contacts(arm64, home, candidates, _link_overlaps(arm64, home, links, candidates), objects)[0]
    gen = torch.Generator().manual_seed(seed)
    counts = torch.zeros(len(candidates), dtype=torch.long)
    for start in range(0, samples, chunk):
        n = min(chunk, samples - start)
        q = low + torch.rand(n, low.numel(), generator=gen, dtype=torch.float64) * (high - low)
        overlap = _link_overlaps(arm64, q, links, candidates)
        counts += _exact_contacts(arm64, q, candidates, overlap, objects).sum(0)
    for k, pair in enumerate(candidates):
        frac = float(counts[k]) / samples
        acm.contact_fraction[pair] = frac
        if at_home[k]:
            acm.dropped["default"].append(pair)
        elif frac >= always_fraction:
            acm.dropped["always"].append(pair)
        elif frac == 0:
            acm.dropped["never"].append(pair)
        else:
            acm.kept.append(pair)
    return acm
