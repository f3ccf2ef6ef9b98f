"""Checks a denoiser must pass, beyond the error curves.

* :func:`evaluate_converged`: every method on a converged (high-spp) input; how
  much it changes it (relMSE and PSNR of the output against that input) and its
  error against the reference next to the input's own. A denoiser must leave a
  converged input nearly as it is.
* :func:`evaluate_exposure`: every method on one spp's input at other exposures (its radiance × 0.01, × 100);
  its error against the reference beside its error at the frame's own exposure. A frame's units (a renderer
  in physical units, an exposure change) must not change how well it is denoised.
* :func:`evaluate_mixed`: every method on a frame whose spp varies per pixel (a low-spp input's pixels inside smooth
  regions, a high-spp input's outside: what an adaptive sampler gives); its error in each region beside its error
  there on the uniform frames. A denoiser must denoise each pixel as its own samples allow.
* :func:`worse_than_input`: every frame (ladder, converged, other exposures, varying spp) where a method's
  output is further from the reference than its noisy input was.
* :func:`against_oidn`: per model and spp, whether its mean relMSE, PSNR and SSIM
  all beat OIDN's.
* :func:`method_table`: each method's cost: denoise seconds and multiply-adds per pixel.
"""
from __future__ import annotations

import zlib
from typing import Mapping, Sequence

import numpy as np

from ..exposure import scale_layers
from ..io import Frame
from ..metrics import all_metrics, psnr, relmse
from ..render import mix_frames
from ..sample_maps import region_mask
from .analysis import is_ref_limited, reference_floor
from .cache import SceneRenders
from .config import BASELINES, MC, MORE_SAMPLES_TOLERANCE, OIDN
from .methods import Method

#: per-scene fields of the converged-input table (``converged.csv``)
CONVERGED_FIELDS = ("scene", "method", "spp", "change_relmse", "change_psnr", "relmse", "psnr", "ssim",
                    "input_relmse", "input_psnr", "input_ssim", "worse_than_input", "ref_floor", "ref_limited",
                    "denoise_s")


def evaluate_converged(sr: SceneRenders, methods: Sequence[Method], floor_factor: float = 3.0) -> list[dict]:
    """One row per method for the scene's converged input (none without one).

    ``change_relmse`` / ``change_psnr``: the output against the converged input
    itself (0 / infinite for a method that returns its input); ``relmse``,
    ``psnr``, ``ssim``: the output against the reference; ``input_*``: the
    converged input against the reference; ``ref_limited``: the input's relMSE is
    below ``floor_factor`` x the reference's noise (then the reference cannot
    tell whether the method improved or degraded it: read ``change_*``).
    """
    if sr.converged is None:
        return []
    frame, ref = sr.converged, sr.reference["color"]
    x = frame["color"]
    with np.errstate(divide="ignore"):  # PSNR of identical images is infinite
        inp = all_metrics(x, ref)
    floor = reference_floor(sr.reference)
    rows = []
    for m in methods:
        img, secs = m(frame)
        with np.errstate(divide="ignore"):
            met, change_psnr = all_metrics(img, ref), psnr(img, x)
        rows.append({
            "scene": sr.label, "method": m.name, "spp": frame.spp,
            "change_relmse": relmse(img.astype(np.float64), x.astype(np.float64)),
            "change_psnr": change_psnr, **{k: met[k] for k in ("relmse", "psnr", "ssim")},
            "input_relmse": inp["relmse"], "input_psnr": inp["psnr"], "input_ssim": inp["ssim"],
            "worse_than_input": met["relmse"] > inp["relmse"], "ref_floor": floor,
            "ref_limited": is_ref_limited(inp["relmse"], floor, floor_factor), "denoise_s": secs,
        })
    return rows


#: per-scene fields of the exposure table (``exposure.csv``)
EXPOSURE_FIELDS = ("scene", "method", "spp", "exposure", "relmse", "psnr", "ssim", "own_relmse", "own_psnr",
                   "own_ssim", "input_relmse", "worse_than_input", "ref_limited")


