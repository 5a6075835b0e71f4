"""Behaviour-cloning baselines of the paper's Table 1: BC-SAC-SILP+ and BC-PRM.

    python recipes/bc.py source_run_dir=results/paper_budget/sac_silp_plus/seed0 logger.exp_name=bc_sac_silp_plus
    python recipes/bc.py source=prm logger.exp_name=bc_prm
    python recipes/bc.py source=prm resume=true   # continue a killed run: the demonstrations collected are kept

``n_demos`` demonstration episodes are collected on training tasks of the task
model ``env.name`` (seeded by ``seed``, never the test seed), from a trained
run's evaluated actor rolled out deterministically (``source=policy``) or from
OMPL's PRM (``source=prm``); the transitions of the successful episodes are
kept and cached in ``run_dir/demos.pt`` (batch by batch in ``run_dir/demos_partial/``
while they are collected, so a killed run resumes at its next batch). A demonstration transition holds the
model's named state (root and ``"next"``), the action, what the BC actor reads
(``observation_keys``, built from the named state by
``make_observation_transform``) and the episode's index. The recipes'
deterministic tanh actor is then fitted to the actions with TorchRL's
``BCLoss`` and evaluated on the fixed test tasks of ``evaluate``. The training
wall time counted is collection plus fitting.

``BCLoss`` is used on the deterministic actor with ``loss_function="l2"``
(mean squared error to the demonstrated actions). On the SAC TanhNormal actor
it would fit the negative log-likelihood of those actions instead, which is
unbounded for actions on the edge of the box (clipped planner steps, saturated
policy actions at +-1); and the policy is deterministic at test time anyway.

Writes ``run_dir/summary.json``, ``history.json`` (the periodic evaluations),
``config.yaml`` and ``checkpoint/state.pt``. ``run(cfg)`` returns the summary,
for sweeps that call it in-process. Configuration: ``recipes/config/bc.yaml``
(typed by ``schema.BCConfig``; ranges and choices are checked by the library
where the values are used).
"""

from __future__ import annotations

import os
import shutil
import time
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import hydra
import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from tensordict import NestedKey, TensorDictBase
from torch import optim
from torchrl.envs import Compose, TransformedEnv
from torchrl.objectives import BCLoss

from torchrl_silp import CollisionHandling, ReachEnv
# OMPL is needed only when they are called
from torchrl_silp.baselines import prm_demonstration_batches, prm_demonstration_stats
from torchrl_silp.data import transition_keys
from torchrl_silp.eval import episode_outcomes, evaluate
from torchrl_silp.models.base import as_model
from torchrl_silp.recipes import schema
from torchrl_silp.recipes.builders import (
    make_actor_critic, make_env, make_model, make_observation_transform, observation_keys,
)
from torchrl_silp.recipes.checkpointing import load_trained_networks
from torchrl_silp.recipes.preflight import checkpoint_exists
from torchrl_silp.recipes.metrics import write_results
from torchrl_silp.recipes.start import start_run

schema.register()

SOURCES = ("policy", "prm")
COLLECT_BATCH = 1000  # source=policy: training tasks rolled out at once
# the keys of a demonstration besides transition_keys(model, observation keys): as collect_prm_demonstrations
DEMO_EXTRA_KEYS = ("is_demo", "episode")


# ---------------------------------------------------------------- checks
def check_config(cfg: DictConfig) -> None:
    """What only this recipe can check (the library checks the rest where the values are used).

    ``source``, the recipe's own loop counts, and the source run of ``source=policy``:
    a directory holding ``config.yaml`` and a checkpoint, trained on ``env.name``.
    """
    if cfg.source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {cfg.source!r}")
    for name in ("optim.batch_size", "optim.n_updates", "eval.every_updates", "checkpoint.every_updates"):
        value = OmegaConf.select(cfg, name)
        if value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    if cfg.source != "policy":
        return
    src = cfg.source_run_dir
    if not src:
        raise ValueError("source_run_dir must name a finished training run dir when source=policy, got null")
    src = Path(src)
    if not src.is_dir():
        raise ValueError(f"source_run_dir {str(src)!r} is not a directory")
    if not (src / "config.yaml").is_file():
        raise ValueError(f"source_run_dir {str(src)!r} holds no config.yaml (the run's resolved config)")
    if not checkpoint_exists(src / "checkpoint"):
        raise ValueError(f"source_run_dir {str(src)!r} holds no checkpoint (expected checkpoint/state.pt)")
    trained_on = OmegaConf.select(OmegaConf.load(src / "config.yaml"), "env.name", default=None)
    if trained_on != cfg.env.name:
        raise ValueError(f"source_run_dir {str(src)!r} was trained on env.name={trained_on!r}, "
                         f"this run's env.name is {cfg.env.name!r}")


