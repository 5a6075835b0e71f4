"""Sphere covers fitted to collision meshes, with trimesh, cached on disk.

A cover holds every point of the mesh's surface, with no tolerance: the mesh is first
subdivided so that no edge is longer than a fraction of its size, each triangle is
assigned to one sphere, and a sphere's radius reaches the farthest vertex of its
triangles (a ball is convex, so it then holds those triangles whole). The triangles are
grouped by k-means on their centroids (area-weighted, farthest-point seeds, so the fit is
deterministic), and each sphere's centre is moved towards the centre of the smallest ball
around its vertices (Badoiu-Clarkson) before its radius is taken.

How many spheres: the fewest, up to ``max_spheres``, whose union's volume is at most
``volume_ratio`` times the mesh's (its enclosed volume if the mesh is watertight, else its
convex hull's), both measured by the same Monte Carlo count; else the ``max_spheres`` fit.
A surface cover of a closed mesh also bounds its solid in practice: the links' covers are
checked against the solid meshes by an exact engine in ``tests/test_urdf_arm.py``.

Fits are cached under ``$TORCHRL_SILP_CACHE/sphere_covers`` (default
``~/.cache/torchrl_silp``), keyed by a hash of the mesh's vertices and faces (after scaling)
and the fit's settings, so a mesh edited on disk is fitted again.

Examples:
    >>> import trimesh
    >>> from torchrl_silp.robots.covers import mesh_sphere_cover
    >>> rod = trimesh.creation.cylinder(radius=0.05, height=0.6)
    >>> centres, radii = mesh_sphere_cover(rod, max_spheres=8, volume_ratio=2.5)
    >>> 1 < len(radii) <= 8
    True
    >>> points = rod.sample(2000, seed=0)
    >>> gap = np.linalg.norm(points[:, None] - centres[None], axis=-1) - radii
    >>> bool((gap.min(1) <= 1e-9).all())
    True
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["mesh_sphere_cover", "cached_mesh_cover", "cover_volume", "cache_dir", "CoverReport"]

#: bumped whenever the fit changes, so stale cache entries are not read
FIT_VERSION = 1
_MC_POINTS = 40_000


def cache_dir() -> Path:
    """Where fitted covers are kept: ``$TORCHRL_SILP_CACHE/sphere_covers``, default ``~/.cache/torchrl_silp/...``."""
    base = os.environ.get("TORCHRL_SILP_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "torchrl_silp")
    return Path(base) / "sphere_covers"


def _farthest_point_seeds(points: np.ndarray, k: int) -> np.ndarray:
    seeds = [int(np.argmax(np.linalg.norm(points - points.mean(0), axis=1)))]
    dist = np.linalg.norm(points - points[seeds[0]], axis=1)
    for _ in range(1, k):
        seeds.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[seeds[-1]], axis=1))
    return points[seeds].copy()


def _kmeans(points: np.ndarray, weights: np.ndarray, k: int, iters: int = 30) -> np.ndarray:
    centres = _farthest_point_seeds(points, k)
    labels = np.zeros(len(points), dtype=np.int64)
    for _ in range(iters):
        d = ((points[:, None, :] - centres[None]) ** 2).sum(-1)
        labels = d.argmin(1)
        w = np.bincount(labels, weights=weights, minlength=k)
        moved = np.stack([np.bincount(labels, weights=weights * points[:, i], minlength=k) for i in range(3)], 1)
        alive = w > 0
        new = centres.copy()
        new[alive] = moved[alive] / w[alive, None]
        if np.allclose(new, centres, atol=1e-9):
            break
        centres = new
    return labels


def _enclosing_centre(points: np.ndarray, iters: int = 100) -> np.ndarray:
    # Badoiu-Clarkson: step towards the farthest point by 1/(i+1); converges to the minimal ball's centre
    c = (points.min(0) + points.max(0)) / 2
    for i in range(iters):
        far = points[np.argmax(((points - c) ** 2).sum(1))]
        c = c + (far - c) / (i + 2)
    return c


def _fit(vertices: np.ndarray, faces: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    tri = vertices[faces]  # (F, 3, 3)
    centroid = tri.mean(1)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) + 1e-12
    k = min(k, len(faces))
    labels = _kmeans(centroid, area, k) if k > 1 else np.zeros(len(faces), dtype=np.int64)
    centres, radii = [], []
    for c in range(k):
        mine = labels == c
        if not mine.any():
            continue
        pts = np.unique(tri[mine].reshape(-1, 3), axis=0)
        centre = _enclosing_centre(pts)
        centres.append(centre)
        radii.append(float(np.sqrt(((pts - centre) ** 2).sum(1).max())))
    return np.asarray(centres), np.asarray(radii)


def cover_volume(centres: np.ndarray, radii: np.ndarray, n: int = _MC_POINTS, seed: int = 0) -> float:
    """The volume (m^3) of the union of balls, by a Monte Carlo count in their bounding box."""
    lo, hi = (centres - radii[:, None]).min(0), (centres + radii[:, None]).max(0)
    pts = lo + np.random.default_rng(seed).random((n, 3)) * (hi - lo)
    inside = (((pts[:, None] - centres[None]) ** 2).sum(-1) <= radii**2).any(1)
    return float(inside.mean() * np.prod(hi - lo))


def mesh_volume(mesh) -> float:
    """The mesh's enclosed volume if it is watertight, else its convex hull's (m^3)."""
    return float(abs(mesh.volume)) if mesh.is_watertight else float(mesh.convex_hull.volume)


def mesh_sphere_cover(mesh, max_spheres: int = 8, volume_ratio: float = 2.5) -> tuple[np.ndarray, np.ndarray]:
    """Fit a sphere cover to a ``trimesh.Trimesh`` (see the module docstring); not cached.

    Args:
        mesh: the mesh, in the frame the centres are returned in.
        max_spheres: the most spheres the cover may hold (>= 1).
        volume_ratio: stop at the fewest spheres whose union is at most this many times the mesh's volume.

    Returns:
        centres ``(n, 3)`` and radii ``(n,)``, float64 numpy, ``n <= max_spheres``.
    """
    import trimesh

    if isinstance(max_spheres, bool) or not isinstance(max_spheres, int) or max_spheres < 1:
        raise ValueError(f"max_spheres must be a positive int, got {max_spheres!r}")
    if not volume_ratio > 1:
        raise ValueError(f"volume_ratio must be > 1, got {volume_ratio!r}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    # small triangles, so that each lies near the centre of the sphere it is assigned to
    max_edge = float(np.linalg.norm(np.ptp(vertices, axis=0))) / (4 * max_spheres)
    if max_edge > 0:
        vertices, faces = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=max_edge, max_iter=12)
    target = volume_ratio * mesh_volume(mesh)
    best = None
    for k in range(1, max_spheres + 1):
        best = _fit(vertices, faces, k)
        if cover_volume(*best) <= target:
            break
    return best


def _key(mesh, max_spheres: int, volume_ratio: float) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    h.update(f"v{FIT_VERSION}:{max_spheres}:{volume_ratio!r}".encode())
    return h.hexdigest()[:32]


def cached_mesh_cover(mesh, max_spheres: int = 8, volume_ratio: float = 2.5) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mesh_sphere_cover`, read from the disk cache when this mesh and these settings were fitted before."""
    path = cache_dir() / f"{_key(mesh, max_spheres, volume_ratio)}.npz"
    if path.is_file():
        with np.load(path) as saved:
            return saved["centres"], saved["radii"]
    centres, radii = mesh_sphere_cover(mesh, max_spheres, volume_ratio)
    path.parent.mkdir(parents=True, exist_ok=True)
    # written whole, then renamed: runs fitting the same mesh at once never read half a file
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz")
    with os.fdopen(fd, "wb") as fh:
        np.savez(fh, centres=centres, radii=radii)
    os.replace(tmp, path)
    return centres, radii


@dataclass(frozen=True)
class CoverReport:
    """How a link's cover sits on its collision geometry (:meth:`ArmKinematics.cover_report`)."""

    link: str
    spheres: int
    cover_volume: float   # m^3, the union of the link's spheres
    geometry_volume: float  # m^3, the union of the link's collision solids (convex hulls of open meshes)

    @property
    def ratio(self) -> float:
        return self.cover_volume / self.geometry_volume if self.geometry_volume > 0 else float("inf")
