"""What every recipe does first: the device, torch's threads, the seeds, the run directory and its config."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from torchrl_silp.recipes.preflight import check_run_folder
from torchrl_silp.recipes.schema import check_device
from torchrl_silp.recipes.update import check_compile


def resolve_device(cfg) -> torch.device:
    """``cfg.device`` checked and resolved ("auto": CUDA when there is one)."""
    check_device(cfg.device)
    return torch.device(("cuda" if torch.cuda.is_available() else "cpu") if cfg.device == "auto" else cfg.device)


def start_run(cfg, write_config: bool = True) -> tuple[torch.device, Path]:
    """What every recipe does first: ``(device, run_dir)``.

    Resolves ``cfg.device`` ("auto": CUDA when there is one), checks what ``cfg`` asks of its
    run folder (:func:`~torchrl_silp.recipes.preflight.check_run_folder`: a fresh start never
    lands on a checkpoint, a resume matches the checkpointed run's config), sets torch's threads
    (``cfg.threads``, 0 leaves the default), seeds torch, numpy and ``random`` with ``cfg.seed``.
    With ``write_config``, then creates ``cfg.run_dir`` and saves the resolved config there
    (:func:`write_run_config`); a recipe that builds more checked objects first passes False and
    writes it once they are built, so that a refused value leaves the folder untouched.
    """
    device = resolve_device(cfg)
    check_compile(cfg, device)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    check_run_folder(cfg)
    run_dir = Path(cfg.run_dir)
    if write_config:
        write_run_config(cfg)
    return device, run_dir


def write_run_config(cfg) -> Path:
    """Create ``cfg.run_dir`` and save the resolved config there as ``config.yaml``: what rebuilds a run's
    networks from its checkpoint (``load_trained_networks``) and what a report cites."""
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml", resolve=True)
    return run_dir
