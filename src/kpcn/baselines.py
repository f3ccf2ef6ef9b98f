"""Baseline denoisers to compare kpcn models against.

Intel Open Image Denoise (OIDN) through the optional ``pyoidn`` package
(``pip install kpcn[oidn]``)::

    from kpcn.baselines import oidn_available, oidn_denoise
    if oidn_available():
        out = oidn_denoise(frame["color"], *oidn_guides(frame))   # (H, W, 3) float32

What the wrapper does about pyoidn's input rules (``pyoidn.denoise``, OIDN 2.5):

- it accepts only float16/float32 ``(H, W, 3)`` arrays (float64 is a
  ``TypeError``): everything is converted to contiguous float32;
- HDR colour must be non-negative, albedo in [0, 1], normals in [-1, 1], and it
  does not reject NaN/Inf (they are passed on silently): colour is clamped at 0,
  albedo to [0, 1] (Mitsuba's albedo exceeds 1 on some conductors), normals to
  [-1, 1], non-finite values are replaced by 0;
- one-channel inputs are broadcast to three channels.

The auxiliary buffers of a render are averaged over few samples and are not
noise-free. By default they are passed as they are with ``clean_aux=False``: OIDN's
standard RT network, trained on noisy guides, reads them (at quality ``"high"``
this is the network ``"balanced"`` runs: 125 k multiply-adds per pixel). With
``prefilter=True`` they are first denoised by OIDN's own albedo and normal
filters and passed with ``clean_aux=True``, which at ``"high"`` runs OIDN's
larger network: Blender's "Accurate" prefilter. On the report's scenes that is
0.3-0.5 dB better at 4-64 spp and takes 6-8x the time (docs/measured.md,
fiftieth session).
"""
from __future__ import annotations

import numpy as np

from .constants import OIDN_ALBEDO, OIDN_NORMAL

__all__ = ["oidn_available", "oidn_version", "oidn_denoise", "oidn_guides", "oidn_prefilter_threads"]


def oidn_guides(frame) -> tuple[np.ndarray, np.ndarray]:
    """OIDN's auxiliary inputs ``(albedo, normal)`` from a :class:`~kpcn.io.Frame`.

    The albedo is the frame's ``denoisingAlbedo`` layer where it has one (Blender Cycles' Denoising
    Albedo and kpcn's Mitsuba renders, which follow mirrors and glass to the next rough surface: the albedo OIDN
    is made for), else ``albedo``; the normal likewise ``denoisingNormal`` (kpcn's Mitsuba renders), else
    ``normal``.
    """
    return frame.get(OIDN_ALBEDO, frame["albedo"]), frame.get(OIDN_NORMAL, frame["normal"])


def oidn_available() -> bool:
    """Whether ``pyoidn`` can be imported (and so OIDN can run here)."""
    try:
        import pyoidn  # noqa: F401
    except Exception:  # ImportError, or the bundled library failing to load
        return False
    return True


def oidn_version() -> str | None:
    """OIDN's version string (e.g. ``"2.5.1"``), or None when pyoidn is missing."""
    try:
        from pyoidn.version import oidn_version as v
    except Exception:
        return None
    return str(v)


def _as_rgb32(x: np.ndarray, name: str, lo: float, hi: float | None) -> np.ndarray:
    """``(H, W, 1|3)`` -> contiguous float32 ``(H, W, 3)``, finite, clipped to [lo, hi].

    NaN and -Inf become ``lo``; +Inf becomes ``hi`` or, when unbounded, the largest finite value.
    """
    a = np.asarray(x, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[-1] not in (1, 3):
        raise ValueError(f"oidn_denoise: {name} must be (H, W, 3) or (H, W, 1), got shape {a.shape}")
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, axis=-1)
    finite = np.isfinite(a)
    if not finite.all():
        top = hi if hi is not None else (float(a[finite].max()) if finite.any() else lo)
        a = np.nan_to_num(a, nan=lo, posinf=max(top, lo), neginf=lo)
    return np.ascontiguousarray(np.clip(a, lo, hi), dtype=np.float32)