def evaluate_exposure(sr: SceneRenders, methods: Sequence[Method], spp: int, factors: Sequence[float],
                      rows: Sequence[dict]) -> list[dict]:
    """One row per method and factor: the scene's ``spp`` input with every radiance layer × the factor (its
    variances × its square; :func:`kpcn.exposure.scale_layers`), denoised, the output divided by the factor and
    compared with the reference; ``own_*``: the same method's row at the frame's own exposure, ``input_relmse``
    and ``ref_limited`` the noisy input's (its ``mc`` row): ``rows`` are :func:`evaluate_scene`'s for the scene."""
    frame = sr.inputs.get(spp)
    if frame is None or not factors:
        return []
    ref = sr.reference["color"]
    own = {r["method"]: r for r in rows if r["scene"] == sr.label and r["spp"] == spp}
    inp, ref_limited = own[MC]["relmse"], bool(own[MC]["ref_limited"])
    out = []
    for f in factors:
        scaled = Frame(scale_layers(frame.layers, float(f)), dict(frame.meta), frame.path)
        for m in methods:
            img, _ = m(scaled)
            met = all_metrics(img / np.float32(f), ref)
            base = own.get(m.name, {})
            out.append({"scene": sr.label, "method": m.name, "spp": spp, "exposure": float(f),
                        **{k: met[k] for k in ("relmse", "psnr", "ssim")},
                        **{f"own_{k}": base.get(k, float("nan")) for k in ("relmse", "psnr", "ssim")},
                        "input_relmse": inp, "worse_than_input": met["relmse"] > inp, "ref_limited": ref_limited})
    return out


def exposure_table(rows: Sequence[dict]) -> list[dict]:
    """One row per method and exposure: over scenes, mean relMSE, PSNR and SSIM at that exposure and at the
    frames' own, the largest ratio of a scene's relMSE to its own, and the frames made worse than their input."""
    out = []
    for key in dict.fromkeys((r["method"], r["exposure"]) for r in rows):
        rs = [r for r in rows if (r["method"], r["exposure"]) == key]
        row = {"method": key[0], "exposure": key[1], "spp": rs[0]["spp"], "scenes": len(rs)}
        for k in ("relmse", "psnr", "ssim", "own_relmse", "own_psnr", "own_ssim"):
            row[k] = float(np.mean([r[k] for r in rs]))
        row["relmse_ratio_max"] = float(max(r["relmse"] / max(r["own_relmse"], 1e-30) for r in rs))
        row["worse_than_input"] = sum(bool(r["worse_than_input"]) for r in rs)
        out.append(row)
    return out


#: per-scene fields of the varying-spp table (``mixed.csv``)
MIXED_FIELDS = ("scene", "method", "spp_low", "spp_high", "low_share", "relmse", "psnr", "ssim", "relmse_low",
                "uniform_relmse_low", "relmse_high", "uniform_relmse_high", "input_relmse", "worse_than_input")


def _region_relmse(x: np.ndarray, ref: np.ndarray, where: np.ndarray) -> float:
    """relMSE over the pixels ``where`` only (NaN where there are none)."""
    return relmse(x[where], ref[where]) if where.any() else float("nan")


