"""The denoisers under test: :class:`Method`, model specs, kpcn models and OIDN.

Every call into :mod:`kpcn.inference` is in :func:`model_method`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..io import Frame
from .config import OIDN, OIDN_MACS_PER_PX, OIDN_PREFILTERED, ReportConfig, log


@dataclass
class Method:
    """A denoiser under test: ``fn(frame) -> (H, W, 3)`` radiance."""

    name: str
    fn: Callable[[Frame], np.ndarray]
    description: str = ""
    repeats: int = 1
    warmed_up: bool = False
    macs_per_px: float | None = None  #: multiply-adds per pixel (None where unknown)
    macs_source: str = ""  #: where ``macs_per_px`` comes from
    layers: tuple[str, ...] = ("color", "albedo", "normal")  #: the frame layers it reads

    def __call__(self, frame: Frame) -> tuple[np.ndarray, float]:
        """Denoise ``frame``; returns the ``(H, W, 3)`` image and the seconds of the call.

        The first call of a method is preceded by an untimed warm-up call (weights,
        thread pools, OIDN's filter set-up); with ``repeats > 1`` the median is returned.
        """
        if not self.warmed_up:
            self.fn(frame)
            self.warmed_up = True
        times = []
        for _ in range(max(1, self.repeats)):
            t0 = time.perf_counter()
            img = self.fn(frame)
            times.append(time.perf_counter() - t0)
        return np.asarray(img, dtype=np.float32), float(np.median(times))


def parse_model_spec(spec: str) -> tuple[str, str]:
    """``"kpcn"`` -> ``("kpcn", "kpcn")``; ``"a/b.pt"`` -> ``("b", "a/b.pt")``; ``"lbl=x"`` -> ``("lbl", "x")``."""
    if "=" in spec:
        label, value = spec.split("=", 1)
        return label.strip(), value.strip()
    p = Path(spec)
    if p.suffix in (".pt", ".pth", ".ckpt", ".safetensors") or p.exists():
        return p.stem, spec
    return spec, spec


def model_method(spec: str, cfg: ReportConfig) -> Method:
    """A :class:`Method` running :func:`kpcn.inference.denoise` with the model ``spec``."""
    from ..inference import denoise, load_model
    from ..models import macs_per_pixel

    label, value = parse_model_spec(spec)
    value, views = split_views(value)
    model = load_model(value, cfg.device, trust_pickle=cfg.trust_checkpoint)  # loaded once: loading is not timed

    def fn(frame: Frame) -> np.ndarray:
        return denoise(frame, model=model, tile=cfg.tile, device=cfg.device, views=views)

    how = f", the mean of {views} mirrored views" if views > 1 else ""
    counted = "counted from the model (kpcn.models.macs_per_pixel)" + (f", × {views} views" if how else "")
    return Method(label, fn, f"kpcn.denoise with model {value!r} ({model.input_spec.name} inputs{how})", cfg.repeats,
                  macs_per_px=views * macs_per_pixel(model),
                  macs_source=counted,
                  layers=tuple(model.input_spec.layers))


def split_views(value: str) -> tuple[str, int]:
    """``"unet_kpcn@8"`` -> ``("unet_kpcn", 8)``: a model spec's ``@N`` suffix, the views of
    :func:`kpcn.inference.denoise` (1, 2, 4 or 8); ``("unet_kpcn", 1)`` without one."""
    from ..inference.ensemble import VIEWS

    head, sep, tail = value.rpartition("@")
    if sep and tail.isdigit() and head:
        if int(tail) not in VIEWS:
            allowed = f"{', '.join(map(str, VIEWS[:-1]))} or {VIEWS[-1]}"
            raise ValueError(f"model spec {value!r}: @N takes {allowed} mirrored views, got {tail}")
        return head, int(tail)
    return value, 1


def oidn_method(repeats: int = 1) -> Method:
    """OIDN (``hdr=True``, colour + albedo + normal) as a :class:`Method`."""
    from ..baselines import oidn_denoise, oidn_guides, oidn_version

    def fn(frame: Frame) -> np.ndarray:
        return oidn_denoise(frame["color"], *oidn_guides(frame))

    return Method(OIDN, fn, f"Intel Open Image Denoise {oidn_version()} (pyoidn), quality high, hdr, albedo + normal",
                  repeats, macs_per_px=OIDN_MACS_PER_PX,
                  macs_source="approximate: OIDN's RT U-Net counted from its layer list (with noisy albedo and normal "
                             "'high' runs the 'balanced' network; docs/measured.md)")


def oidn_prefiltered_method(repeats: int = 1) -> Method:
    """OIDN with its albedo and normal denoised by its own filters first and passed as clean (``cleanAux``; at quality
    high its larger network): Blender's "Accurate" prefilter, as a :class:`Method`."""
    from ..baselines import oidn_denoise, oidn_guides, oidn_version

    def fn(frame: Frame) -> np.ndarray:
        return oidn_denoise(frame["color"], *oidn_guides(frame), prefilter=True)

    return Method(OIDN_PREFILTERED, fn, f"Intel Open Image Denoise {oidn_version()} (pyoidn), quality high, hdr, "
                  "albedo + normal prefiltered by its own filters (cleanAux)", repeats,
                  macs_source="not counted: OIDN's larger network and its albedo and normal filters")


class MissingLayersError(ValueError):
    """A method needs layers that a scene's renders lack."""


def check_layers(methods: list[Method], frame: Frame, scene: str) -> None:
    """:class:`MissingLayersError` naming each method that needs layers ``frame`` lacks (a Blender
    Cycles render has no variances)."""
    missing = {m.name: [n for n in m.layers if n not in frame.layers] for m in methods}
    missing = {k: v for k, v in missing.items() if v}
    if missing:
        lacks = "; ".join(f"{k} needs {', '.join(v)}" for k, v in missing.items())
        found = ", ".join(sorted(n for n in frame.layers if "." not in n))  # the contract's layers, not the raw passes
        raise MissingLayersError(f"{scene}: {lacks}, which its renders lack (they have {found}). "
                         "For renders without variance layers (Blender Cycles) use models for them, e.g. "
                         "--models kpcn:novar_small kpcn:can_small")


def build_methods(cfg: ReportConfig) -> tuple[list[Method], list[str]]:
    """The methods to evaluate and notes on the ones left out (a model that fails to load, no OIDN)."""
    from ..baselines import oidn_available

    methods, notes = [], []
    for spec in cfg.models:
        try:
            methods.append(model_method(spec, cfg))
        except Exception as exc:
            msg = f"model {spec!r} left out: {type(exc).__name__}: {exc}"
            log.error(msg)
            notes.append(msg)
    if cfg.oidn:
        if oidn_available():
            methods.append(oidn_method(cfg.repeats))
            if cfg.oidn_prefiltered:
                methods.append(oidn_prefiltered_method(cfg.repeats))
        else:
            notes.append("OIDN was not installed (pip install pyoidn): no OIDN rows.")
    return methods, notes