# -------------------------------------------------------------- demonstrations
def load_source_policy(run_dir: Path, model, device) -> tuple[torch.nn.Module, Compose]:
    """A finished training run's evaluated actor (the averaged one if the run kept it) and what builds its inputs.

    The actor is rebuilt from the run's ``config.yaml`` and loaded from its checkpoint;
    the transform is the run's ``make_observation_transform`` on ``model``.
    """
    run_dir = Path(run_dir)
    source_cfg = OmegaConf.load(run_dir / "config.yaml")
    env = make_env(source_cfg, model, device, seed=0)  # only its specs: no task is drawn from it
    actor, _, _ = load_trained_networks(source_cfg, model, env, run_dir / "checkpoint", device)
    return actor, make_observation_transform(source_cfg, model)


def collect_policy_demonstrations(
    policy,
    model,
    n_episodes: int,
    *,
    seed: int = 0,
    max_steps: int = 50,
    device=None,
    progress: bool = False,
    policy_transform=None,
    observation_transform=None,
    observation_keys: Sequence[NestedKey] = ("observation",),
) -> tuple[TensorDictBase, dict]:
    """Roll ``policy`` out deterministically on ``n_episodes`` training tasks; keep its successful episodes.

    The tasks are those a batched ``ReachEnv(model, num_envs=min(n_episodes, COLLECT_BATCH),
    seed=seed)`` draws on its successive resets, run as ``evaluate`` runs a policy on the
    test tasks (collision type 0: a collision ends the episode). :func:`policy_demonstration_batches`
    gives the same batches one at a time.

    Args:
        policy: reads what ``policy_transform`` builds (the model's flat observation by default).
        model: the task model (or an env holding one).
        n_episodes: tasks attempted.
        seed, max_steps, device, progress: the tasks' seed, the episode length, the env's
            device, a tqdm bar.
        policy_transform: builds the policy's inputs from the named state (its training env's
            observation transforms).
        observation_transform, observation_keys: build what the demonstrations keep for the
            network that learns from them (as in ``collect_prm_demonstrations``).

    Returns:
        ``(demos, stats)``: a flat TensorDict of the transitions of the successful episodes, in
        time order per episode, with the keys of ``transition_keys(model, observation_keys)``,
        ``"is_demo"`` (True) and ``"episode"`` (the episode's index among the ``n_episodes``
        attempted); ``stats`` holds ``n_attempted``, ``n_kept``, ``n_transitions``, ``success_rate``.
    """
    batches = list(policy_demonstration_batches(
        policy, model, n_episodes, seed=seed, max_steps=max_steps, device=device, progress=progress,
        policy_transform=policy_transform, observation_transform=observation_transform,
        observation_keys=observation_keys,
    ))
    demos = torch.cat([d for d, _ in batches])
    return demos, policy_demonstration_stats([b for _, b in batches], demos.shape[0])


