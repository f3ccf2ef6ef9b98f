"""Run configuration: dataclasses loaded from YAML, with command-line overrides.

One parser serves every command (as in OIDN's training scripts)::

    python -m kpcn.train --config configs/small.yaml --set train.lr=3e-4 --name exp1

``--set section.field=value`` overrides one field (values parsed as YAML). The
resolved config is saved as ``results/<name>/config.yaml`` beside every result.
"""
from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml


@dataclass
class ModelConfig:
    name: str = "kpcn"  #: registry name (kpcn, dpcn, ...)
    layers: int = 9
    width: int = 100
    conv_size: int = 5
    kernel_size: int = 21  #: k of the predicted k×k kernels (KPCN only)
    extra: dict = field(default_factory=dict)  #: further keyword arguments for the model


@dataclass
class DataConfig:
    root: str = "data/train"  #: folder written by `python -m kpcn.render dataset`
    val_root: str | None = None  #: held-out frames; None: the last `val_scenes` scenes of root
    val_scenes: int = 2
    spp: list[int] | None = None  #: input spp to train on (None: all)
    patch_size: int = 65
    patches_per_frame: int | None = None  #: None: the paper's 400 per 1280×720, scaled by area
    sampling: str = "importance"
    # the built-in default data set, rendered when `root` has no manifest and `render_if_missing`
    render_if_missing: bool = True
    render_scenes: int = 24
    render_spp: list[int] = field(default_factory=lambda: [2, 4, 8, 16, 32])
    render_ref_spp: int = 1024
    render_resolution: list[int] = field(default_factory=lambda: [128, 128])
    render_first_seed: int = 0


@dataclass
class TrainConfig:
    stage1_steps: int = 1000  #: diffuse and specular branches on their own targets
    stage2_steps: int = 500  #: joint fine-tuning on the final colour
    batch_size: int = 4
    lr: float = 1e-5
    stage2_lr: float | None = None  #: None: same as lr
    loss: str = "l1"
    stage2_loss: str | None = None  #: None: same as loss
    grad_clip: float = 1.0
    val_every: int = 250
    ckpt_every: int = 100
    log_every: int = 10
    seed: int = 0
    threads: int | None = None  #: torch CPU threads (None: PyTorch's default)
    device: str = "auto"  #: auto, cpu or cuda


@dataclass
class Config:
    name: str = "default"
    results_dir: str = "results"
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    @property
    def run_dir(self) -> Path:
        return Path(self.results_dir) / self.name

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _coerce(cls, name: str, value):
    """YAML 1.1 reads ``3e-3`` as a string: convert values for float fields."""
    ann = str(next(f.type for f in dataclasses.fields(cls) if f.name == name))
    if "float" in ann and isinstance(value, (str, int)) and not isinstance(value, bool):
        try:
            return float(value)
        except ValueError:
            raise ValueError(f"{cls.__name__}.{name}: expected a number, got {value!r}") from None
    return value


def _from_dict(cls, data: dict):
    if data is None:
        return cls()
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown field(s) {sorted(unknown)}; known: {sorted(names)}")
    kwargs = {}
    for key, value in data.items():
        sub = {"model": ModelConfig, "data": DataConfig, "train": TrainConfig}.get(key) if cls is Config else None
        kwargs[key] = _from_dict(sub, value) if sub else _coerce(cls, key, value)
    return cls(**kwargs)


def config_from_dict(data: dict) -> Config:
    return _from_dict(Config, data or {})


def apply_override(cfg: Config, assignment: str) -> None:
    """Apply ``section.field=value`` (value parsed as YAML) to ``cfg`` in place."""
    if "=" not in assignment:
        raise ValueError(f"override {assignment!r} is not of the form section.field=value")
    key, raw = assignment.split("=", 1)
    target: Any = cfg
    parts = key.strip().split(".")
    for p in parts[:-1]:
        if not hasattr(target, p):
            raise ValueError(f"override {key!r}: no section {p!r}")
        target = getattr(target, p)
    last = parts[-1]
    value = yaml.safe_load(raw)
    if isinstance(target, dict):
        target[last] = value
        return
    if last not in {f.name for f in dataclasses.fields(target)}:
        raise ValueError(f"override {key!r}: {type(target).__name__} has no field {last!r}")
    setattr(target, last, _coerce(type(target), last, value))


def load_config(path: str | Path | None = None, overrides: list[str] | None = None, name: str | None = None) -> Config:
    """Read a YAML config (or the defaults), apply ``overrides`` and ``name``."""
    data = {}
    if path is not None:
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"config not found: {p}")
        data = yaml.safe_load(p.read_text()) or {}
    cfg = config_from_dict(data)
    if name is None and path is not None and "name" not in data:
        cfg.name = Path(path).stem
    for o in overrides or []:
        apply_override(cfg, o)
    if name:
        cfg.name = name
    return cfg


def save_config(cfg: Config, path: str | Path) -> None:
    from .io import atomic_write

    text = yaml.safe_dump(cfg.to_dict(), sort_keys=False)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def make_parser(description: str, prog: str | None = None) -> argparse.ArgumentParser:
    """The argument parser shared by kpcn's commands (config file, overrides, run name)."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("--config", "-c", help="YAML config file (see configs/)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override one config field; may be repeated")
    p.add_argument("--name", help="run name: results go to <results_dir>/<name>")
    p.add_argument("--results-dir", help="parent folder of run folders (default: results)")
    return p


def config_from_args(args: argparse.Namespace) -> Config:
    cfg = load_config(args.config, args.overrides, args.name)
    if getattr(args, "results_dir", None):
        cfg.results_dir = args.results_dir
    return cfg
