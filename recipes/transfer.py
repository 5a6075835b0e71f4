"""A trained policy on the MuJoCo twin of its task: the paper's Free, Block and Change scenarios (Fig. 9)
and its reaching test (Table 5) in simulation.

    python recipes/transfer.py checkpoint=results/paper_budget/sac_silp_plus/seed0 scenario=block noise=paper
    python recipes/transfer.py checkpoint=RUN_DIR                 # every scenario x noise level
    python recipes/transfer.py checkpoint=RUN_DIR scenario=pick_place   # the pick-and-place pipeline (Fig. 8)
    python recipes/transfer.py checkpoint=RUN_DIR scenario=reaching     # Table 5: 10 scenarios x 10 trials

Rebuilds the run's actor from its ``config.yaml`` and checkpoint (the parameters
it evaluated), draws the scenario's seeded tasks (``torchrl_silp.sim.scenario_tasks``)
and runs the policy closed-loop on the twin (``torchrl_silp.sim.run_transfer``),
one MuJoCo world per task. Prints success, collisions and time per task for each
scenario and noise level and writes them, with the config, to ``out``.
``run(cfg)`` returns that dict. Configuration: ``recipes/config/transfer.yaml``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_silp.recipes import schema
from torchrl_silp.recipes.builders import make_env, make_model, make_observation_transform
from torchrl_silp.recipes.checkpointing import load_trained_networks
from torchrl_silp.recipes.start import check_device
from torchrl_silp.sim.pick_place import STAGES, pick_place_tasks, run_pick_place
from torchrl_silp.sim.replan import ReplanningPRMPolicy
from torchrl_silp.sim.transfer import NOISE_LEVELS, SCENARIOS, reaching_trials, run_transfer, scenario_tasks

PICK_PLACE = "pick_place"
REACHING = "reaching"  # Table 5's test: fixed scenarios, several trials each

schema.register()


def _choices(name: str, value: str, allowed: tuple) -> list[str]:
    if value == "all":
        return list(allowed)
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed} or 'all', got {value!r}")
    return [value]


def run(cfg: DictConfig) -> dict:
    """Every scenario x noise level of ``cfg`` for the run at ``cfg.checkpoint``; returns the results dict."""
    scenarios = _choices("scenario", cfg.scenario, (*SCENARIOS, PICK_PLACE, REACHING))
    noises = _choices("noise", cfg.noise, tuple(NOISE_LEVELS))
    for name, value, low in (("n_tasks", cfg.n_tasks, 1), ("trials", cfg.trials, 1), ("seed", cfg.seed, 0),
                             ("task_seed", cfg.task_seed, 0), ("threads", cfg.threads, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if (cfg.checkpoint is None) == (cfg.prm_budget_s is None):
        raise ValueError("give one of checkpoint (a trained policy) and prm_budget_s (OMPL's PRM, replanned each "
                         f"control step), got checkpoint={cfg.checkpoint!r}, prm_budget_s={cfg.prm_budget_s!r}")
    check_device(cfg.device)
    device = torch.device(cfg.device)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    if cfg.prm_budget_s is not None:  # the planner needs no checkpoint: the default config's task
        if not (isinstance(cfg.prm_budget_s, (int, float)) and cfg.prm_budget_s > 0):
            raise ValueError(f"prm_budget_s must be a positive number of seconds, got {cfg.prm_budget_s!r}")
        checkpoint_dir = None
        train_cfg = OmegaConf.create({"env": OmegaConf.load(schema.CONFIG_DIR / "env" / "ur5e_reach.yaml"),
                                      "logger": {"exp_name": f"prm_{cfg.prm_budget_s:g}_replanned"}, "seed": cfg.seed})
        model = make_model(train_cfg, device)
        actor, transform, state = None, None, {"counters": {"frames": 0, "episodes": 0}}
    else:
        checkpoint_dir = Path(cfg.checkpoint)
        if not (checkpoint_dir / "config.yaml").exists():
            raise FileNotFoundError(f"checkpoint: {checkpoint_dir} holds no config.yaml (give a training run's directory)")
        train_cfg = OmegaConf.load(checkpoint_dir / "config.yaml")
        model = make_model(train_cfg, device)
        env = make_env(train_cfg, model, device, seed=0)
        actor, _, state = load_trained_networks(train_cfg, model, env, checkpoint_dir / "checkpoint", device)
        transform = make_observation_transform(train_cfg, model)
    max_steps = cfg.max_steps if cfg.max_steps is not None else int(train_cfg.env.max_steps)
    rows = []
    print(f"{'scenario':<8} {'noise':<7} {'success':>8} {'collision':>10} {'steps':>6} {'time to success (s)':>20} "
          f"{'policy ms/step':>15}")
    for scenario in scenarios:
        if scenario == PICK_PLACE:
            if actor is None:  # the pipeline asks its policy for goal positions, the planner needs configurations
                print("pick_place: skipped for the PRM planner")
                continue
            rows += _pick_place_rows(cfg, model, actor, transform, noises, max_steps)
            continue
        if scenario == REACHING:
            tasks = reaching_trials(model, trials=cfg.trials, seed=cfg.task_seed + len(SCENARIOS) + 1)
        else:
            tasks = scenario_tasks(model, scenario, cfg.n_tasks, seed=cfg.task_seed + SCENARIOS.index(scenario))
        for noise in noises:
            tick = time.perf_counter()
            policy = actor if actor is not None else ReplanningPRMPolicy(model, tasks["goal_joint_position"],
                                                                         cfg.prm_budget_s, seed=cfg.seed)
            out = run_transfer(policy, model, tasks, observation_transform=transform, perception=NOISE_LEVELS[noise],
                               control_dt=cfg.control_dt, max_steps=max_steps, seed=cfg.seed)
            ok = out["success"]
            row = {
                "scenario": scenario, "noise": noise, "n_tasks": len(tasks),
                "success_rate": ok.float().mean().item(), "collision_rate": out["collision"].float().mean().item(),
                "mean_steps": out["steps"].float().mean().item(),
                "time_to_success_s": out["time_s"][ok].mean().item() if ok.any() else None,
                "policy_ms_per_step": out["policy_ms_per_step"], "wall_s": time.perf_counter() - tick,
                "perception": dict(vars(NOISE_LEVELS[noise])),
            }
            if scenario == REACHING:  # each scenario's share of its trials (reaching_trials is scenario-major)
                row["scenario_success"] = ok.float().view(-1, cfg.trials).mean(-1).tolist()
            rows.append(row)
            to_success = "—" if row["time_to_success_s"] is None else f"{row['time_to_success_s']:.2f}"
            print(f"{scenario:<8} {noise:<7} {row['success_rate']:>8.3f} {row['collision_rate']:>10.3f} "
                  f"{row['mean_steps']:>6.1f} {to_success:>20} {row['policy_ms_per_step']:>15.3f}")
    # the run's method: its summary's name (a sweep's row name) when it has finished, else its exp_name
    summary = None if checkpoint_dir is None else checkpoint_dir / "summary.json"
    method = json.loads(summary.read_text())["method"] if summary and summary.exists() else str(train_cfg.logger.exp_name)
    if cfg.pictures:
        if actor is None:
            raise ValueError("pictures: draws a trained policy; give checkpoint, not prm_budget_s")
        _pictures(cfg, model, actor, transform, max_steps)
    result = {
        "checkpoint": None if checkpoint_dir is None else str(checkpoint_dir), "method": method,
        "seed": int(train_cfg.seed),
        "trained_frames": state["counters"]["frames"], "trained_episodes": state["counters"]["episodes"],
        "control_dt": cfg.control_dt, "max_steps": max_steps, "task_seed": cfg.task_seed, "rows": rows,
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    parts = [f"{result['method']}_seed{result['seed']}"] + [v for v in (cfg.scenario, cfg.noise) if v != "all"]
    if cfg.out:
        out_path = Path(cfg.out)
    elif cfg.run_dir:  # a sweep's run: its summary.json marks it finished
        out_path = Path(cfg.run_dir) / "summary.json"
    else:
        out_path = Path("results/transfer") / ("_".join(parts) + ".json")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out_path}")
    return result


def _pictures(cfg, model, actor, transform, max_steps) -> None:
    """Frames of the first task of each scenario and of the first pick-and-place trial (no noise), one row each."""
    from torchrl_silp.sim.render import FrameRecorder, save_strip

    import mujoco

    try:
        mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8).close()
    except mujoco.FatalError as err:
        raise RuntimeError("pictures: MuJoCo has no OpenGL context here; on a headless machine run with "
                           "MUJOCO_GL=egl (or osmesa) in the environment") from err
    rows = []
    for scenario in SCENARIOS:
        task = scenario_tasks(model, scenario, cfg.n_tasks, seed=cfg.task_seed + SCENARIOS.index(scenario))[:1]
        recorder = FrameRecorder()
        out = run_transfer(actor, model, task, observation_transform=transform, control_dt=cfg.control_dt,
                           max_steps=max_steps, on_step=recorder)
        verdict = "success" if out["success"].item() else "collision" if out["collision"].item() else "time-out"
        rows.append((f"{scenario}: {verdict}", recorder.frames))
    trial = pick_place_tasks(model, cfg.n_tasks, seed=cfg.task_seed + len(SCENARIOS))[:1]
    recorder = FrameRecorder()
    out = run_pick_place(actor, model, trial, observation_transform=transform, control_dt=cfg.control_dt,
                         max_steps=max_steps, on_step=recorder)
    rows.append((f"pick-and-place: {'placed' if out['place'].item() else 'failed'}", recorder.frames))
    Path(cfg.pictures).parent.mkdir(parents=True, exist_ok=True)
    save_strip(rows, cfg.pictures)
    print(f"wrote {cfg.pictures}")


def _pick_place_rows(cfg, model, actor, transform, noises, max_steps) -> list[dict]:
    """The pick-and-place pipeline's trials at each noise level: the share of trials through each stage."""
    tasks = pick_place_tasks(model, cfg.n_tasks, seed=cfg.task_seed + len(SCENARIOS))
    rows = []
    for noise in noises:
        tick = time.perf_counter()
        out = run_pick_place(actor, model, tasks, observation_transform=transform, perception=NOISE_LEVELS[noise],
                             control_dt=cfg.control_dt, max_steps=max_steps, seed=cfg.seed)
        row = {"scenario": PICK_PLACE, "noise": noise, "n_tasks": len(tasks),
               **{f"{stage}_rate": out[stage].float().mean().item() for stage in STAGES},
               "success_rate": out["place"].float().mean().item(),
               "collision_rate": out["collision"].float().mean().item(), "wall_s": time.perf_counter() - tick,
               "perception": dict(vars(NOISE_LEVELS[noise]))}
        rows.append(row)
        print(f"{PICK_PLACE:<10} {noise:<7} " + "  ".join(f"{s} {row[s + '_rate']:.3f}" for s in STAGES)
              + f"  collision {row['collision_rate']:.3f}")
    return rows


@hydra.main(version_base="1.3", config_path="config", config_name="transfer")
def main(cfg):
    return run(cfg)


if __name__ == "__main__":
    main()