def policy_demonstration_batches(
    policy,
    model,
    n_episodes: int,
    *,
    start_episode: int = 0,
    seed: int = 0,
    max_steps: int = 50,
    device=None,
    progress: bool = False,
    policy_transform=None,
    observation_transform=None,
    observation_keys: Sequence[NestedKey] = ("observation",),
) -> Iterator[tuple[TensorDictBase, dict]]:
    """:func:`collect_policy_demonstrations` one batch of ``min(n_episodes, COLLECT_BATCH)`` tasks at a time.

    The arguments are checked and the env built when this is called; the rollouts happen as the
    iterator is consumed.

    Args:
        start_episode: the first task attempted, a multiple of the batch size below ``n_episodes``.
            The env's resets before it are drawn and skipped, so task ``e`` is the one a
            collection from 0 attempts as its ``e``-th: a collection cut after a batch resumes
            at the next.
        the others: as in :func:`collect_policy_demonstrations`.

    Yields:
        ``(demos, batch_stats)`` per batch: the batch's kept transitions (``"episode"`` is the
        task's index in the whole collection) and ``{"n_attempted", "n_kept"}``, the input of
        :func:`policy_demonstration_stats`.
    """
    if isinstance(n_episodes, bool) or not isinstance(n_episodes, int) or n_episodes < 1:
        raise ValueError(f"n_episodes must be a positive int, got {n_episodes!r}")
    batch = min(n_episodes, COLLECT_BATCH)
    if (isinstance(start_episode, bool) or not isinstance(start_episode, int) or start_episode < 0
            or start_episode >= n_episodes or start_episode % batch):
        raise ValueError(f"start_episode must be a multiple of the batch size {batch} below n_episodes={n_episodes}, "
                         f"got {start_episode!r}")
    model = as_model(model)
    base = ReachEnv(model, num_envs=batch, seed=seed, max_steps=max_steps, device=device)
    env = TransformedEnv(
        base,
        Compose(CollisionHandling(0), model.observation_transform() if policy_transform is None else policy_transform),
    )
    build = model.observation_transform() if observation_transform is None else observation_transform
    keys = (*transition_keys(model, observation_keys), *DEMO_EXTRA_KEYS)

    @torch.no_grad()
    def batches() -> Iterator[tuple[TensorDictBase, dict]]:
        for _ in range(start_episode // batch):
            base.sample_tasks(batch)  # what a reset of the whole batch draws
        attempted = start_episode
        with tqdm.tqdm(total=n_episodes, initial=start_episode, disable=not progress, desc="demonstrations") as pbar:
            while attempted < n_episodes:
                _, rollout = evaluate(policy, env=env, return_rollout=True)
                alive, success, _ = episode_outcomes(rollout)
                take = min(batch, n_episodes - attempted)
                success[take:] = False  # the last batch may hold more tasks than are still wanted
                episode = torch.arange(attempted, attempted + batch, device=rollout.device)
                rollout.set("episode", episode.unsqueeze(-1).expand(rollout.batch_size))
                steps = rollout[alive & success.unsqueeze(-1)]  # flat, episode by episode, in time order
                root = steps.select(*model.state_keys, "action", "episode")
                root.set("is_demo", torch.ones(*root.batch_size, 1, dtype=torch.bool, device=root.device))
                nxt = steps.get("next").select(*model.state_keys, "reward", "done", "terminated", "truncated")
                root = build(root)
                root.set("next", build(nxt))
                attempted += take
                pbar.update(take)
                yield root.select(*keys), {"n_attempted": take, "n_kept": int(success.sum())}

    return batches()


def policy_demonstration_stats(batch_stats: Sequence[dict], n_transitions: int) -> dict:
    """The stats of :func:`collect_policy_demonstrations` from its batches' (:func:`policy_demonstration_batches`)."""
    attempted = sum(b["n_attempted"] for b in batch_stats)
    kept = sum(b["n_kept"] for b in batch_stats)
    return {"n_attempted": attempted, "n_kept": kept, "n_transitions": int(n_transitions),
            "success_rate": kept / attempted}


def demonstration_batches(
    cfg: DictConfig, model, device, start_episode: int = 0
) -> Iterator[tuple[TensorDictBase, dict]]:
    """The demonstrations of ``cfg.source``, batch by batch from ``start_episode``: ``(demos, batch_stats)``."""
    common = dict(start_episode=start_episode, seed=cfg.seed, max_steps=cfg.env.max_steps, device=device,
                  progress=cfg.progress, observation_transform=make_observation_transform(cfg, model),
                  observation_keys=observation_keys(cfg))
    if cfg.source == "policy":
        policy, policy_transform = load_source_policy(Path(cfg.source_run_dir), model, device)
        return policy_demonstration_batches(policy, model, cfg.n_demos, policy_transform=policy_transform, **common)
    return prm_demonstration_batches(model, cfg.n_demos, cfg.prm_budget_s, **common)


def demonstration_stats(cfg: DictConfig, batch_stats: Sequence[dict], n_transitions: int, wall_s: float) -> dict:
    """The collection's stats from its batches': those of ``collect_policy_demonstrations`` or
    ``collect_prm_demonstrations``, by ``cfg.source``."""
    if cfg.source == "policy":
        return policy_demonstration_stats(batch_stats, n_transitions)
    return prm_demonstration_stats(batch_stats, n_transitions, wall_s)


def _collection_settings(cfg: DictConfig) -> dict:
    """What the cached demonstrations depend on: a resumed run must ask for the same."""
    out = {"source": cfg.source, "n_demos": cfg.n_demos, "seed": cfg.seed,
           "env": {"name": cfg.env.name, "max_steps": cfg.env.max_steps,
                   "model": OmegaConf.to_container(cfg.env.model, resolve=True)},
           "observation_keys": list(observation_keys(cfg))}
    if cfg.source == "policy":
        out["source_run_dir"] = str(Path(cfg.source_run_dir).resolve())
    else:
        out["prm_budget_s"] = float(cfg.prm_budget_s)
    return out


def _check_settings(cached: dict, settings: dict, path: Path) -> None:
    if cached != settings:
        differ = sorted(k for k in settings if cached.get(k) != settings[k])
        raise ValueError(f"the demonstrations cached in {path} were collected with other {differ}: "
                         f"{ {k: cached.get(k) for k in differ} }; resume with those or resume=false")


def _save_atomic(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def demonstrations(cfg: DictConfig, model, run_dir: Path, device) -> dict:
    """The run's demonstrations: ``run_dir/demos.pt`` when a resumed run has it, else collected now.

    The collection saves each batch to ``run_dir/demos_partial/`` as it comes, so a run killed
    during it resumes (``resume=true``) at its next batch; the whole is then cached in
    ``run_dir/demos.pt`` and the batches removed. ``collection_wall_s`` adds up the wall time of
    the batches kept, whatever sitting collected them (a batch cut by the kill is not counted).
    """
    path, partial = run_dir / "demos.pt", run_dir / "demos_partial"
    settings = _collection_settings(cfg)
    if cfg.resume and path.exists():
        cache = torch.load(path, map_location=device, weights_only=False)
        _check_settings(cache["settings"], settings, path)
        print(f"demonstrations: {cache['stats']['n_kept']} episodes from the cache {path}")
        return cache
    if not cfg.resume:
        shutil.rmtree(partial, ignore_errors=True)
    parts = []
    for file in sorted(partial.glob("batch_*.pt")):
        parts.append(torch.load(file, map_location=device, weights_only=False))
        _check_settings(parts[-1]["settings"], settings, file)
    start = sum(part["stats"]["n_attempted"] for part in parts)
    if parts:
        print(f"demonstrations: {len(parts)} batches ({start} of {cfg.n_demos} episodes) from {partial}; "
              f"collecting the rest")
    if not parts or start < cfg.n_demos:
        batches = demonstration_batches(cfg, model, device, start_episode=start)  # checks the arguments
        partial.mkdir(exist_ok=True)
        tick = time.perf_counter()
        for demos, stats in batches:
            part = {"settings": settings, "demos": demos, "stats": stats, "wall_s": time.perf_counter() - tick}
            _save_atomic(part, partial / f"batch_{len(parts):05d}.pt")
            parts.append(part)
            tick = time.perf_counter()
    demos = torch.cat([part["demos"] for part in parts])
    wall_s = sum(part["wall_s"] for part in parts)
    cache = {"settings": settings, "demos": demos, "collection_wall_s": wall_s,
             "stats": demonstration_stats(cfg, [part["stats"] for part in parts], demos.shape[0], wall_s)}
    _save_atomic(cache, path)
    shutil.rmtree(partial)
    return cache


# ----------------------------------------------------------------- BC policy
def make_bc_actor(cfg: DictConfig, model, device) -> torch.nn.Module:
    """The BC policy: the recipes' deterministic tanh actor (that of DDPG/TD3) on ``cfg.network``,
    reading ``observation_keys(cfg)``."""
    net_cfg = OmegaConf.create({
        "algorithm": "ddpg",
        "network": {"hidden_sizes": list(cfg.network.hidden_sizes), "goal_relative": bool(cfg.network.goal_relative),
                    "next_tcp_feature": False},
    })
    env = make_env(cfg, model, device, seed=0)  # specs only
    actor, _ = make_actor_critic(net_cfg, model, env, device)  # the Q-network is left unused
    return actor


def make_bc_loss(actor) -> BCLoss:
    with warnings.catch_warnings():
        # BCLoss sets an unannotated target-parameter attribute it never uses
        warnings.filterwarnings("ignore", message=".*target_actor_network_params.*")
        return BCLoss(actor, loss_function="l2")


# ----------------------------------------------------------------------- run
def run(cfg: DictConfig) -> dict:
    """Collect (or load) the demonstrations, fit the BC policy, evaluate, checkpoint, report. Returns the summary."""
    check_config(cfg)
    device, run_dir = start_run(cfg)
    ckpt = run_dir / "checkpoint" / "state.pt"
    # everything the library checks is built before the demonstrations are collected
    model = make_model(cfg, device)
    actor = make_bc_actor(cfg, model, device)
    loss = make_bc_loss(actor)
    optimizer = optim.Adam(loss.parameters(), lr=cfg.optim.lr)
    keys = observation_keys(cfg)

    cache = demonstrations(cfg, model, run_dir, device)
    demos, stats, collection_wall_s = cache["demos"], cache["stats"], cache["collection_wall_s"]
    if not demos.shape[0]:  # (a TensorDict's numel() is never below 1)
        raise RuntimeError(f"none of the {stats['n_attempted']} demonstration episodes succeeded: nothing to clone")
    data = demos.select(*keys, "action").to(device)

    sampler = torch.Generator().manual_seed(cfg.seed)  # minibatch indices, on the CPU on every device
    counters = {"updates": 0, "bc_wall_s": 0.0}
    history: list[dict] = []
    if cfg.resume and ckpt.exists():
        state = torch.load(ckpt, map_location=device, weights_only=False)
        loss.load_state_dict(state["loss"])
        optimizer.load_state_dict(state["optimizer"])
        counters, history = state["counters"], state["history"]
        sampler.set_state(state["sampler_rng"])
        torch.set_rng_state(state["torch_rng"])
        print(f"resumed from {ckpt}: {counters['updates']} updates")

    def save():
        ckpt.parent.mkdir(exist_ok=True)
        _save_atomic({"loss": loss.state_dict(), "optimizer": optimizer.state_dict(), "counters": dict(counters),
                      "history": list(history), "sampler_rng": sampler.get_state(),
                      "torch_rng": torch.get_rng_state()}, ckpt)

    def tested(seed: int) -> dict:
        return evaluate(actor, n_tasks=cfg.eval.n_tasks, seed=seed, model=model,
                        observation_transform=make_observation_transform(cfg, model),
                        max_steps=cfg.env.max_steps, device=device)

    def record(bc_loss: float | None) -> dict:
        metrics = tested(cfg.eval.seed)
        point = {"updates": counters["updates"], "train_wall_s": collection_wall_s + counters["bc_wall_s"],
                 "bc_wall_s": counters["bc_wall_s"], "bc_loss": bc_loss, **metrics}
        history.append(point)
        return point

    n = data.shape[0]
    pbar = tqdm.tqdm(total=cfg.optim.n_updates, initial=counters["updates"], disable=not cfg.progress, desc="BC")
    loss_sum, loss_count = torch.zeros((), device=device), 0
    tick = time.perf_counter()
    while counters["updates"] < cfg.optim.n_updates:
        idx = torch.randint(n, (cfg.optim.batch_size,), generator=sampler).to(device)
        value = loss(data[idx])["loss_bc"]
        value.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        loss_sum += value.detach()
        loss_count += 1
        counters["updates"] += 1
        pbar.update(1)
        at_eval = counters["updates"] % cfg.eval.every_updates == 0 or counters["updates"] == cfg.optim.n_updates
        at_save = counters["updates"] % cfg.checkpoint.every_updates == 0
        if at_eval or at_save:
            counters["bc_wall_s"] += time.perf_counter() - tick  # evaluations and saving are not training
            if at_eval:
                point = record((loss_sum / loss_count).item())
                loss_sum, loss_count = torch.zeros((), device=device), 0
                pbar.set_postfix(success=f"{point['success_rate']:.3f}", bc_loss=f"{point['bc_loss']:.4f}")
            save()
            tick = time.perf_counter()
    pbar.close()
    if not history or history[-1]["updates"] != counters["updates"]:
        record(None)
        save()
    validation = history[-1]
    final = tested(cfg.eval.test_seed)  # the test tasks, read once; the curve is the validation one

    summary = {
        "method": cfg.logger.exp_name,
        "env": cfg.env.name,
        "seed": cfg.seed,
        "source": cfg.source,
        "source_run_dir": str(cfg.source_run_dir) if cfg.source == "policy" else None,
        "prm_budget_s": float(cfg.prm_budget_s) if cfg.source == "prm" else None,
        "success_rate": final["success_rate"],
        "test_seed": cfg.eval.test_seed,
        "validation_success_rate": validation["success_rate"],
        "validation_seed": cfg.eval.seed,
        "test_collision_rate": final["collision_rate"],
        "mean_steps": final["mean_steps"],
        "train_wall_s": collection_wall_s + counters["bc_wall_s"],
        "collection_wall_s": collection_wall_s,
        "bc_wall_s": counters["bc_wall_s"],
        "rollout_time_per_episode_s": final["time_per_rollout_s"],
        "n_demos_attempted": stats["n_attempted"],
        "n_demos_kept": stats["n_kept"],
        "n_transitions": stats["n_transitions"],
        "updates": counters["updates"],
        "bc_loss": validation["bc_loss"],
        "episodes": 0,  # BC never interacts with the training env
        "frames": 0,
    }
    write_results(run_dir, summary, history)
    return summary


@hydra.main(version_base="1.3", config_path="config", config_name="bc")
def main(cfg: DictConfig):
    return run(cfg)


if __name__ == "__main__":
    main()
