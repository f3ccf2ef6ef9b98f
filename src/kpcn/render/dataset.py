"""Rendering data sets: noisy inputs at several sample counts and a reference per scene."""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from ..io import atomic_write
from .frame import render_to_exr
from .scene import load_scene


@dataclass
class DatasetConfig:
    """What ``python -m kpcn.render dataset`` renders (``--config FILE``, ``--set key=value`` or the flags)."""

    out: str = "data/train"  #: the data set folder (manifest.json, one folder per scene)
    scenes: int = 16  #: procedural scenes random:<first_seed> ... random:<first_seed + scenes - 1>
    first_seed: int = 0
    spp: list[int] = field(default_factory=lambda: [2, 4, 8, 16, 32])  #: input sample counts
    ref_spp: int = 1024
    resolution: tuple[int, int] = (128, 128)  #: (width, height)

    def __post_init__(self) -> None:
        from ..config import ConfigError

        if self.scenes < 1:
            raise ConfigError(f"scenes: must be >= 1, got {self.scenes}")
        if not self.spp or min(self.spp) < 2 or self.ref_spp < 2:
            raise ConfigError(f"spp and ref_spp: every sample count must be >= 2 (variances need two), got "
                              f"spp={self.spp}, ref_spp={self.ref_spp}")
        if min(self.resolution) < 1:
            raise ConfigError(f"resolution: width and height must be >= 1, got {list(self.resolution)}")


def render_dataset(
    out_dir: str | os.PathLike,
    n_scenes: int,
    spp_list: Sequence[int] = (2, 4, 8, 16, 32),
    ref_spp: int = 1024,
    resolution: tuple[int, int] = (128, 128),
    first_seed: int = 0,
    scenes: Sequence[Any] | None = None,
    progress: bool = True,
) -> Path:
    """Render procedural scenes (or ``scenes``) into ``out_dir`` with a manifest.

    Layout: ``out_dir/<scene>/input_<spp>spp.exr`` for each input spp, and
    ``out_dir/<scene>/reference.exr``; ``out_dir/manifest.json`` lists them.
    Frames already on disk are kept (an interrupted run resumes).
    """
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    items = list(scenes) if scenes is not None else [f"random:{first_seed + i}" for i in range(n_scenes)]
    manifest = {"ref_spp": int(ref_spp), "spp": [int(s) for s in spp_list], "resolution": list(resolution), "scenes": []}
    for i, sc in enumerate(tqdm(items, desc="render", disable=not progress)):
        sname = f"scene_{i:04d}" if isinstance(sc, dict) else str(sc).replace(":", "_").replace("/", "_")
        folder = out / sname
        folder.mkdir(exist_ok=True)
        seed = first_seed + i
        # role 1 = reference; each input spp gets a role of its own so no two frames share noise
        jobs = [(s, folder / f"input_{s}spp.exr", 2 + s) for s in spp_list] + [(ref_spp, folder / "reference.exr", 1)]
        loaded = None
        for s, path, role in jobs:
            if path.exists():  # resume: keep what an earlier run finished
                continue
            loaded = loaded or load_scene(sc, resolution)
            render_to_exr(sc, path, s, seed=seed, role=role, loaded=loaded)
        manifest["scenes"].append({
            "name": sname,
            "source": sc if isinstance(sc, str) else "dict",
            "seed": seed,
            "inputs": {str(s): str(p.relative_to(out)) for s, p, role in jobs if role != 1},
            "reference": str(jobs[-1][1].relative_to(out)),
        })
        atomic_write(out / "manifest.json", lambda tmp: Path(tmp).write_text(json.dumps(manifest, indent=1)))
    return out
