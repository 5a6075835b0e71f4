"""Env throughput: EnvBase.step, the raw batched task model, the Gymnasium env, and MuJoCo as the peer.

Prints steps (transitions) per second for batch 1, 1024 and 16384:

* ``EnvBase.step``: ``step_and_maybe_reset`` of ``UR5eReachEnv`` as a TorchRL collector calls it;
* the raw task model (:class:`~torchrl_silp.models.UR5eReach`, no TorchRL bookkeeping):
  ``transition`` (the kinematic model f_s) alone; ``step`` (f_s and f_r in one pass: FK,
  sphere cover, obstacle / table / self / workspace checks of the swept motion, up to
  ``ceil(0.125 / motion_resolution) + 1`` configurations per step); and
  ``collision_flags`` of one configuration per state (configurations per second);
* the Gymnasium env (unbatched, batch 1 only);
* MuJoCo on the same URDF's collision primitives plus the box and the table
  plane: set qpos, ``mj_kinematics`` + ``mj_collision``, one configuration at a
  time in a Python loop (single thread) — the peer of ``collision_flags`` on one
  configuration (``vs MuJoCo`` compares those two rates).

Each figure is run eager and with ``compile_collision=True`` (the collision
kernel fused by ``torch.compile``). Run:

    python benchmarks/env_throughput.py            # full table
    python benchmarks/env_throughput.py --quick    # smaller repeat counts
    python benchmarks/env_throughput.py --quick --batch-sizes 1 64 --no-compile --mujoco-configs 1000
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
import torch

from torchrl_silp import UR5eReachEnv
from torchrl_silp.models import UR5eReach
from torchrl_silp.robots import default_urdf_path


def timed(fn, min_time: float, min_reps: int = 3, device: torch.device = torch.device("cpu")) -> float:
    """Seconds per call: warm up for ``min_time`` (at least one call), then repeat until ``min_time`` has passed.

    The warm-up is that long because a compiled step meets new sizes for a while: its
    swept-motion check samples a number of configurations set by the step's largest joint
    move, padded to a power of two, one compilation per size; timing them would count compilations.
    """
    # a CUDA call returns once its kernels are queued: wait for them before reading the clock
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    start = time.perf_counter()
    fn()
    while time.perf_counter() - start < min_time:
        fn()
    sync()
    reps, start = 0, time.perf_counter()
    while True:
        fn()
        reps += 1
        sync()
        elapsed = time.perf_counter() - start
        if elapsed >= min_time and reps >= min_reps:
            return elapsed / reps


def bench_envbase(env: UR5eReachEnv, min_time: float) -> float:
    td = env.reset()
    gen = torch.Generator().manual_seed(0)
    actions = (torch.rand(64, *env.batch_size, env.model.action_dim, generator=gen) * 2 - 1).to(env.device)
    state = {"td": td, "i": 0}

    def one():
        td = state["td"]
        td["action"] = actions[state["i"] % 64]
        state["i"] += 1
        _, state["td"] = env.step_and_maybe_reset(td)

    return env.batch_size.numel() / timed(one, min_time, device=env.device)


def bench_model(model: UR5eReach, batch: int, kind: str, min_time: float) -> float:
    """States (or configurations) per second of ``model.transition``, ``model.step`` or ``model.collision_flags``."""
    gen = torch.Generator(device=model.device).manual_seed(0)
    state = model.sample_tasks(batch, gen).select(*model.state_keys)
    action = torch.rand(batch, model.action_dim, generator=gen, device=model.device) * 2 - 1
    scene = state.select(*model.scene_keys)
    config = state.get(model.config_key)
    calls = {
        "transition": lambda: model.transition(state, action),
        "step": lambda: model.step(state, action),
        "collision_flags": lambda: model.collision_flags(config, scene),
    }
    return batch / timed(calls[kind], min_time, device=model.device)


def bench_gym(min_time: float) -> float:
    import gymnasium as gym

    import torchrl_silp  # noqa: F401  (registers the id)

    env = gym.make("torchrl_silp/UR5eReach-v0")
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def one():
        _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 3).astype(np.float32))
        if terminated or truncated:
            env.reset()

    return 1.0 / timed(one, min_time)


def bench_mujoco(n: int) -> tuple[float, int]:
    import mujoco

    spec = mujoco.MjSpec.from_file(default_urdf_path())
    # links without inertials need bounds to compile (collision only; nothing is simulated)
    spec.compiler.boundmass = 1e-3
    spec.compiler.boundinertia = 1e-6
    box = spec.worldbody.add_body(name="obstacle", mocap=True, pos=[0.5, 0.25, 0.15])
    box.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.1, 0.1, 0.15])
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[2, 2, 0.1])
    model = spec.compile()
    data = mujoco.MjData(model)
    task_model = UR5eReach()
    tasks = task_model.sample_tasks(n, torch.Generator().manual_seed(0))
    qpos = task_model.robot.full_joints(tasks[task_model.config_key]).double().numpy()
    centres = ((tasks["obstacle"][:, 0::2] + tasks["obstacle"][:, 1::2]) / 2).double().numpy()
    contacts = 0
    start = time.perf_counter()
    for i in range(n):
        data.qpos[:] = qpos[i]
        data.mocap_pos[0] = centres[i]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        contacts += data.ncon
    return n / (time.perf_counter() - start), model.ngeom


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="shorter timing windows")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 1024, 16384])
    parser.add_argument("--no-compile", action="store_true", help="skip the compiled variant")
    parser.add_argument("--mujoco-configs", type=int, default=None,
                        help="configurations MuJoCo checks (default 100000, 20000 with --quick; 0: no MuJoCo row)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--device", default="cpu", help="where the envs and the model run (MuJoCo runs on the CPU)")
    args = parser.parse_args()
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    min_time = 0.5 if args.quick else 2.0
    load = os.getloadavg()[0]
    where = f", {torch.cuda.get_device_name(device)}" if device.type == "cuda" else ""
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {platform.processor() or platform.machine()}"
          f"{where}, device {device}"
          f"{'' if load < 0.5 else f' (not alone: load average {load:.1f})'}")

    if args.mujoco_configs is not None and args.mujoco_configs < 0:
        parser.error(f"--mujoco-configs must be >= 0, got {args.mujoco_configs}")
    n_mujoco = (20_000 if args.quick else 100_000) if args.mujoco_configs is None else args.mujoco_configs
    mj_rate = float("nan")
    if n_mujoco:
        mj_rate, ngeom = bench_mujoco(n_mujoco)
        print(f"MuJoCo mj_kinematics + mj_collision ({ngeom} geoms), Python loop, 1 thread: {mj_rate:,.0f} configs/s")
    else:
        print("MuJoCo: not measured (--mujoco-configs 0)")
    gym_rate = bench_gym(min_time)
    print(f"Gymnasium env (batch 1): {gym_rate:,.0f} steps/s ({1e6 / gym_rate:.0f} us/step)")

    variants = [("eager", False)] + ([] if args.no_compile else [("compiled", True)])
    header = (f"{'variant':9s} {'batch':>6s} {'EnvBase.step':>14s} {'transition':>14s} {'model.step':>14s} "
              f"{'configs/s':>14s} {'vs MuJoCo':>10s}")
    print(header)
    print("-" * len(header))
    for name, compiled in variants:
        for b in args.batch_sizes:
            env = UR5eReachEnv(batch_size=(b,), seed=0, compile_collision=compiled, device=device)
            model = env.model
            step = bench_envbase(env, min_time)
            trans = bench_model(model, b, "transition", min_time)
            fused = bench_model(model, b, "step", min_time)
            configs = bench_model(model, b, "collision_flags", min_time)
            print(
                f"{name:9s} {b:6d} {step:14,.0f} {trans:14,.0f} {fused:14,.0f} {configs:14,.0f} {configs / mj_rate:9.1f}x"
                f"   (one step {1e6 * b / step:,.0f} us)"
            )


if __name__ == "__main__":
    main()