def oidn_denoise(
    color: np.ndarray,
    albedo: np.ndarray | None = None,
    normal: np.ndarray | None = None,
    *,
    quality: str = "high",
    prefilter: bool = False,
) -> np.ndarray:
    """Denoise an HDR render with OIDN's ``RT`` filter (``hdr=True``).

    Args:
        color: ``(H, W, 3)`` linear radiance (noisy).
        albedo: ``(H, W, 3)`` first-hit albedo, or None.
        normal: ``(H, W, 3)`` first-hit normal in [-1, 1], or None. OIDN needs
            albedo whenever normal is given; a normal without albedo is dropped.
        quality: ``"high"``, ``"balanced"`` or ``"fast"``.
        prefilter: denoise ``albedo`` and ``normal`` with OIDN's own filters first (at ``quality``) and pass them as
            clean (``cleanAux``), as Blender's "Accurate" prefilter does; without ``albedo`` it changes nothing.

    Returns:
        ``(H, W, 3)`` float32 denoised radiance.

    Raises:
        ImportError: pyoidn is not installed.
        ValueError: shapes disagree.
    """
    try:
        import pyoidn
    except ImportError as exc:
        raise ImportError("OIDN baseline needs the pyoidn package: pip install pyoidn (or kpcn[oidn])") from exc

    c = _as_rgb32(color, "color", 0.0, None)
    a = _as_rgb32(albedo, "albedo", 0.0, 1.0) if albedo is not None else None
    n = _as_rgb32(normal, "normal", -1.0, 1.0) if normal is not None and a is not None else None
    for name, aux in (("albedo", a), ("normal", n)):
        if aux is not None and aux.shape != c.shape:
            raise ValueError(f"oidn_denoise: {name} {aux.shape} and color {c.shape} differ in shape")
    clean = bool(prefilter and a is not None)
    if clean:
        a = np.clip(_oidn_aux(pyoidn, a, pyoidn.OIDN_IMAGE_ALBEDO, quality), 0.0, 1.0)
        if n is not None:
            n = np.clip(_oidn_aux(pyoidn, n, pyoidn.OIDN_IMAGE_NORMAL, quality), -1.0, 1.0)
    out = pyoidn.denoise(c, a, n, hdr=True, clean_aux=clean, quality=quality)
    return np.asarray(out, dtype=np.float32)


#: the guides' filters (``prefilter=True``): their CPU device ("device") and one RT filter per (slot, quality)
_AUX: dict = {}


def _aux_device(pyoidn, threads: int | None = None):
    """The CPU device of the guides' filters (``prefilter=True``), made on first use with ``threads`` (OIDN's
    ``numThreads``; None: OIDN's default, every core)."""
    if "device" not in _AUX:
        dev = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
        if threads:
            dev.set_int("numThreads", int(threads))
        dev.commit()
        _AUX["device"] = dev
    return _AUX["device"]


def oidn_prefilter_threads(threads: int) -> bool:
    """Give the guides' filters of ``oidn_denoise(..., prefilter=True)`` ``threads`` threads; only before their
    first use (returns whether it took: False once their device exists, or without pyoidn)."""
    if "device" in _AUX or not oidn_available():
        return False
    import pyoidn

    _aux_device(pyoidn, threads)
    return True


def _oidn_aux(pyoidn, image: np.ndarray, slot: str, quality: str) -> np.ndarray:
    """``image`` (contiguous float32 ``(H, W, 3)``) denoised by OIDN's RT filter given only that auxiliary image
    (``slot``: albedo or normal), as OIDN prefilters its guides. The filter is made once per slot and quality and
    kept, as ``pyoidn.denoise`` keeps its own (a new one a call cost 0.4 s more at 1920x1080)."""
    dev = _aux_device(pyoidn)
    q = getattr(pyoidn, f"OIDN_QUALITY_{quality.upper()}") if isinstance(quality, str) else quality
    f = _AUX.get((slot, q))
    if f is None:
        f = _AUX[(slot, q)] = pyoidn.Filter(dev, pyoidn.OIDN_FILTER_TYPE_RT)
        f.set_quality(q)
    out = np.empty_like(image)
    try:
        f.set_image(slot, image, pyoidn.OIDN_FORMAT_FLOAT3)
        f.set_image(pyoidn.OIDN_IMAGE_OUTPUT, out, pyoidn.OIDN_FORMAT_FLOAT3)
        f.commit()
        f.execute()
        err = dev.get_error()
    finally:  # the filter keeps no pointer to these arrays past the call
        f.unset_image(slot)
        f.unset_image(pyoidn.OIDN_IMAGE_OUTPUT)
    if err:
        raise RuntimeError(f"oidn_denoise: OIDN's {slot} prefilter failed: {err}")
    return out
