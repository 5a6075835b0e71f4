"""UR5e kinematics and collision spheres, from ``assets/ur5e.urdf``.

The URDF is parsed once by pytorch-kinematics; its joint origins are then
held as constant tensors (buffers) and forward kinematics runs as a short
chain of batched rotations, which is several times faster than the generic
tree walk of ``Chain.forward_kinematics_tensor`` for this serial, all-``z``-axis
arm (see ``benchmarks/env_throughput.py``). The generic library FK remains the
reference the tests compare against.

Only three joints are active (shoulder_pan, shoulder_lift, elbow); wrist_1
follows them so that the tool axis points straight down, wrist_2 and wrist_3
are fixed (paper, sec. 3.1).
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from importlib import resources

import numpy as np
import pytorch_kinematics as pk
import torch
from torch import nn

__all__ = ["UR5e", "default_urdf_path", "CollisionPrimitive"]

ACTIVE_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint")
# wrist_2 = -pi/2 and wrist_1 = -pi/2 - (q2 + q3) keep the tool z axis at -z
# for every (q1, q2, q3): the three lift/elbow/wrist_1 axes are parallel, so the
# tool pitch is their sum.
WRIST_2_FIXED = -math.pi / 2
WRIST_3_FIXED = 0.0
TCP_FRAME = "tcp"


def default_urdf_path() -> str:
    """Path of ``assets/ur5e.urdf``, installed with the package as ``torchrl_silp.assets``."""
    return str(resources.files("torchrl_silp.assets") / "ur5e.urdf")


def read_urdf(path: str) -> str:
    """The text of a URDF file; a ValueError naming ``urdf_path`` when it cannot be read."""
    try:
        with open(path) as fh:
            return fh.read()
    except OSError as err:
        raise ValueError(f"urdf_path: cannot read URDF file {path!r}: {err}") from err


def origin_matrix(origin) -> np.ndarray:
    """The 4x4 pose (float64) of a URDF ``<origin xyz rpy>`` element; identity when it is None."""
    xyz, rpy = np.zeros(3), np.zeros(3)
    if origin is not None:
        xyz = np.array([float(v) for v in origin.get("xyz", "0 0 0").split()])
        rpy = np.array([float(v) for v in origin.get("rpy", "0 0 0").split()])
    T = np.eye(4)
    T[:3, :3] = _rpy_to_matrix(rpy)
    T[:3, 3] = xyz
    return T


def _rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    # URDF convention: R = Rz(yaw) @ Ry(pitch) @ Rx(roll)
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


class CollisionPrimitive:
    """One ``<collision>`` element: a cylinder (axis along local z), box or sphere.

    Attributes:
        link: name of the link it belongs to.
        kind: ``"cylinder"``, ``"box"`` or ``"sphere"``.
        size: cylinder ``(radius, length)``, box ``(x, y, z)`` or sphere ``(radius,)``.
        transform: 4x4 pose of the primitive in its link frame (float64 numpy).
    """

    def __init__(self, link: str, kind: str, size: tuple[float, ...], transform: np.ndarray):
        self.link, self.kind, self.size, self.transform = link, kind, tuple(size), transform

    def __repr__(self) -> str:
        return f"CollisionPrimitive(link={self.link!r}, kind={self.kind!r}, size={self.size})"

    def sphere_cover(self) -> tuple[np.ndarray, np.ndarray]:
        """A conservative sphere cover: every point of the solid lies in some sphere.

        Returns:
            centres ``(n, 3)`` in the link frame and radii ``(n,)`` (float64 numpy).
        """
        if self.kind == "sphere":
            local = np.zeros((1, 3))
            radii = np.array([self.size[0]])
        elif self.kind == "cylinder":
            r, length = self.size
            # n slabs of height h = length / n; the sphere at a slab's centre with
            # radius sqrt(r^2 + (h/2)^2) contains the whole slab (its rim corners
            # are the farthest points). h <= 1.2 r bounds the inflation to ~17 %.
            n = max(1, math.ceil(length / (1.2 * r)))
            h = length / n
            z = -length / 2 + h * (np.arange(n) + 0.5)
            local = np.stack([np.zeros(n), np.zeros(n), z], axis=1)
            radii = np.full(n, math.sqrt(r * r + (h / 2) ** 2))
        elif self.kind == "box":
            size = np.asarray(self.size, dtype=np.float64)
            # cells no longer than max(smallest side, largest side / 3); each cell
            # lies in the sphere through its corners. The bound keeps thin plates
            # (the fingers) to a handful of spheres.
            cell = max(size.min(), size.max() / 3)
            counts = np.maximum(1, np.ceil(size / cell - 1e-9)).astype(int)
            step = size / counts
            axes = [-size[i] / 2 + step[i] * (np.arange(counts[i]) + 0.5) for i in range(3)]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
            local = grid
            radii = np.full(len(grid), 0.5 * float(np.linalg.norm(step)))
        else:  # pragma: no cover - rejected by the parser
            raise ValueError(f"unsupported primitive {self.kind!r}")
        centres = local @ self.transform[:3, :3].T + self.transform[:3, 3]
        return centres, radii


def _parse_collisions(urdf_text: str) -> list[CollisionPrimitive]:
    root = ET.fromstring(urdf_text)
    prims: list[CollisionPrimitive] = []
    for link in root.iter("link"):
        for col in link.findall("collision"):
            T = origin_matrix(col.find("origin"))
            geom = col.find("geometry")
            if geom is None or len(geom) != 1:
                raise ValueError(f"urdf: link {link.get('name')!r} has a <collision> without one geometry")
            g = geom[0]
            if g.tag == "cylinder":
                size = (float(g.get("radius")), float(g.get("length")))
            elif g.tag == "box":
                size = tuple(float(v) for v in g.get("size").split())
            elif g.tag == "sphere":
                size = (float(g.get("radius")),)
            else:
                raise ValueError(
                    f"urdf: link {link.get('name')!r}: collision geometry {g.tag!r} is not supported; "
                    "allowed: cylinder, box, sphere"
                )
            prims.append(CollisionPrimitive(link.get("name"), g.tag, size, T))
    return prims


def _snap(m: torch.Tensor) -> torch.Tensor:
    m = m.clone()
    for v in (0.0, 1.0, -1.0):
        m[(m - v).abs() < 1e-6] = v
    return m


# Scalar algebra over "a tensor or a Python float", folding 0 and +-1 so the
# traced chain only holds the products that are really there.
def _mul(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return a * b
    if isinstance(a, float):
        a, b = b, a
    if isinstance(b, float):
        return 0.0 if b == 0.0 else a if b == 1.0 else -a if b == -1.0 else a * b
    return a * b


def _add(a, b):
    if isinstance(a, float) and a == 0.0:
        return b
    if isinstance(b, float) and b == 0.0:
        return a
    return a + b


def _sub(a, b):
    return _add(a, _mul(b, -1.0))


def _dot(row, col):
    acc = 0.0
    for a, b in zip(row, col):
        acc = _add(acc, _mul(a, b))
    return acc


class _Sym:
    """A named value in a traced program; arithmetic on it records a line of code."""

    def __init__(self, tracer: "_Tracer", name: str, negates: "_Sym | None" = None):
        self.tracer, self.name, self.negates = tracer, name, negates

    def _emit(self, expr: str, deps: tuple) -> "_Sym":
        return self.tracer.emit(expr, deps)

    @staticmethod
    def _ref(x):
        return x.name if isinstance(x, _Sym) else repr(float(x))

    def __mul__(self, other):
        return self._emit(f"{self.name} * {self._ref(other)}", (self, other))

    __rmul__ = __mul__

    def __add__(self, other):
        return self._emit(f"{self.name} + {self._ref(other)}", (self, other))

    __radd__ = __add__

    def __neg__(self):
        if self.negates is not None:  # -(-x) is x
            return self.negates
        out = self._emit(f"-{self.name}", (self,))
        out.negates = self
        return out

    def unsqueeze(self, dim: int):
        return self._emit(f"{self.name}.unsqueeze({dim})", (self,))


class _Tracer:
    """Records straight-line tensor code from the 0/+-1-folding algebra above.

    The chain and sphere formulas are run once at construction on symbolic
    inputs; the recorded lines become a plain Python function, so the hot path
    runs only the ~100 tensor ops that remain, without re-deciding the folding
    on every call (which cost ~2.5 ms of Python per call).
    """

    def __init__(self):
        self.lines: list[tuple[str, str, set]] = []
        self._seen: dict[str, _Sym] = {}  # common subexpressions

    def input(self, name: str) -> _Sym:
        return _Sym(self, name)

    def emit(self, expr: str, deps: tuple) -> _Sym:
        if expr in self._seen:
            return self._seen[expr]
        name = f"v{len(self.lines)}"
        self.lines.append((name, expr, {d.name for d in deps if isinstance(d, _Sym)}))
        self._seen[expr] = sym = _Sym(self, name)
        return sym

    def function(self, fname: str, args: list[str], outputs) -> "callable":
        """Compile ``outputs`` (a nested tuple of _Sym / floats) into ``fname(*args)``."""

        def render(o):
            if isinstance(o, (tuple, list)):
                return "(" + "".join(render(x) + ", " for x in o) + ")"
            return o.name if isinstance(o, _Sym) else repr(float(o))

        def names(o):
            if isinstance(o, (tuple, list)):
                return set().union(*[names(x) for x in o]) if o else set()
            return {o.name} if isinstance(o, _Sym) else set()

        needed, body = names(outputs), []
        for name, expr, deps in reversed(self.lines):  # drop dead code
            if name in needed:
                body.append(f"    {name} = {expr}")
                needed |= deps
        src = f"def {fname}({', '.join(args)}):\n" + "\n".join(reversed(body)) + f"\n    return {render(outputs)}\n"
        scope: dict = {}
        exec(compile(src, f"<torchrl_silp.robot.{fname}>", "exec"), scope)
        scope[fname].source = src
        return scope[fname]


def _stack_vec(v, n, like):
    return torch.stack([x if isinstance(x, torch.Tensor) else like.new_full((n,), x) for x in v], dim=-1)


def _stack_affine(R, p, n, like):
    """(n, 3, 4) tensor [R | p] from entries that are tensors or Python floats."""
    entries = [x for i in range(3) for x in (*R[i], p[i])]
    if all(isinstance(x, float) for x in entries):
        return like.new_tensor(entries).reshape(1, 3, 4).expand(n, 3, 4)
    return _stack_vec(entries, n, like).reshape(n, 3, 4)


def _as_slice(indices: list[int]):
    """``slice`` equal to a run of consecutive indices, else the index list itself."""
    if indices and indices == list(range(indices[0], indices[-1] + 1)):
        return slice(indices[0], indices[-1] + 1)
    return torch.tensor(indices, dtype=torch.long)


class UR5e(nn.Module):
    """UR5e with a Robotiq 2F-140-sized gripper, three active joints.

    Every method takes joint angles with any leading batch dims ``(..., 3)``,
    on the module's device, and is differentiable. Constants (joint origins,
    sphere centres) are buffers, so ``.to(device)`` moves them.

    Args:
        urdf_path: URDF file; defaults to the one shipped in the package.
        device: torch device of the constant tensors.
        dtype: floating dtype (float32 default; float64 for tests).
        self_collision_links: links whose spheres are checked against the gripper's.

    Examples:
        >>> import torch
        >>> from torchrl_silp import UR5e
        >>> robot = UR5e()
        >>> q = torch.tensor([0.0, -1.5708, 1.5708])
        >>> robot.fk(q).shape
        torch.Size([3])
        >>> robot.full_joints(torch.zeros(4, 2, 3)).shape
        torch.Size([4, 2, 6])
        >>> centres, radii = robot.link_spheres(q)
        >>> centres.shape[-1], radii.ndim
        (3, 1)
    """

    GRIPPER_LINKS = ("tool0",)
    # batches up to this size take the whole-matrix path (measured crossover,
    # benchmarks/env_throughput.py); larger ones the generated vector kernel
    SMALL_BATCH = 1

    def __init__(
        self,
        urdf_path: str | os.PathLike | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        self_collision_links: tuple[str, ...] = ("base_link", "shoulder_link", "upper_arm_link"),
    ):
        super().__init__()
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        path = default_urdf_path() if urdf_path is None else os.fspath(urdf_path)
        text = read_urdf(path)
        try:
            chain = pk.build_serial_chain_from_urdf(text, TCP_FRAME)
        except Exception as err:  # the parser raises assorted types
            raise ValueError(f"urdf_path: {path!r} is not a UR5e URDF with a {TCP_FRAME!r} frame: {err}") from err
        self.urdf_path = path
        self.chain = chain  # kept for reference FK (tests, tools); not used in hot paths
        names = chain.get_joint_parameter_names()
        if tuple(names[:3]) != ACTIVE_JOINTS or len(names) != 6:
            raise ValueError(f"urdf_path: expected the 6 UR joints starting with {ACTIVE_JOINTS}, got {names}")

        # Walk the serial chain once: one entry per frame after the root, with
        # its static origin and whether a joint rotates it about local z.
        frame_names: list[str] = []
        origins: list[torch.Tensor] = []
        joint_of_frame: list[int] = []
        frame = chain._root
        jidx = 0
        while frame.children:
            frame = frame.children[0]
            frame_names.append(frame.name)
            origins.append(frame.joint.offset.get_matrix()[0].to(torch.float64))
            if frame.joint.joint_type == "revolute":
                axis = frame.joint.axis.to(torch.float64)
                if not torch.allclose(axis, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)):
                    raise ValueError(f"urdf_path: joint {frame.joint.name!r} must rotate about its local z axis")
                joint_of_frame.append(jidx)
                jidx += 1
            elif frame.joint.joint_type == "fixed":
                joint_of_frame.append(-1)
            else:
                raise ValueError(f"urdf_path: joint type {frame.joint.joint_type!r} is not supported")
        self.frame_names = ["base_link"] + frame_names
        self._joint_of_frame = joint_of_frame
        # pytorch-kinematics stores origins in float32: cos(pi/2) comes back as
        # -4.4e-8. Entries within 1e-6 of 0 or +-1 are snapped to the exact value
        # the URDF's rpy means, so float64 FK matches closed-form DH to ~1e-8 m.
        self._origins = [(_snap(o[:3, :3]).tolist(), o[:3, 3].tolist()) for o in origins]

        low, high = chain.get_joint_limits()
        self.register_buffer("joint_low", torch.tensor(low[:3], dtype=dtype))
        self.register_buffer("joint_high", torch.tensor(high[:3], dtype=dtype))

        # Sphere cover of every collision primitive, grouped by the frame it rides on.
        prims = _parse_collisions(text)
        if not prims:
            raise ValueError(f"urdf_path: {path!r} has no <collision> geometry")
        self.primitives = prims
        centres, radii, frame_idx, prim_idx = [], [], [], []
        for k, prim in enumerate(prims):
            if prim.link not in self.frame_names:
                raise ValueError(f"urdf_path: collision on link {prim.link!r} which is not on the arm's chain")
            c, r = prim.sphere_cover()
            centres.append(c)
            radii.append(r)
            frame_idx += [self.frame_names.index(prim.link)] * len(r)
            prim_idx += [k] * len(r)
        all_local, all_radii = np.concatenate(centres), np.concatenate(radii)
        if any(a > b for a, b in zip(frame_idx, frame_idx[1:])):
            raise ValueError("urdf_path: list <link> elements in chain order (collision spheres are grouped by frame)")
        self.register_buffer("sphere_local", torch.tensor(all_local, dtype=dtype))  # (S, 3) in link frames
        self.register_buffer("sphere_radii", torch.tensor(all_radii, dtype=dtype))  # (S,)
        self.register_buffer("sphere_frame", torch.tensor(frame_idx, dtype=torch.long))  # index in frame_names
        self.register_buffer("sphere_primitive", torch.tensor(prim_idx, dtype=torch.long))  # index in primitives
        self._sphere_groups = [
            (f, frame_idx.index(f), len(frame_idx) - frame_idx[::-1].index(f)) for f in sorted(set(frame_idx))
        ]
        # which local coordinate columns of a frame's spheres are all zero (skipped in the hot path)
        self._group_nonzero = [
            tuple(bool(np.any(all_local[lo:hi, j] != 0.0)) for j in range(3)) for _, lo, hi in self._sphere_groups
        ]
        links = [p.link for p in prims]
        sphere_link = [links[k] for k in prim_idx]
        self.sphere_link_names = sphere_link
        # The base may rest on the table; every other sphere is checked against z = 0.
        self.register_buffer("table_mask", torch.tensor([n != "base_link" for n in sphere_link]))
        self.register_buffer(
            "gripper_spheres", torch.tensor([i for i, n in enumerate(sphere_link) if n in self.GRIPPER_LINKS])
        )
        # one sphere around all gripper spheres (on the tool0 frame): a cheap first
        # test before the sphere-by-sphere self-collision check
        g = [i for i, n in enumerate(sphere_link) if n in self.GRIPPER_LINKS]
        if {frame_idx[i] for i in g} != {self.frame_names.index(self.GRIPPER_LINKS[0])}:
            raise ValueError(f"urdf_path: gripper collision geometry must sit on {self.GRIPPER_LINKS[0]!r}")
        gc = all_local[g]
        bound_centre = (gc.min(0) + gc.max(0)) / 2
        bound_radius = float((np.linalg.norm(gc - bound_centre, axis=1) + all_radii[g]).max())
        self._gripper_bound_list = bound_centre.tolist()
        self.register_buffer("_gripper_bound_t", torch.tensor(bound_centre, dtype=dtype), persistent=False)
        self.gripper_bound_radius = bound_radius
        self._gripper_frame = self.frame_names.index(self.GRIPPER_LINKS[0])
        unknown = set(self_collision_links) - set(self.frame_names)
        if unknown:
            raise ValueError(f"self_collision_links: unknown links {sorted(unknown)}; allowed: {self.frame_names}")
        self.register_buffer(
            "self_collision_spheres",
            torch.tensor([i for i, n in enumerate(sphere_link) if n in self_collision_links]),
        )
        # The sets above are contiguous runs of the frame-ordered spheres: keep
        # them as slices too, so the hot path takes views instead of gathers.
        self.table_slice = _as_slice(self.table_mask.nonzero().squeeze(-1).tolist())
        self.gripper_slice = _as_slice(self.gripper_spheres.tolist())
        self.self_collision_slice = _as_slice(self.self_collision_spheres.tolist())
        origin_h = torch.eye(4, dtype=torch.float64).repeat(len(origins), 1, 1)
        for f, (O, o) in enumerate(self._origins):
            origin_h[f, :3, :3], origin_h[f, :3, 3] = torch.tensor(O), torch.tensor(o)
        self.register_buffer("_origin_h", origin_h.to(dtype), persistent=False)
        self.register_buffer(
            "_joint_origin_h", origin_h[[f for f, j in enumerate(joint_of_frame) if j >= 0]].to(dtype), persistent=False
        )
        self.register_buffer("_root_h", torch.eye(4, dtype=dtype), persistent=False)
        local_h = torch.cat([self.sphere_local, torch.ones_like(self.sphere_local[:, :1])], dim=-1)
        self.register_buffer("_sphere_local_h", local_h.unsqueeze(-1), persistent=False)  # (S, 4, 1)
        self._generate_kernels()
        self._refresh_sphere_cols()

    def __getstate__(self):
        # the generated kernels are exec'd functions, which pickle cannot name: rebuilt on load
        state = self.__dict__.copy()
        for name in ("_gen_tcp", "_gen_tcp_pos", "_gen_frames", "_gen_spheres"):
            state.pop(name, None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._generate_kernels()

    def _refresh_sphere_cols(self) -> None:
        # per-frame local columns, the generated sphere kernel's constant inputs
        self._sphere_cols = [self.sphere_local[lo:hi, j] for _, lo, hi in self._sphere_groups for j in range(3)]

    def _apply(self, fn, *args, **kwargs):
        out = super()._apply(fn, *args, **kwargs)
        self._refresh_sphere_cols()  # .to(device / dtype) replaced the buffers
        return out

    # ------------------------------------------------------------------ joints
    @property
    def dtype(self) -> torch.dtype:
        return self.joint_low.dtype

    @property
    def device(self) -> torch.device:
        return self.joint_low.device

    def _check_q3(self, q3: torch.Tensor, name: str = "q3") -> None:
        if not isinstance(q3, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor of shape (..., 3), got {type(q3).__name__}")
        if q3.shape[-1:] != (3,):
            raise ValueError(f"{name} must have shape (..., 3) (the 3 active joints), got {tuple(q3.shape)}")
        if not q3.is_floating_point():
            raise TypeError(f"{name} must be a floating tensor, got {q3.dtype}")

    def full_joints(self, q3: torch.Tensor) -> torch.Tensor:
        """The 6 joint angles for active angles ``q3``: the tool points straight down.

        ``wrist_1 = -pi/2 - (shoulder_lift + elbow)``, ``wrist_2 = -pi/2``, ``wrist_3 = 0``.
        """
        self._check_q3(q3)
        w1 = -math.pi / 2 - q3[..., 1:2] - q3[..., 2:3]
        fixed = q3.new_tensor([WRIST_2_FIXED, WRIST_3_FIXED]).expand(*q3.shape[:-1], 2)
        return torch.cat([q3, w1, fixed], dim=-1)

    def _chain(self, c, s) -> list:
        # Each frame is T = T_parent @ origin @ Rz(q_j). The origins of a UR
        # description are axis-aligned (entries 0 / +-1), so the chain is
        # evaluated entry by entry on (n,)-vectors, with products by 0 and +-1
        # folded away: ~10 vector ops per frame instead of a batched 3x3 matmul,
        # which on CPU is dominated by per-matrix overhead. Generic over the
        # value type: run once on _Sym inputs to generate the hot-path code.
        R: list[list] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        p: list = [0.0, 0.0, 0.0]
        out = [(R, p)]
        for f, j in enumerate(self._joint_of_frame):
            O, o = self._origins[f]
            p = [_add(p[i], _dot(R[i], o)) for i in range(3)]
            R = [[_dot(R[i], [O[0][k], O[1][k], O[2][k]]) for k in range(3)] for i in range(3)]
            if j >= 0:
                cj, sj = c[j], s[j]
                R = [[_add(_mul(r[0], cj), _mul(r[1], sj)), _sub(_mul(r[1], cj), _mul(r[0], sj)), r[2]] for r in R]
            out.append((R, p))
        return out

    def _sphere_blocks(self, out, cols) -> tuple:
        # centre_i = p_i + sum_j R_ij * local_j, one (N, k) block per frame and
        # coordinate; zero local columns and constant rotation entries fold away.
        coords = []
        for i in range(3):
            blocks = []
            for g, (f, lo, hi) in enumerate(self._sphere_groups):
                R, p = out[f]
                acc = p[i] if isinstance(p[i], float) else p[i].unsqueeze(-1)
                for j in range(3):
                    if self._group_nonzero[g][j]:
                        r = R[i][j]
                        acc = _add(acc, _mul(cols[g][j], r) if isinstance(r, float) else r.unsqueeze(-1) * cols[g][j])
                blocks.append(acc)
            coords.append(tuple(blocks))
        R, p = out[self._gripper_frame]
        bound = tuple(_add(p[i], _dot(R[i], self._gripper_bound_list)) for i in range(3))
        return tuple(coords), tuple(out[-1][1]), bound

    def _generate_kernels(self) -> None:
        names = [f"c{j}" for j in range(6)] + [f"s{j}" for j in range(6)]
        col_names = [[f"L{g}_{j}" for j in range(3)] for g in range(len(self._sphere_groups))]

        def trace():
            tr = _Tracer()
            cs = [tr.input(n) for n in names]
            cols = [[tr.input(n) for n in row] for row in col_names]
            return tr, self._chain(cs[:6], cs[6:]), cols

        tr, out, _ = trace()
        flat = lambda R, p: tuple(x for i in range(3) for x in (*R[i], p[i]))  # noqa: E731
        self._gen_tcp = tr.function("ur5e_tcp", names, flat(*out[-1]))
        tr, out, _ = trace()
        self._gen_tcp_pos = tr.function("ur5e_tcp_pos", names, tuple(out[-1][1]))
        tr, out, _ = trace()
        self._gen_frames = tr.function("ur5e_frames", names, tuple(flat(R, p) for R, p in out))
        tr, out, cols = trace()
        args = names + [n for row in col_names for n in row]
        self._gen_spheres = tr.function("ur5e_spheres", args, self._sphere_blocks(out, cols))

    def _small_frames(self, q: torch.Tensor) -> torch.Tensor:
        # Few configurations: ~15 whole-matrix ops beat the ~100 vector ops of the
        # generated kernel, whose cost is per-op overhead at this size.
        n = q.shape[0]
        c, s = torch.cos(q), torch.sin(q)
        z, o = torch.zeros_like(c), torch.ones_like(c)
        rz = torch.stack([c, -s, z, z, s, c, z, z, z, z, o, z, z, z, z, o], dim=-1).reshape(n, 6, 4, 4)
        joint_T = self._joint_origin_h @ rz  # (n, 6, 4, 4)
        T = self._root_h.expand(n, 4, 4)
        out = [T]
        for f, j in enumerate(self._joint_of_frame):
            T = T @ (joint_T[:, j] if j >= 0 else self._origin_h[f])
            out.append(T)
        return torch.stack(out, dim=1)  # (n, F, 4, 4)

    def _q6(self, q3: torch.Tensor) -> torch.Tensor:
        return self.full_joints(q3).reshape(-1, 6).to(self.dtype)

    @staticmethod
    def _cos_sin(q: torch.Tensor) -> list:
        return [*torch.cos(q).unbind(-1), *torch.sin(q).unbind(-1)]

    def frames(self, q3: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World poses of every frame (``self.frame_names``) for active angles ``q3``.

        Returns:
            rotations ``(..., F, 3, 3)`` and positions ``(..., F, 3)``.
        """
        self._check_q3(q3)
        q = self._q6(q3)
        n = q.shape[0]
        frames = self._gen_frames(*self._cos_sin(q))
        T = torch.stack([_stack_vec(e, n, q) for e in frames], dim=1)
        T = T.reshape(*q3.shape[:-1], len(frames), 3, 4)
        return T[..., :3], T[..., 3]

    def tcp_pose(self, q3: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotation ``(..., 3, 3)`` and position ``(..., 3)`` of the tcp frame."""
        self._check_q3(q3)
        q = self._q6(q3)
        T = _stack_vec(self._gen_tcp(*self._cos_sin(q)), q.shape[0], q).reshape(*q3.shape[:-1], 3, 4)
        return T[..., :3], T[..., 3]

    def fk(self, q3: torch.Tensor) -> torch.Tensor:
        """TCP position ``(..., 3)`` in the base frame (metres)."""
        self._check_q3(q3)
        q = self._q6(q3)
        n = q.shape[0]
        if n <= self.SMALL_BATCH:
            return self._small_frames(q)[:, -1, :3, 3].reshape(*q3.shape[:-1], 3)
        return _stack_vec(self._gen_tcp_pos(*self._cos_sin(q)), n, q).reshape(*q3.shape[:-1], 3)

    def link_spheres(self, q3: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Centres ``(..., S, 3)`` and radii ``(S,)`` of the collision-sphere cover."""
        centres, _ = self.spheres_and_tcp(q3)
        return centres, self.sphere_radii

    def spheres_and_tcp(self, q3: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Sphere centres ``(..., S, 3)`` and TCP position ``(..., 3)`` from one FK pass."""
        (x, y, z), tcp, _ = self.sphere_coords(q3)
        batch = q3.shape[:-1]
        return torch.stack([x, y, z], dim=-1).reshape(*batch, -1, 3), tcp.reshape(*batch, 3)

    def sphere_coords(self, q3: torch.Tensor) -> tuple[tuple[torch.Tensor, ...], torch.Tensor, torch.Tensor]:
        """Coordinate-major collision geometry, flattened over the batch (the hot-path form).

        Returns:
            ``(x, y, z)`` sphere-centre coordinates, each ``(N, S)`` with ``N`` the
            flattened batch; the TCP ``(N, 3)``; the centre of the gripper's
            bounding sphere ``(N, 3)`` (radius ``gripper_bound_radius``).
        """
        self._check_q3(q3)
        q = self._q6(q3)
        n = q.shape[0]
        if n <= self.SMALL_BATCH:
            T = self._small_frames(q)
            centres = (T[:, self.sphere_frame] @ self._sphere_local_h).squeeze(-1)  # (n, S, 4)
            G = T[:, self._gripper_frame]
            bound = G[:, :3, :3] @ self._gripper_bound_t + G[:, :3, 3]
            return (centres[..., 0], centres[..., 1], centres[..., 2]), T[:, -1, :3, 3], bound
        return self.sphere_coords_from_trig(torch.cos(q), torch.sin(q))

    def joint_trig(self, q3: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Cosines and sines ``(N, 6)`` of the 6 joint angles of ``q3``, flattened over the batch."""
        self._check_q3(q3)
        q = self._q6(q3)
        return torch.cos(q), torch.sin(q)

    def sphere_coords_from_trig(self, cos6: torch.Tensor, sin6: torch.Tensor) -> tuple:
        """:meth:`sphere_coords` from the joints' cosines and sines ``(N, 6)`` (:meth:`joint_trig`).

        The form for a ``torch.compile``'d caller: computed outside it, the trigonometry runs
        once, in ATen's vectorised kernels; traced inside, inductor's CPU code evaluates it
        element by element and again in every loop that reads it.
        """
        if cos6.dim() != 2 or cos6.shape[-1] != 6 or sin6.shape != cos6.shape:
            raise ValueError(f"cos6 and sin6 must both have shape (N, 6), got {tuple(cos6.shape)} and "
                             f"{tuple(sin6.shape)}")
        n = cos6.shape[0]
        coords, tcp, bound = self._gen_spheres(*cos6.unbind(-1), *sin6.unbind(-1), *self._sphere_cols)
        xyz = tuple(
            torch.cat(
                [
                    (b if isinstance(b, torch.Tensor) else cos6.new_full((hi - lo,), b)).expand(n, hi - lo)
                    for b, (_, lo, hi) in zip(blocks, self._sphere_groups)
                ],
                dim=-1,
            )
            for blocks in coords
        )
        return xyz, _stack_vec(tcp, n, cos6), _stack_vec(bound, n, cos6)

    def reference_fk(self, q3: torch.Tensor) -> torch.Tensor:
        """TCP position through pytorch-kinematics' generic chain (slow; for checks)."""
        self._check_q3(q3)
        q = self.full_joints(q3)
        batch = q.shape[:-1]
        chain = self.chain.to(dtype=q.dtype, device=q.device)
        m = chain.forward_kinematics(q.reshape(-1, 6)).get_matrix()
        return m[:, :3, 3].reshape(*batch, 3)
