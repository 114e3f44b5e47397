"""The jobs behind ``run`` and ``eval``: compose, build, train, evaluate, write the run folder."""

from __future__ import annotations

import hashlib
import platform
import sys
import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from gpnerf_core.build import build_components, resolve_device
from gpnerf_core.errors import GpnerfError
from gpnerf_core.io import atomic_write_json, atomic_write_text


def _run_dir(cfg: DictConfig) -> Path:
    if cfg.out_dir:
        return Path(cfg.out_dir)
    from hydra.core.hydra_config import HydraConfig

    return Path(HydraConfig.get().runtime.output_dir)


def _machine() -> dict[str, Any]:
    import os

    return {
        "platform": platform.platform(),
        "processor": platform.machine(),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }


def _prepare(cfg: DictConfig) -> tuple[Path, torch.device, str]:
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    device = resolve_device(cfg.device)
    run_dir = _run_dir(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    config_yaml = OmegaConf.to_yaml(cfg, resolve=True)
    atomic_write_text(run_dir / "config.yaml", config_yaml)
    atomic_write_text(run_dir / "config.sha256", hashlib.sha256(config_yaml.encode()).hexdigest() + "\n")
    from gpnerf_core.registry import get_registry

    registry = get_registry()
    atomic_write_json(
        run_dir / "plugins.json",
        {
            "components": [
                {"kind": e.kind, "name": e.spec.name, "provider": e.provider, "version": e.version}
                for entries in registry.components.values()
                for e in entries.values()
            ],
            "problems": [{"plugin": p, "reason": r} for p, r in registry.problems],
        },
    )
    return run_dir, device, config_yaml


def _guarded(job):
    """Turn user-facing errors into one line on stderr and exit code 2 (Hydra would print a traceback)."""

    def wrapper(cfg: DictConfig) -> Any:
        try:
            return job(cfg)
        except GpnerfError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)

    wrapper.__name__ = job.__name__
    return wrapper


@_guarded
def run_task(cfg: DictConfig) -> dict[str, Any]:
    from gpnerf_core.evaluation.evaluator import evaluate, print_summary
    from gpnerf_core.evaluation.visualize import plot_training_curves
    from gpnerf_core.training.trainer import Trainer

    run_dir, device, config_yaml = _prepare(cfg)
    components = build_components(cfg)
    trainer = Trainer(cfg, components, device, run_dir, config_yaml)
    started = time.perf_counter()
    result = trainer.fit(progress=True)
    atomic_write_json(run_dir / "training_curves.json", result.history)
    if result.history:
        loss_keys = [k for k in result.history[-1] if k not in ("step", "seconds") and not k.startswith("lr_")]
        plot_training_curves(result.history, run_dir / "training_curves.png", loss_keys=loss_keys)
    evaluation = evaluate(cfg, components, trainer.views, device, run_dir)
    metrics = {
        "config_sha256": (run_dir / "config.sha256").read_text().strip(),
        "seed": int(cfg.seed),
        "machine": _machine(),
        "train": {
            "steps": result.steps,
            "seconds": round(result.seconds, 2),
            "rays_per_second": round(result.rays_per_second, 1),
            "final_loss": result.history[-1]["loss"] if result.history else None,
            "checkpoint": str(result.checkpoint) if result.checkpoint else None,
        },
        **evaluation,
        "wall_seconds": round(time.perf_counter() - started, 2),
    }
    atomic_write_json(run_dir / "metrics.json", metrics)
    print_summary(metrics, run_dir)
    return metrics


@_guarded
def eval_task(cfg: DictConfig) -> dict[str, Any]:
    from gpnerf_core.evaluation.evaluator import evaluate, print_summary
    from gpnerf_core.training.checkpoint import load_checkpoint
    from gpnerf_core.views import SceneViews

    checkpoint = Path(cfg.checkpoint)
    run_dir, device, _ = _prepare(cfg)
    components = build_components(cfg)
    state = load_checkpoint(checkpoint, components.model)
    components.model.to(device)
    evaluation = evaluate(cfg, components, SceneViews(components.dataset, device), device, run_dir)
    metrics = {"checkpoint": str(checkpoint), "checkpoint_step": state["step"], "machine": _machine(), **evaluation}
    atomic_write_json(run_dir / "metrics.json", metrics)
    print_summary(metrics, run_dir)
    return metrics
