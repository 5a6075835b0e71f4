"""Matplotlib pictures of the reach task: the arm's collision geometry, the table,
the obstacle, the goal and TCP paths.

Every figure here is built on matplotlib's Agg canvas directly
(:class:`~matplotlib.backends.backend_agg.FigureCanvasAgg`), never through
``pyplot``: no window opens, nothing depends on the global backend, and
figures are freed with their last reference instead of piling up in pyplot's
registry when a training loop renders every episode.

The arm is drawn from the same collision primitives the env checks
(``robot.primitives`` placed by ``robot.frames``), so a picture shows exactly
the solid that counts for collisions, not a visual mesh.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import matplotlib.patches
import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d import Axes3D
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from torchrl_silp.models.base import TaskModel
from torchrl_silp.models.ur5e import UR5eReach
from torchrl_silp.robots.base import ArmKinematics

__all__ = ["draw_scene", "render_rgb", "save_rollout_png", "save_task_rollout_png", "arm_polygons", "save_cover_png"]

# Scene box drawn by default: the TCP workspace of the task plus the arm's
# base, so that panels of different episodes share one scale.
_SCENE_LOW = np.array([-0.4, -0.5, 0.0])
_SCENE_HIGH = np.array([1.0, 0.9, 1.0])
_CYLINDER_SEGMENTS = 16
_LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
_ARM_COLOURS = ("#8fa9c2", "#5f7f9f")  # alternating by link so neighbouring links read apart
_GRIPPER_COLOUR = "#3c3c3c"
_OBSTACLE_COLOUR = (0.85, 0.25, 0.2, 0.45)
_OBSTACLE_EDGE = (0.55, 0.1, 0.08, 0.9)
_TABLE_COLOUR = (0.82, 0.76, 0.66, 0.55)
_DEFAULT_VIEW = (22.0, -40.0)  # elevation, azimuth (degrees): from the front right, a little above


# ------------------------------------------------------------------ inputs
def _vector(value, length: int | None, name: str, rows: bool = False) -> np.ndarray:
    """``value`` as a float64 array of shape ``(length,)`` (any 1-D length when None; ``(T, 3)`` when ``rows``)."""
    if isinstance(value, torch.Tensor):
        value = value.detach().to("cpu", torch.float64).numpy()
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name} must be an array of numbers, got {type(value).__name__}") from err
    if rows:
        if arr.ndim != 2 or arr.shape[-1] != 3 or arr.shape[0] < 1:
            raise ValueError(f"{name} must have shape (T, 3) with T >= 1, got {arr.shape}")
    elif arr.ndim != 1 or (length is not None and arr.shape != (length,)):
        raise ValueError(f"{name} must have shape ({length},), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


def _positive_int(value, name: str, low: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    return int(value)


def _check_robot(robot) -> ArmKinematics:
    if not isinstance(robot, ArmKinematics):
        raise TypeError(f"robot must be an arm of torchrl_silp.robots (UR5e, Panda), got {type(robot).__name__}")
    return robot


# ---------------------------------------------------------------- geometry
def _shade(faces: list[np.ndarray], centre: np.ndarray, rgba) -> list[tuple]:
    # Lambert shading with a fixed light; a face normal points away from its
    # primitive's centre, so the vertex order of a face does not matter.
    out = []
    base = np.asarray(rgba, dtype=np.float64)
    for f in faces:
        n = np.cross(f[1] - f[0], f[2] - f[0])
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            n = np.zeros(3)
        else:
            n = n / norm
            if np.dot(n, f.mean(0) - centre) < 0:
                n = -n
        k = 0.55 + 0.45 * max(0.0, float(np.dot(n, _LIGHT)))
        out.append((*np.clip(base[:3] * k, 0, 1), base[3]))
    return out


def _cylinder_faces(radius: float, length: float, pose: np.ndarray) -> list[np.ndarray]:
    theta = np.linspace(0.0, 2 * math.pi, _CYLINDER_SEGMENTS, endpoint=False)
    ring = np.stack([radius * np.cos(theta), radius * np.sin(theta), np.zeros_like(theta)], axis=1)
    bottom = ring + [0.0, 0.0, -length / 2]
    top = ring + [0.0, 0.0, length / 2]
    bottom = bottom @ pose[:3, :3].T + pose[:3, 3]
    top = top @ pose[:3, :3].T + pose[:3, 3]
    nxt = np.roll(np.arange(_CYLINDER_SEGMENTS), -1)
    sides = np.stack([bottom, bottom[nxt], top[nxt], top], axis=1)  # (n, 4, 3)
    # Caps as fans of quads (centre + three rim points), not one n-gon: with
    # every polygon a quad, mplot3d keeps one dense vertex array instead of a
    # padded one whose uninitialised padding it projects (overflow warnings).
    caps = []
    for rim in (bottom, top):
        centre = rim.mean(0)
        for i in range(0, _CYLINDER_SEGMENTS, 2):
            caps.append(np.stack([centre, rim[i], rim[nxt[i]], rim[nxt[nxt[i]]]]))
    return [*sides, *caps]


def _box_faces(lo: np.ndarray, hi: np.ndarray, pose: np.ndarray | None = None) -> list[np.ndarray]:
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    if pose is not None:
        corners = corners @ pose[:3, :3].T + pose[:3, 3]
    # corner index = 4 * ix + 2 * iy + iz
    quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    return [corners[list(q)] for q in quads]


def _sphere_faces(radius: float, pose: np.ndarray) -> list[np.ndarray]:
    lat = np.linspace(-math.pi / 2, math.pi / 2, 7)
    lon = np.linspace(0, 2 * math.pi, 13)
    pts = radius * np.stack(
        [np.cos(lat)[:, None] * np.cos(lon), np.cos(lat)[:, None] * np.sin(lon), np.sin(lat)[:, None] + 0 * lon],
        axis=-1,
    )
    pts = pts @ pose[:3, :3].T + pose[:3, 3]
    return [
        np.stack([pts[i, j], pts[i, j + 1], pts[i + 1, j + 1], pts[i + 1, j]])
        for i in range(len(lat) - 1)
        for j in range(len(lon) - 1)
    ]


def arm_polygons(robot: ArmKinematics, q3) -> tuple[list[np.ndarray], list[tuple]]:
    """World-frame polygons and shaded RGBA face colours of the arm's collision primitives.

    Every polygon is a quad: a cylinder is 16 side quads and two caps of 8
    quads each, a box six faces, a sphere a coarse latitude-longitude mesh;
    a collision mesh is drawn as its sphere cover (what the collision test reads).

    Args:
        robot: the arm (:class:`~torchrl_silp.robots.base.ArmKinematics`: the UR5e, the Panda) whose
            ``primitives`` are drawn; its ``END_EFFECTOR_LINKS`` in the gripper's colour.
        q3: one configuration ``(robot.config_dim,)`` (tensor, array or sequence): the UR5e's 3 active
            joints, the Panda's 7.

    Returns:
        a list of ``(k, 3)`` vertex arrays and a list of RGBA tuples, one per polygon.

    Examples:
        >>> from torchrl_silp import UR5e
        >>> from torchrl_silp.viz import arm_polygons
        >>> polys, colours = arm_polygons(UR5e(), [0.0, -1.57, 1.57])
        >>> len(polys) == len(colours), polys[0].shape
        (True, (4, 3))
    """
    robot = _check_robot(robot)
    q = torch.as_tensor(_vector(q3, robot.config_dim, "q3"), dtype=robot.dtype, device=robot.device)
    with torch.no_grad():
        rot, pos = robot.frames(q)
    rot = rot.to("cpu", torch.float64).numpy()
    pos = pos.to("cpu", torch.float64).numpy()
    polys: list[np.ndarray] = []
    colours: list[tuple] = []
    local = robot.sphere_local.to("cpu", torch.float64).numpy()
    radii = robot.sphere_radii.to("cpu", torch.float64).numpy()
    owner = robot.sphere_primitive.cpu().numpy()
    for k, prim in enumerate(robot.primitives):
        f = robot.frame_names.index(prim.link)
        link_pose = np.eye(4)
        link_pose[:3, :3], link_pose[:3, 3] = rot[f], pos[f]
        pose = link_pose @ prim.transform
        if prim.kind == "mesh":
            faces = []
            for i in np.flatnonzero(owner == k):
                ball = link_pose.copy()
                ball[:3, 3] = link_pose[:3, :3] @ local[i] + link_pose[:3, 3]
                faces += _sphere_faces(radii[i], ball)
        elif prim.kind == "cylinder":
            faces = _cylinder_faces(prim.size[0], prim.size[1], pose)
        elif prim.kind == "box":
            half = np.asarray(prim.size) / 2
            faces = _box_faces(-half, half, pose)
        else:
            faces = _sphere_faces(prim.size[0], pose)
        if prim.link in robot.END_EFFECTOR_LINKS:
            rgba = (*_hex_rgb(_GRIPPER_COLOUR), 1.0)
        else:
            rgba = (*_hex_rgb(_ARM_COLOURS[f % 2]), 1.0)
        polys += faces
        colours += _shade(faces, pose[:3, 3], rgba)
    return polys, colours


def _hex_rgb(code: str) -> tuple[float, float, float]:
    return tuple(int(code[i : i + 2], 16) / 255 for i in (1, 3, 5))


def _box_edges(lo, hi) -> np.ndarray:
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pairs = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
    return np.stack([c[[a, b]] for a, b in pairs])


# ------------------------------------------------------------------ drawing
def _new_axes(width_in: float = 4.8, height_in: float = 4.8, dpi: int = 100) -> Axes3D:
    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    FigureCanvasAgg(fig)
    # a right margin keeps the z tick labels, which sit on the right from the default view, in the picture
    ax = fig.add_axes((0.0, 0.0, 0.92, 1.0), projection="3d")
    return ax


def draw_scene(
    robot: ArmKinematics,
    q3,
    obstacle,
    goal,
    start_tcp=None,
    trajectory=None,
    ax: Axes3D | None = None,
    *,
    title: str | None = None,
    view: tuple[float, float] = _DEFAULT_VIEW,
    workspace=None,
) -> Axes3D:
    """Draw the arm at ``q3``, the table, the obstacle, the goal and optional TCP points.

    The arm is drawn from its collision primitives (cylinders as shaded
    surfaces, boxes as faces) placed by ``robot.frames(q3)``; the obstacle is
    the translucent red box of the 6-vector AABB; the table is the plane
    ``z = 0``; the TCP workspace is the dotted box. The goal is a green star,
    the start TCP a blue dot and the trajectory an orange line. Points and the
    trajectory are drawn on top of the solids so they stay visible behind the arm.

    Args:
        robot: an arm of :mod:`torchrl_silp.robots` (the UR5e, the Panda).
        q3: the arm's configuration ``(robot.config_dim,)`` (tensor, array or sequence).
        obstacle: the obstacle AABBs ``(xmin, xmax, ymin, ymax, zmin, zmax)``, one after the other ``(6 k,)``.
        goal: goal position ``(3,)``.
        start_tcp: TCP position ``(3,)`` at the start of the episode, or ``None``.
        trajectory: TCP positions ``(T, 3)``, or ``None``.
        ax: a 3-D axes to draw into; a new figure on the Agg canvas when ``None``.
        title: axes title.
        view: ``(elevation, azimuth)`` of the camera in degrees.
        workspace: the task's TCP workspace ``(low, high)`` drawn dotted; the UR5e task's by default.

    Returns:
        the axes drawn into (``ax.figure`` is its figure).

    Examples:
        >>> import io
        >>> from torchrl_silp import UR5eReachEnv
        >>> from torchrl_silp.viz import draw_scene
        >>> env = UR5eReachEnv(seed=0)
        >>> td = env.reset()
        >>> ax = draw_scene(env.model.robot, td["joint_position"], td["obstacle"], td["desired_goal"],
        ...                 start_tcp=td["achieved_goal"])
        >>> ax.figure.savefig(io.BytesIO(), format="png")
    """
    robot = _check_robot(robot)
    box = _vector(obstacle, None, "obstacle")
    if box.size == 0 or box.size % 6:
        raise ValueError(f"obstacle must hold boxes (xmin, xmax, ymin, ymax, zmin, zmax), 6 numbers each, got {box.size}")
    boxes = box.reshape(-1, 6)
    lows, highs = boxes[:, 0::2], boxes[:, 1::2]
    if (lows > highs).any():
        raise ValueError(f"obstacle must be (xmin, xmax, ymin, ymax, zmin, zmax) with min <= max, got {box}")
    goal = _vector(goal, 3, "goal")
    start = None if start_tcp is None else _vector(start_tcp, 3, "start_tcp")
    path = None if trajectory is None else _vector(trajectory, None, "trajectory", rows=True)
    if ax is None:
        ax = _new_axes()
    elif not isinstance(ax, Axes3D):
        raise TypeError(f"ax must be a 3-D axes (projection='3d'), got {type(ax).__name__}")
    if not (isinstance(view, Sequence) and len(view) == 2):
        raise ValueError(f"view must be (elevation, azimuth) in degrees, got {view!r}")

    arm, arm_colours = arm_polygons(robot, q3)
    obstacle_faces, obstacle_colours = [], []
    for lo, hi in zip(lows, highs):
        faces = _box_faces(lo, hi)
        obstacle_faces += faces
        obstacle_colours += _shade(faces, (lo + hi) / 2, _OBSTACLE_COLOUR)
    polys = arm + obstacle_faces
    face = arm_colours + obstacle_colours
    edge = [(0, 0, 0, 0)] * len(arm) + [_OBSTACLE_EDGE] * len(obstacle_faces)

    # Everything the picture must hold sets the limits; the default scene box
    # keeps panels of one rollout at one scale.
    pts = np.concatenate([*arm, *obstacle_faces, goal[None]])
    extra = [p for p in (start[None] if start is not None else None, path) if p is not None]
    if extra:
        pts = np.concatenate([pts, *extra])
    low = np.minimum(_SCENE_LOW, pts.min(0))
    high = np.maximum(_SCENE_HIGH, pts.max(0))
    low[2] = min(low[2], 0.0)

    # mplot3d's per-artist depth sort puts large flat artists (the table) in
    # front of the arm from many views; fixed z-orders draw table, solids,
    # then markers, while the solids still sort their own faces by depth.
    ax.computed_zorder = False
    # autolim=False: the limits are set explicitly below, from all the data.
    table = np.array([[low[0], low[1], 0.0], [high[0], low[1], 0.0], [high[0], high[1], 0.0], [low[0], high[1], 0.0]])
    ax.add_collection3d(
        Poly3DCollection([table], facecolors=[_TABLE_COLOUR], edgecolors="none", zorder=0), autolim=False
    )
    grid = [
        [[x, low[1], 0.0], [x, high[1], 0.0]] for x in np.arange(math.ceil(low[0] * 5) / 5, high[0] + 1e-9, 0.2)
    ] + [[[low[0], y, 0.0], [high[0], y, 0.0]] for y in np.arange(math.ceil(low[1] * 5) / 5, high[1] + 1e-9, 0.2)]
    ax.add_collection3d(
        Line3DCollection(grid, colors=[(0.5, 0.45, 0.38, 0.5)], linewidths=0.5, zorder=1), autolim=False
    )
    ax.add_collection3d(
        Line3DCollection(
            _box_edges(*(workspace if workspace is not None else (UR5eReach.WORKSPACE_LOW, UR5eReach.WORKSPACE_HIGH))),
            colors=[(0.4, 0.4, 0.4, 0.5)],
            linewidths=0.6,
            linestyles=":",
            zorder=1,
        ),
        autolim=False,
    )
    solids = Poly3DCollection(polys, facecolors=face, edgecolors=edge, linewidths=0.6, zorder=2)
    ax.add_collection3d(solids, autolim=False)
    if path is not None:
        ax.plot(
            path[:, 0], path[:, 1], path[:, 2], color="tab:orange", lw=1.5, marker=".", ms=3, zorder=3, label="TCP path"
        )
    if start is not None:
        ax.scatter(*start, color="tab:blue", s=40, depthshade=False, zorder=4, label="start TCP")
    ax.scatter(*goal, color="tab:green", marker="*", s=160, depthshade=False, zorder=4, label="goal")

    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_zlim(low[2], high[2])
    ax.set_box_aspect(tuple(high - low), zoom=1.0)
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_xlabel("x [m]", fontsize=7, labelpad=-8)
    ax.set_ylabel("y [m]", fontsize=7, labelpad=-8)
    ax.set_zlabel("z [m]", fontsize=7, labelpad=-8)
    ax.tick_params(labelsize=6, pad=-3)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_pane_color((0.97, 0.97, 0.97, 1.0))
    if title is not None:
        ax.set_title(title, fontsize=8, pad=0)
    return ax


def render_rgb(
    robot: ArmKinematics,
    q3,
    obstacle,
    goal,
    start_tcp=None,
    trajectory=None,
    *,
    width: int = 480,
    height: int = 480,
    title: str | None = None,
    view: tuple[float, float] = _DEFAULT_VIEW,
) -> np.ndarray:
    """The scene of :func:`draw_scene` as an RGB picture.

    Args:
        robot, q3, obstacle, goal, start_tcp, trajectory, title, view: as in :func:`draw_scene`.
        width: picture width in pixels (>= 16).
        height: picture height in pixels (>= 16).

    Returns:
        ``uint8`` array of shape ``(height, width, 3)``.

    Examples:
        >>> from torchrl_silp import UR5e
        >>> from torchrl_silp.viz import render_rgb
        >>> box = [0.4, 0.6, 0.1, 0.3, 0.0, 0.3]
        >>> img = render_rgb(UR5e(), [0.0, -1.57, 1.57], box, [0.5, 0.0, 0.2], width=160, height=120)
        >>> img.shape, img.dtype
        ((120, 160, 3), dtype('uint8'))
    """
    width = _positive_int(width, "width", 16)
    height = _positive_int(height, "height", 16)
    dpi = 100
    ax = _new_axes(width / dpi, height / dpi, dpi)
    draw_scene(robot, q3, obstacle, goal, start_tcp, trajectory, ax=ax, title=title, view=view)
    canvas = ax.figure.canvas
    canvas.draw()
    img = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    if img.shape[:2] != (height, width):  # pragma: no cover - Agg sizes are exact for dpi 100
        raise RuntimeError(f"Agg canvas gave {img.shape[:2]}, expected {(height, width)}")
    return img


# ----------------------------------------------------------------- rollouts
def _episodes(done: np.ndarray) -> list[tuple[int, int, int]]:
    """``(row, first, last)`` step indices of every episode in ``done`` ``(B, T)``.

    Ordered by episode index within its row, then by row, so the first panels
    show the first episode of several envs rather than many of env 0.
    """
    per_row = []
    for b, row in enumerate(done):
        ends = np.flatnonzero(row).tolist()
        if not ends or ends[-1] != len(row) - 1:
            ends.append(len(row) - 1)
        starts = [0] + [e + 1 for e in ends[:-1]]
        per_row.append([(b, s, e) for s, e in zip(starts, ends)])
    out = []
    for k in range(max(len(r) for r in per_row)):
        out += [r[k] for r in per_row if k < len(r)]
    return out


def _outcomes(td, shape: tuple) -> tuple[np.ndarray, ...]:
    """A ``[B, T]`` rollout's ``("next", ...)`` flags as arrays of ``shape``: ``(done, reward, success,
    collision, terminated)``; a key the rollout lacks reads as False (NaN for the reward)."""

    def optional(key, fill, dtype):
        if ("next", key) in td.keys(True):
            return td["next", key].detach().to("cpu").numpy().reshape(shape).astype(dtype)
        return np.full(shape, fill, dtype=dtype)

    return (optional("done", False, bool), optional("reward", np.nan, np.float64), optional("success", False, bool),
            optional("collision", False, bool), optional("terminated", False, bool))


def save_rollout_png(env_or_robot, rollout, path: str | os.PathLike, max_panels: int = 4, *, dpi: int = 100):
    """Save one panel per episode of a TorchRL rollout: the arm at the episode's final state and its TCP path.

    Episodes are cut at ``("next", "done")``, so rollouts made with
    ``break_when_any_done=False`` (envs reset inside the rollout) give one
    panel per episode, not per env. Panels show the first episode of each env
    first, then second episodes, and so on, up to ``max_panels``. A panel's
    title gives the env index, the number of steps, the return and how the
    episode ended (success, collision count, or still running / truncated).

    Args:
        env_or_robot: an arm of :mod:`torchrl_silp.robots` (the UR5e, the Panda), or an env or model
            holding one (``.robot`` or ``.model.robot``): the arm is drawn. Any other task model (or an env
            holding one): :func:`save_task_rollout_png` draws its achieved-goal paths.
        rollout: TensorDict with batch ``[B, T]`` or ``[T]`` (more leading dims
            are flattened) holding the named state (``"joint_position"``,
            ``"achieved_goal"``, ``"obstacle"``, ``"desired_goal"``) at the root and the
            configuration and achieved goal under ``"next"``;
            ``("next", "done")``, ``("next", "reward")``, ``("next", "success")``
            and ``("next", "collision")`` are used when present.
        path: where to write the PNG.
        max_panels: most panels to draw.
        dpi: resolution; a panel is 4 x 4 inches.

    Returns:
        ``path``, as given.

    Examples:
        >>> import os, tempfile, torch
        >>> from torchrl_silp import UR5eReachEnv
        >>> from torchrl_silp.viz import save_rollout_png
        >>> env = UR5eReachEnv(num_envs=2, seed=0)
        >>> _ = torch.manual_seed(0)
        >>> td = env.rollout(5)
        >>> out = save_rollout_png(env, td, os.path.join(tempfile.mkdtemp(), "rollout.png"))
        >>> os.path.getsize(out) > 0
        True
    """
    from tensordict import TensorDictBase

    robot = env_or_robot
    for attr in ("model", "robot"):
        if not isinstance(robot, ArmKinematics) and hasattr(robot, attr):
            if isinstance(robot, TaskModel) and not isinstance(getattr(robot, attr), ArmKinematics):
                break
            robot = getattr(robot, attr)
    if not isinstance(robot, ArmKinematics):
        model = env_or_robot if isinstance(env_or_robot, TaskModel) else getattr(env_or_robot, "model", None)
        if isinstance(model, TaskModel):  # a task without an arm of torchrl_silp.robots: its goal-space paths
            return save_task_rollout_png(model, rollout, path, max_panels, dpi=dpi)
        raise TypeError(
            "env_or_robot must be an arm of torchrl_silp.robots, a TaskModel, or an env holding one (`robot` or `model`), "
            f"got {type(env_or_robot).__name__}"
        )
    owner = env_or_robot if isinstance(env_or_robot, TaskModel) else getattr(env_or_robot, "model", None)
    workspace = None
    if getattr(owner, "workspace_low", None) is not None:  # the task model's TCP workspace, drawn dotted
        workspace = (_vector(owner.workspace_low, 3, "workspace_low"), _vector(owner.workspace_high, 3, "workspace_high"))
    if not isinstance(rollout, TensorDictBase):
        raise TypeError(f"rollout must be a TensorDict, got {type(rollout).__name__}")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    max_panels = _positive_int(max_panels, "max_panels")
    dpi = _positive_int(dpi, "dpi", 10)
    if rollout.batch_dims < 1 or rollout.batch_size.numel() == 0:
        raise ValueError(f"rollout must have batch [B, T] or [T] with T >= 1, got {tuple(rollout.batch_size)}")
    needed = ("joint_position", "achieved_goal", "obstacle", "desired_goal", ("next", "joint_position"),
              ("next", "achieved_goal"))
    missing = [k for k in needed if k not in rollout.keys(True)]
    if missing:
        raise ValueError(f"rollout is missing the keys {missing}")
    td = rollout.reshape(-1, rollout.batch_size[-1])

    def array(key):
        return td[key].detach().to("cpu", torch.float64).numpy()

    start_tcp, obstacle, goal = array("achieved_goal"), array("obstacle"), array("desired_goal")
    next_q, next_tcp = array(("next", "joint_position")), array(("next", "achieved_goal"))
    shape = start_tcp.shape[:2]

    done, reward, success, collision, terminated = _outcomes(td, shape)

    episodes = _episodes(done)[:max_panels]
    n = len(episodes)
    ncols = math.ceil(math.sqrt(n))
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(4.0 * ncols, 4.0 * nrows), dpi=dpi)
    FigureCanvasAgg(fig)
    for i, (b, first, last) in enumerate(episodes):
        ax = fig.add_subplot(nrows, ncols, i + 1, projection="3d")
        steps = slice(first, last + 1)
        path_xyz = np.concatenate([start_tcp[b, first, None], next_tcp[b, steps]])
        if success[b, last]:
            end = "success"
        elif terminated[b, last] and collision[b, last]:
            end = "ended by a collision"
        elif done[b, last]:
            end = "truncated"
        else:
            end = "running"
        n_coll = int(collision[b, steps].sum())
        title = f"env {b}: {last - first + 1} steps, return {np.nansum(reward[b, steps]):.1f}\n{end}"
        if n_coll:
            title += f", {n_coll} collision{'s' if n_coll > 1 else ''}"
        draw_scene(
            robot,
            next_q[b, last],
            obstacle[b, first],
            goal[b, first],
            start_tcp=start_tcp[b, first],
            trajectory=path_xyz,
            ax=ax,
            title=title,
            workspace=workspace,
        )
    fig.subplots_adjust(left=0.0, right=0.95, bottom=0.02, top=0.95, wspace=0.08, hspace=0.12)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower right", fontsize=7, frameon=False)
    fig.savefig(path, format="png")
    return path


def save_task_rollout_png(model: TaskModel, rollout, path: str | os.PathLike, max_panels: int = 4, *,
                          dpi: int = 100):
    """One panel per episode of any task model's rollout, drawn in its goal space.

    Each panel shows the achieved-goal path from the episode's start, the desired goal with a circle
    (sphere) of the model's ``success_distance``, and the scene's boxes where the model gives them
    (:meth:`~torchrl_silp.models.TaskModel.scene_boxes`): in 2-D for a 2-D goal space, in 3-D for
    three or more dimensions (the first three). A model with a ``draw_scene(ax, state)`` method draws
    the rest itself (its obstacles, its robot at ``state``: the episode's last reached state, a
    TensorDict without batch dims). Episodes are cut as in :func:`save_rollout_png`.

    Args:
        model: the task model the rollout ran on.
        rollout: TensorDict ``[B, T]`` or ``[T]`` holding the model's achieved and desired goal and
            its scene at the root, the achieved goal under ``"next"``; ``("next", "done")``,
            ``"reward"``, ``"success"`` and ``"collision"`` when present.
        path: where to write the PNG.

    Returns:
        ``path``, as given.

    Examples:
        >>> import os, tempfile, torch
        >>> from torchrl_silp import PandaReach, ReachEnv
        >>> env = ReachEnv(PandaReach(), num_envs=2, seed=0)
        >>> _ = torch.manual_seed(0)
        >>> out = save_task_rollout_png(env.model, env.rollout(5), os.path.join(tempfile.mkdtemp(), "r.png"))
        >>> os.path.getsize(out) > 0
        True
    """
    from tensordict import TensorDictBase

    if not isinstance(model, TaskModel):
        raise TypeError(f"model must be a torchrl_silp.models.TaskModel, got {type(model).__name__}")
    if not isinstance(rollout, TensorDictBase):
        raise TypeError(f"rollout must be a TensorDict, got {type(rollout).__name__}")
    max_panels = _positive_int(max_panels, "max_panels")
    dpi = _positive_int(dpi, "dpi", 10)
    if rollout.batch_dims < 1 or rollout.batch_size.numel() == 0:
        raise ValueError(f"rollout must have batch [B, T] or [T] with T >= 1, got {tuple(rollout.batch_size)}")
    achieved_key, desired_key = model.achieved_goal_key, model.desired_goal_key
    needed = (achieved_key, desired_key, ("next", achieved_key), *model.scene_keys)
    missing = [k for k in needed if k not in rollout.keys(True)]
    if missing:
        raise ValueError(f"rollout is missing the keys {missing}")
    td = rollout.reshape(-1, rollout.batch_size[-1])
    shape = tuple(td.batch_size)

    def array(key):
        return td[key].detach().to("cpu", torch.float64).numpy()

    start, desired, reached = array(achieved_key), array(desired_key), array(("next", achieved_key))
    boxes = model.scene_boxes(td.select(*model.scene_keys))
    boxes = None if boxes is None else boxes.detach().to("cpu", torch.float64).numpy()

    done, reward, success, collision, _ = _outcomes(td, shape)
    dims = min(start.shape[-1], 3)
    episodes = _episodes(done)[:max_panels]
    n = len(episodes)
    ncols = math.ceil(math.sqrt(n))
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(4.0 * ncols, 4.0 * nrows), dpi=dpi)
    FigureCanvasAgg(fig)
    radius = float(getattr(model, "success_distance", 0.0))
    for i, (b, first, last) in enumerate(episodes):
        ax = fig.add_subplot(nrows, ncols, i + 1, **({"projection": "3d"} if dims == 3 else {}))
        path_pts = np.concatenate([start[b, first, None], reached[b, first:last + 1]])[:, :dims]
        goal = desired[b, first, :dims]
        if boxes is not None:
            for box in boxes[b, first]:
                lo, hi = box[0::2][:dims], box[1::2][:dims]
                if dims == 3:
                    ax.add_collection3d(Poly3DCollection(_box_faces(lo, hi), facecolor=_OBSTACLE_COLOUR,
                                                         edgecolor=_OBSTACLE_EDGE, linewidths=0.5))
                else:
                    ax.add_patch(matplotlib.patches.Rectangle(lo, *(hi - lo), facecolor=_OBSTACLE_COLOUR,
                                                              edgecolor=_OBSTACLE_EDGE))
        draw = getattr(model, "draw_scene", None)
        if callable(draw):
            draw(ax, td["next"][b, last].select(*model.state_keys).to("cpu"))
        ax.plot(*path_pts.T, color="#1f5fa8", marker=".", markersize=3, linewidth=1.2, label="achieved goal")
        ax.scatter(*path_pts[0], color="#2a9d3f", s=25, label="start")
        ax.scatter(*goal, color="#d4a017", marker="*", s=90, label="desired goal")
        if dims == 2 and radius:
            ax.add_patch(matplotlib.patches.Circle(goal, radius, fill=False, color="#d4a017", linewidth=0.8))
        if dims == 2:
            ax.set_aspect("equal", adjustable="datalim")
        end = "success" if success[b, last] else ("truncated" if done[b, last] else "running")
        n_coll = int(collision[b, first:last + 1].sum())
        title = f"env {b}: {last - first + 1} steps, return {np.nansum(reward[b, first:last + 1]):.1f}\n{end}"
        if n_coll:
            title += f", {n_coll} collision{'s' if n_coll > 1 else ''}"
        ax.set_title(title, fontsize=8)
        ax.tick_params(labelsize=6)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower right", fontsize=7, frameon=False)
    fig.savefig(path, format="png")
    return path


def save_cover_png(robot: ArmKinematics, path: str | os.PathLike, q=None, *, max_faces: int = 10_000,
                   view: tuple[float, float] = _DEFAULT_VIEW, dpi: int = 110) -> None:
    """Save a picture of the arm's collision geometry (its meshes and primitives, grey) inside its sphere cover
    (translucent blue), side by side: how closely the spheres the collision test reads wrap the real links.

    Args:
        robot: the arm.
        path: the PNG file.
        q: the configuration drawn (default: every joint at 0 within its limits, or ``robot.HOME``).
        max_faces: a mesh with more triangles is drawn from an even subset of them (the picture only).
    """
    robot = _check_robot(robot)
    if q is None:
        q = robot.HOME if robot.HOME is not None else torch.zeros(robot.config_dim).clamp(
            robot.joint_low.cpu().float(), robot.joint_high.cpu().float())
    q = torch.as_tensor(_vector(q, robot.config_dim, "q"), dtype=robot.dtype, device=robot.device)
    with torch.no_grad():
        rot, pos = robot.frames(q)
        centres, _ = robot.spheres_and_tcp(q)
    rot, pos = rot.to("cpu", torch.float64).numpy(), pos.to("cpu", torch.float64).numpy()
    centres = centres.to("cpu", torch.float64).numpy()
    radii = robot.sphere_radii.to("cpu", torch.float64).numpy()
    fig = Figure(figsize=(9.0, 4.6), dpi=dpi)
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.02, top=0.95, wspace=0.0)
    meshes = []
    for prim in robot.primitives:
        f = robot.frame_names.index(prim.link)
        pose = np.eye(4)
        pose[:3, :3], pos_f = rot[f], pos[f]
        pose[:3, 3] = pos_f
        mesh = prim.trimesh()
        tri = mesh.vertices[mesh.faces] @ pose[:3, :3].T + pose[:3, 3]
        if len(tri) > max_faces:
            tri = tri[np.linspace(0, len(tri) - 1, max_faces).astype(int)]
        meshes.append(tri)
    tri = np.concatenate(meshes)
    balls = [face for c, r in zip(centres, radii) for face in _sphere_faces(r, _translation_pose(c))]
    pts = np.concatenate([tri.reshape(-1, 3), centres + radii[:, None], centres - radii[:, None]])
    low, high = pts.min(0), pts.max(0)
    side = (high - low).max() / 2
    mid = (high + low) / 2
    for k, (title, with_cover) in enumerate((("collision geometry", False), ("its sphere cover", True))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(list(tri), facecolors=_shade(list(tri), mid, (0.55, 0.55, 0.55, 1.0)),
                                             edgecolors="none"), autolim=False)
        if with_cover:
            ax.add_collection3d(Poly3DCollection(balls, facecolors=[(0.25, 0.45, 0.8, 0.18)],
                                                 edgecolors=[(0.2, 0.35, 0.7, 0.25)], linewidths=0.3), autolim=False)
        for i, lim in enumerate((ax.set_xlim, ax.set_ylim, ax.set_zlim)):
            lim(mid[i] - side, mid[i] + side)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=view[0], azim=view[1])
        ax.tick_params(labelsize=6, pad=-3)
        ax.set_title(f"{title}" + (f": {robot.n_spheres} spheres" if with_cover else ""), fontsize=9)
    fig.savefig(os.fspath(path))


def _translation_pose(centre: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = centre
    return pose
