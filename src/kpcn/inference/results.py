"""What a denoise call returns: the colour, the other denoised layers, and what was done (:class:`DenoiseStats`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["DenoiseStats", "DenoiseResult", "peak_rss_mb"]


@dataclass
class DenoiseStats:
    """What one :func:`denoise_result` call did and how long it took.

    Attributes:
        seconds: wall time of the denoising (inputs, network, assembly), without reading or writing files.
        read_seconds, write_seconds: time spent reading the input / writing the output EXR.
        size: ``(H, W)`` of the frame.
        tile, halo, alignment: interior tile size, halo and crop alignment in pixels.
        tiles: number of tiles; tiles_run: tiles on which at least one branch ran.
        tiles_passed_through: no-hit, converged tiles whose output is the noisy colour.
        tiles_zero: tiles with every branch zero (output exactly 0; nothing run).
        tiles_fp32_fallback: ``half=True`` only: tiles re-run in float32 because float16 overflowed.
        branches_skipped: branches not run anywhere because their colour is zero over the whole frame.
        branch_tiles_run / branch_tiles_skipped: per branch, tiles on which it ran / was left out.
        frame_context_seconds: time spent on the whole-frame context (models that use one).
        device: where the network ran.
        peak_rss_mb: the process's peak resident memory after the call (an upper bound for this call).
        peak_cuda_mb: peak CUDA memory allocated by torch during the call (CUDA only).
        nonfinite: NaN/Inf values replaced per layer (by the reader or here).
        noise_precision: the frame's estimated noise precision (:mod:`kpcn.noise`) for models whose
            input spec reads it; None otherwise.
        precision: the dtype the model's hidden layers ran in (``float32`` or ``bfloat16``;
            :mod:`kpcn.inference.precision`).
        row_bands: the whole frame was run a band of rows at a time (:mod:`kpcn.inference.rows`), in
            this many bands; 0: it was not.
        detail_radius: the radius of the normal-guided detail stage run after the network
            (:mod:`kpcn.inference.detail`); 0: none was run. detail_seconds: its wall time (part of ``seconds``).
        exposure_key: the frame's exposure key (:func:`kpcn.exposure.frame_key`) for a model with an
            ``exposure_range``; None otherwise. exposure_scale: the factor its radiance was denoised at (1.0: its own).
        sample_count: ``(least, most)`` samples of a pixel, for a frame with a ``sampleCount`` layer (its spp
            varies per pixel); None otherwise.
        views: how many mirrored copies of the frame were denoised and averaged (:mod:`kpcn.inference.ensemble`);
            the other fields are the first view's, ``seconds`` and ``detail_seconds`` the sums over all.
    """

    seconds: float = 0.0
    read_seconds: float = 0.0
    write_seconds: float = 0.0
    size: tuple[int, int] = (0, 0)
    tile: int = 0
    halo: int = 0
    alignment: int = 1
    tiles: int = 0
    tiles_run: int = 0
    tiles_passed_through: int = 0
    tiles_zero: int = 0
    tiles_fp32_fallback: int = 0
    precision: str = "float32"
    branches_skipped: tuple[str, ...] = ()
    branch_tiles_run: dict[str, int] = field(default_factory=dict)
    branch_tiles_skipped: dict[str, int] = field(default_factory=dict)
    frame_context_seconds: float = 0.0
    device: str = "cpu"
    peak_rss_mb: float | None = None
    peak_cuda_mb: float | None = None
    nonfinite: dict[str, int] = field(default_factory=dict)
    noise_precision: float | None = None
    row_bands: int = 0
    detail_radius: int = 0
    detail_seconds: float = 0.0
    exposure_key: float | None = None
    exposure_scale: float = 1.0
    sample_count: tuple[float, float] | None = None
    views: int = 1

    def summary(self) -> str:
        h, w = self.size
        parts = [f"{w}x{h}", f"{self.seconds:.2f} s", self.precision, f"tiles run {self.tiles_run}/{self.tiles}"]
        if self.row_bands:
            parts.append(f"in {self.row_bands} row bands")
        if self.tiles_passed_through:
            parts.append(f"passed through {self.tiles_passed_through}")
        if self.tiles_zero:
            parts.append(f"zero {self.tiles_zero}")
        if self.branches_skipped:
            parts.append(f"branch skipped: {', '.join(self.branches_skipped)}")
        else:
            partial = [f"{b} on {self.branch_tiles_run[b]}/{self.tiles}" for b in self.branch_tiles_run
                       if self.branch_tiles_skipped.get(b)]
            if partial:
                parts.append("ran " + ", ".join(partial))
        if self.noise_precision is not None:
            parts.append(f"noise precision {self.noise_precision:.2f}")
        if self.detail_radius:
            parts.append(f"detail stage {self.detail_seconds:.2f} s")
        if self.exposure_scale != 1.0:
            parts.append(f"exposure key {self.exposure_key:.3g} denoised x {self.exposure_scale:.3g}")
        if self.sample_count is not None:
            parts.append(f"{self.sample_count[0]:g}-{self.sample_count[1]:g} spp per pixel")
        if self.views > 1:
            parts.append(f"mean of {self.views} mirrored views")
        return ", ".join(parts)


@dataclass
class DenoiseResult:
    """Denoised colour ``(H, W, 3)`` float32, the stats, and the model's description."""

    color: np.ndarray
    stats: DenoiseStats
    model_name: str = ""
    out_path: str | None = None
    layers: dict[str, np.ndarray] = field(default_factory=dict)  #: other layers denoised with the beauty's kernels


def peak_rss_mb() -> float | None:
    """The process's peak resident memory (``VmHWM``) in MiB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    try:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    except Exception:  # pragma: no cover - non-POSIX
        return None
