"""Figures: ``error_vs_time.png`` and ``contact_sheet.png`` (matplotlib, Agg backend, imported on use)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..io import atomic_write
from ..metrics import tonemap
from .config import MC


def _method_colors(methods: Sequence[str]) -> dict[str, str]:
    fixed = {MC: "black", "oidn": "tab:green", "oidn_prefiltered": "tab:olive", "kpcn": "tab:blue",
             "dpcn": "tab:orange"}
    spare = iter(["tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:cyan", "tab:gray"])
    return {m: fixed.get(m) or next(spare, "tab:gray") for m in methods}


def _save_fig(fig, path: Path, dpi: int = 110) -> None:
    import matplotlib.pyplot as plt

    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png"))
    plt.close(fig)


def _log_axes(ax) -> None:
    """Log-log axes with plain numbers (``0.03``): at 1×, 2× and 5× each decade, every tick on short ranges."""
    from matplotlib.ticker import FuncFormatter

    def formatter(axis):
        def fmt(v, _pos):
            lo, hi = sorted(axis.get_view_interval())
            if v <= 0:
                return ""
            mant = v / 10 ** math.floor(math.log10(v) + 1e-9)
            short = lo > 0 and math.log10(hi / lo) < 0.6
            return f"{v:.3g}" if short or any(abs(mant - m) < 1e-6 for m in (1, 2, 5)) else ""

        return FuncFormatter(fmt)

    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(formatter(axis))
        axis.set_minor_formatter(formatter(axis))
    ax.tick_params(which="minor", labelsize=7)


def plot_error_vs_time(path: Path, rows: Sequence[dict], means: Sequence[dict], floor_factor: float | None = None) -> None:
    """Log-log relMSE against total seconds; one panel per scene plus the mean; one line per method.

    With ``floor_factor``, a dashed line in each scene's panel at that multiple of the reference's noise
    (rows' ``ref_floor``): errors below it are not resolved by the reference.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colors = _method_colors(methods)
    panels = [(s, [r for r in rows if r["scene"] == s]) for s in scenes] + [(f"mean over {len(scenes)} scenes", list(means))]
    ncol = min(3, len(panels))
    nrow = math.ceil(len(panels) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.6 * nrow), squeeze=False)
    for ax, (title, rs) in zip(axes.flat, panels):
        for m in methods:
            pts = sorted((r for r in rs if r["method"] == m), key=lambda r: r["spp"])
            if not pts:
                continue
            x = [max(r["total_s"], 1e-4) for r in pts]
            y = [max(r["relmse"], 1e-8) for r in pts]
            ax.plot(x, y, "o-", color=colors[m], label=m, ms=3.5, lw=1.4)
            if m == MC:
                for r, xi, yi in zip(pts, x, y):
                    ax.annotate(str(r["spp"]), (xi, yi), textcoords="offset points", xytext=(3, 3), fontsize=7)
        floors = {r.get("ref_floor") for r in rs if r.get("ref_floor")} if title in scenes else set()
        if floor_factor and len(floors) == 1:
            ax.axhline(floor_factor * floors.pop(), color="gray", ls="--", lw=0.9,
                       label=f"{floor_factor:g}× reference noise")
        _log_axes(ax)
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xlabel("total seconds (render + denoise)")
        ax.set_ylabel("relMSE")
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    fig.suptitle("Error against run time (numbers: spp of raw MC)", fontsize=11)
    fig.tight_layout()
    _save_fig(fig, path)


def _center_crop(img: np.ndarray, size: int) -> np.ndarray:
    h, w = img.shape[:2]
    ch, cw = min(size, h), min(size, w)
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    return img[y0 : y0 + ch, x0 : x0 + cw]


def contact_sheet(path: Path, images: dict[str, dict[str, np.ndarray]], rows: Sequence[dict], spp: int, crop: int) -> None:
    """Tone-mapped centre crops: one row per scene; columns noisy, each method, reference (at ``spp``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(images)
    cols = [MC] + [m for m in dict.fromkeys(r["method"] for r in rows) if m != MC] + ["reference"]
    err = {(r["scene"], r["method"]): r["relmse"] for r in rows if r["spp"] == spp}
    fig, axes = plt.subplots(len(scenes), len(cols), figsize=(2.0 * len(cols), 2.4 * len(scenes)), squeeze=False)
    for i, s in enumerate(scenes):
        for j, c in enumerate(cols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            img = images[s].get(c)
            if img is None:
                ax.axis("off")
                continue
            ax.imshow(tonemap(_center_crop(img, crop)), interpolation="nearest")
            label = {MC: f"noisy {spp} spp", "reference": "reference"}.get(c, c)
            e = err.get((s, c))
            ax.set_title(label + (f"\nrelMSE {e:.3g}" if e is not None else ""), fontsize=8)
            if j == 0:
                ax.set_ylabel(s, fontsize=8)
    fig.tight_layout()
    _save_fig(fig, path)