def mixed_mask(label: str, shape: tuple[int, int]) -> np.ndarray:
    """The report's low-spp regions of a scene: half the frame, in regions an eighth of its side across (cells of
    1/8 of the shorter side), the same for the same scene label and size on every run."""
    cell = max(4, min(shape) // 8)
    return region_mask(shape, np.random.default_rng(zlib.crc32(label.encode())), cell=cell, quantile=0.5)


def evaluate_mixed(sr: SceneRenders, methods: Sequence[Method], spp: Sequence[int],
                   uniform: Mapping[int, Mapping[str, np.ndarray]] | None = None) -> list[dict]:
    """One row per method: the scene's ``spp[0]`` input inside :func:`mixed_mask`'s regions and its ``spp[1]``
    input outside (:func:`kpcn.render.mix_frames`, with its sample-count layer), denoised; its relMSE in each
    region (``relmse_low``, ``relmse_high``) beside the same method's on the uniform inputs there
    (``uniform_relmse_*``), its whole-frame relMSE, PSNR and SSIM, and the composite input's relMSE.
    ``uniform[spp][method name]``: a method's results on the uniform inputs where the caller has them
    (:func:`kpcn.report.analysis.evaluate_scene`'s ``outputs``); the others are denoised here."""
    lo, hi = (sr.inputs.get(int(s)) for s in spp)
    if lo is None or hi is None:
        return []
    ref = sr.reference["color"]
    low = mixed_mask(sr.label, lo.shape)
    mixed = mix_frames(lo, hi, low)
    inp = relmse(mixed["color"], ref)

    def result(m: Method, s: int, frame):
        have = (uniform or {}).get(int(s), {}).get(m.name)
        return have if have is not None else m(frame)[0]

    out = []
    for m in methods:
        img = m(mixed)[0]
        met = all_metrics(img, ref)
        out.append({"scene": sr.label, "method": m.name, "spp_low": int(spp[0]), "spp_high": int(spp[1]),
                    "low_share": float(low.mean()), **{k: met[k] for k in ("relmse", "psnr", "ssim")},
                    "relmse_low": _region_relmse(img, ref, low),
                    "uniform_relmse_low": _region_relmse(result(m, spp[0], lo), ref, low),
                    "relmse_high": _region_relmse(img, ref, ~low),
                    "uniform_relmse_high": _region_relmse(result(m, spp[1], hi), ref, ~low),
                    "input_relmse": inp, "worse_than_input": met["relmse"] > inp})
    return out


def mixed_table(rows: Sequence[dict]) -> list[dict]:
    """One row per method: over scenes, the means of :func:`evaluate_mixed`'s figures, each region's mean relMSE
    over the uniform frames' there, and the frames made worse than their input."""
    out = []
    for m in dict.fromkeys(r["method"] for r in rows):
        rs = [r for r in rows if r["method"] == m]
        row = {"method": m, "spp_low": rs[0]["spp_low"], "spp_high": rs[0]["spp_high"], "scenes": len(rs)}
        for k in ("relmse", "psnr", "ssim", "relmse_low", "uniform_relmse_low", "relmse_high", "uniform_relmse_high"):
            row[k] = float(np.mean([r[k] for r in rs]))
        row["ratio_low"] = row["relmse_low"] / max(row["uniform_relmse_low"], 1e-30)
        row["ratio_high"] = row["relmse_high"] / max(row["uniform_relmse_high"], 1e-30)
        row["worse_than_input"] = sum(bool(r["worse_than_input"]) for r in rs)
        out.append(row)
    return out


def converged_table(rows: Sequence[dict]) -> list[dict]:
    """One row per method: over scenes, the mean and largest change of the converged input
    (relMSE against the input), the median PSNR against the input, the mean relMSE against the
    reference of the output and of the input, and on how many scenes the output was further
    from the reference than the input."""
    out = []
    for m in dict.fromkeys(r["method"] for r in rows):
        rs = [r for r in rows if r["method"] == m]
        out.append({
            "method": m, "spp": rs[0]["spp"], "scenes": len(rs),
            "change_relmse": float(np.mean([r["change_relmse"] for r in rs])),
            "change_relmse_max": float(max(r["change_relmse"] for r in rs)),
            "change_psnr": float(np.median([r["change_psnr"] for r in rs])),
            "relmse": float(np.mean([r["relmse"] for r in rs])),
            "input_relmse": float(np.mean([r["input_relmse"] for r in rs])),
            "psnr": float(np.mean([r["psnr"] for r in rs])),
            "input_psnr": float(np.mean([r["input_psnr"] for r in rs])),
            "worse_than_input": sum(bool(r["worse_than_input"]) for r in rs),
        })
    return out


def worse_than_input(rows: Sequence[dict], converged: Sequence[dict] = (), exposure: Sequence[dict] = (),
                     mixed: Sequence[dict] = ()) -> list[dict]:
    """Frames where a method's relMSE against the reference is above its noisy input's.

    ``rows``: the ladder rows (the input's relMSE is the ``mc`` row of the same
    scene and spp); ``converged``: :func:`evaluate_converged` rows; ``exposure``: :func:`evaluate_exposure` rows;
    ``mixed``: :func:`evaluate_mixed` rows. Each item: ``scene, spp, method, relmse, input_relmse, ratio, converged,
    ref_limited`` (and ``exposure``, the factor, for a frame at another exposure; ``mixed``, the two spp, for a frame
    whose spp varies).
    """
    def item(r: dict, input_relmse: float, ref_limited, converged: bool = False, **extra) -> dict:
        return {"scene": r["scene"], "spp": r["spp"], "method": r["method"], "relmse": r["relmse"],
                "input_relmse": input_relmse, "ratio": r["relmse"] / max(input_relmse, 1e-30),
                "converged": converged, "ref_limited": bool(ref_limited), **extra}

    inputs = {(r["scene"], r["spp"]): r for r in rows if r["method"] == MC}
    out = []
    for r in rows:
        inp = inputs.get((r["scene"], r["spp"]))
        if r["method"] != MC and inp is not None and r["relmse"] > inp["relmse"]:
            out.append(item(r, inp["relmse"], inp.get("ref_limited")))
    out += [item(r, r["input_relmse"], r["ref_limited"], converged=True) for r in converged if r["worse_than_input"]]
    out += [item(r, r["input_relmse"], r["ref_limited"], exposure=r["exposure"])
            for r in exposure if r["worse_than_input"]]
    out += [item({**r, "spp": r["spp_low"]}, r["input_relmse"], False, mixed=(r["spp_low"], r["spp_high"]))
            for r in mixed if r["worse_than_input"]]
    return out


def worse_with_more_samples(rows: Sequence[dict], tolerance: float = MORE_SAMPLES_TOLERANCE) -> list[dict]:
    """Outputs whose relMSE rose with more samples: a method's output at ``spp`` further from the reference
    than its best output on the same scene at fewer samples.

    A denoiser given more samples should come out closer to the reference; where it does not, it keeps
    noise it had removed at fewer samples (or adds artefacts). The reference's own noise adds the same
    relMSE to every spp of a scene, so the comparison holds on reference-limited rows too. ``tolerance``:
    a rise of at most this fraction is not listed (independent renders at neighbouring spp differ a little).
    Each item: ``scene, method, spp, relmse, best_spp, best_relmse, ratio``. MC rows are not checked.
    """
    by: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        if r["method"] != MC:
            by.setdefault((r["scene"], r["method"]), []).append(r)
    out = []
    for (scene, method), rs in by.items():
        best = None
        for r in sorted(rs, key=lambda r: r["spp"]):
            if best is not None and r["relmse"] > best["relmse"] * (1.0 + tolerance):
                out.append({"scene": scene, "method": method, "spp": r["spp"], "relmse": r["relmse"],
                            "best_spp": best["spp"], "best_relmse": best["relmse"],
                            "ratio": r["relmse"] / max(best["relmse"], 1e-30)})
            if best is None or r["relmse"] < best["relmse"]:
                best = r
    return out


def against_oidn(means: Sequence[dict], rows: Sequence[dict] = ()) -> list[dict]:
    """Per model (not MC, not an OIDN baseline) and spp: does its mean relMSE <= OIDN's, mean PSNR >= and mean SSIM >=?

    ``beats_oidn`` is True when all three hold. With ``rows``, also
    ``scenes_won_relmse``: on how many scenes its relMSE <= OIDN's. Empty without OIDN rows.
    """
    oidn = {r["spp"]: r for r in means if r["method"] == OIDN}
    per_scene = {(r["scene"], r["spp"], r["method"]): r["relmse"] for r in rows}
    out = []
    for r in means:
        o = oidn.get(r["spp"])
        if r["method"] == MC or r["method"] in BASELINES or o is None:
            continue
        ok = {"relmse_ok": r["relmse"] <= o["relmse"], "psnr_ok": r["psnr"] >= o["psnr"], "ssim_ok": r["ssim"] >= o["ssim"]}
        scenes = sorted({s for s, p, m in per_scene if p == r["spp"] and m == r["method"] and (s, p, OIDN) in per_scene})
        won = sum(per_scene[(s, r["spp"], r["method"])] <= per_scene[(s, r["spp"], OIDN)] for s in scenes)
        out.append({"method": r["method"], "spp": r["spp"], **ok, "beats_oidn": all(ok.values()),
                    "relmse": r["relmse"], "oidn_relmse": o["relmse"], "psnr": r["psnr"], "oidn_psnr": o["psnr"],
                    "ssim": r["ssim"], "oidn_ssim": o["ssim"], "scenes_won_relmse": won, "scenes": len(scenes)})
    return out


def method_table(methods: Sequence[Method], rows: Sequence[dict], converged: Sequence[dict] = ()) -> list[dict]:
    """One row per method: multiply-adds per pixel (and where the figure comes from), denoise seconds per
    frame (mean and median over every timed call) and megapixels per second at the report's size."""
    out = []
    for m in methods:
        rs = [r for r in rows if r["method"] == m.name] + [r for r in converged if r["method"] == m.name]
        secs = [r["denoise_s"] for r in rs]
        px = [r["width"] * r["height"] for r in rows if r["method"] == m.name][:1]
        mean_s = float(np.mean(secs)) if secs else None
        out.append({"method": m.name, "macs_per_px": m.macs_per_px, "macs_source": m.macs_source,
                    "denoise_s_mean": mean_s, "denoise_s_median": float(np.median(secs)) if secs else None,
                    "frames": len(secs), "mpix_per_s": (px[0] / mean_s / 1e6) if px and mean_s else None,
                    "description": m.description})
    return out
