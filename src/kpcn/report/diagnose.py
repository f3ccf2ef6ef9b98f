"""Where a split-input model's error comes from: ``python -m kpcn.report.diagnose``.

On a report's cached renders (``<out>/<name>/renders``), for each scene and spp, a model's output (the network's,
before the detail stage :func:`kpcn.denoise` runs after it, so the parts below add up) against the reference beside
the same output with one of its parts replaced by the reference's:

* ``diffuse=ref`` / ``specular=ref``: the branch's radiance replaced (what the other branch's error is);
* ``albedo=ref``: the diffuse branch's output remodulated with the reference's albedo rather than the one the model
  remodulates with (what the albedo's own noise costs: a 4-spp albedo is the mean of 4 sub-pixel texture samples);

and how bright the output is against the reference (mean ratios, per part), and its error in PSNR's tone map split
two ways: into a low band (blurred by a Gaussian of ``--sigma`` pixels) and the rest (MSE of each), and into the
pixels at most ``--edge-px`` pixels from a geometric edge of the reference (:func:`geometric_edges`: where its normal
turns or its depth jumps) and the others (each part's sum over the frame's pixel count, so the two add up to the
MSE; ``edge share`` is the edge pixels' share of the frame). OIDN, as the report runs it, gets the same rows where it
is installed.
A diagnosis, not a figure of merit: replacing a part by the reference's is an oracle no denoiser has.

Example::

    python -m kpcn.report.diagnose --renders results/rep/s16/renders --model unet_kpcn:wide64c --spp 4 8
"""
from __future__ import annotations

import argparse
import glob
import os
import re
from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt, gaussian_filter

from ..data import model_inputs, pair_tensors
from ..inputs import radiance_of, split_reconstruct
from ..io.frame import Frame
from ..io.read import read_exr
from ..metrics import psnr, relmse, tonemap

__all__ = ["diagnose_frame", "find_renders", "geometric_edges", "main"]

#: the columns of a model's row, in order (relMSE each; psnr the output's; the bands tone-mapped MSE; ratios
#: mean(output) / mean(reference))
MODEL_KEYS = ("relmse", "psnr", "diffuse=ref", "specular=ref", "albedo=ref", "psnr albedo=ref", "low band",
              "high band", "edge band", "off-edge band", "edge share", "ratio", "diffuse ratio", "specular ratio")
OIDN_KEYS = ("relmse", "psnr", "low band", "high band", "edge band", "off-edge band", "ratio")


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t[0].permute(1, 2, 0).numpy()


def _bands(x: np.ndarray, ref: np.ndarray, sigma: float) -> tuple[float, float]:
    """MSE of the tone-mapped error's low band (Gaussian of ``sigma`` px, per channel) and of the rest, in the tone
    map PSNR is computed in (``kpcn.metrics.tonemap``: a relMSE split would spread a bright pixel's error onto dark
    neighbours, each weighed by its own 1 / (ref² + eps))."""
    e = tonemap(x) - tonemap(ref)
    low = np.stack([gaussian_filter(e[..., c], sigma, mode="nearest") for c in range(e.shape[-1])], -1)
    return float(np.mean(low**2)), float(np.mean((e - low) ** 2))


def geometric_edges(normal: np.ndarray, depth: np.ndarray, turn: float = 0.3, jump: float = 0.05) -> np.ndarray:
    """``(H, W)`` bool: the pixels where the geometry changes between a pixel and its right or lower neighbour: the
    normal ``(H, W, 3)`` by more than ``turn`` (the sum of the absolute component differences; 0.3: a turn of
    10–17°, by its direction) or the depth ``(H, W[, 1])`` by more than ``jump`` of the pixel's own (an occlusion
    edge on a surface of one normal). Both pixels of such a pair are marked. Meant for a reference's clean layers."""
    n = np.asarray(normal, dtype=np.float64)
    z = np.asarray(depth, dtype=np.float64)
    z = z[..., 0] if z.ndim == 3 else z
    edge = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        dn = np.abs(np.diff(n, axis=axis)).sum(-1)
        a = np.take(z, range(z.shape[axis] - 1), axis=axis)
        b = np.take(z, range(1, z.shape[axis]), axis=axis)
        dz = np.abs(b - a) > jump * np.maximum(np.minimum(a, b), 1e-6)
        step = (dn > turn) | dz
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        edge[tuple(lo)] |= step
        edge[tuple(hi)] |= step
    return edge


def _edge_bands(x: np.ndarray, ref: np.ndarray, near: np.ndarray) -> tuple[float, float]:
    """The tone-mapped squared error summed over the pixels ``near`` (``(H, W)`` bool) and over the others, each
    over the frame's pixel count (so they add up to the MSE)."""
    e2 = ((tonemap(x) - tonemap(ref)) ** 2).mean(-1)
    return float((e2 * near).mean()), float((e2 * ~near).mean())


def _ratio(x: np.ndarray, ref: np.ndarray) -> float:
    m = float(ref.mean())
    return float(x.mean()) / m if m > 0 else float("nan")


def diagnose_frame(net, noisy: Frame, ref: Frame, sigma: float = 3.0,
                   oidn: bool = False, edge_px: float = 1.0) -> dict[str, dict[str, float]]:
    """``{"model": {key: value for MODEL_KEYS}, "oidn": {...}}`` for one noisy frame and its reference.

    ``net`` a model with a ``diffuse`` / ``specular`` split input spec (``kpcn_split``, ``split_novar``); ``oidn``:
    also OIDN's row (the report's :func:`~kpcn.report.methods.oidn_method`); ``edge_px``: the edge band's reach
    from the reference's :func:`geometric_edges` (0: the edge pixels alone)."""
    spec = net.input_spec
    if set(spec.branches) != {"diffuse", "specular"}:
        raise ValueError(f"diagnose: needs a model with the diffuse/specular split; {spec.name!r} has {spec.branches}")
    t = pair_tensors(noisy, ref, spec)
    with torch.no_grad():
        out = net(model_inputs(net, t))
    colour = _hwc(out["color"])
    spec_rad = _hwc(radiance_of(out["specular"]))
    diff_rad = colour - spec_rad
    ref_d, ref_s = np.clip(ref["diffuse"], 0, None), np.clip(ref["specular"], 0, None)
    target = _hwc(t["y_color"])  # the spec's colour target: the two parts' sum
    ref_albedo = torch.as_tensor(np.ascontiguousarray(ref["albedo"])).permute(2, 0, 1)[None].float()
    remod = _hwc(split_reconstruct({"diffuse": out["diffuse"], "specular": out["specular"]}, {"albedo": ref_albedo}))
    low, high = _bands(colour, target, sigma)
    edges = geometric_edges(ref["normal"], ref["depth"])
    near = distance_transform_edt(~edges) <= edge_px if edges.any() else edges
    on_edge, off_edge = _edge_bands(colour, target, near)
    row = {"relmse": relmse(colour, target), "psnr": psnr(colour, target),
           "diffuse=ref": relmse(ref_d + spec_rad, target), "specular=ref": relmse(diff_rad + ref_s, target),
           "albedo=ref": relmse(remod, target), "psnr albedo=ref": psnr(remod, target), "low band": low,
           "high band": high, "edge band": on_edge, "off-edge band": off_edge, "edge share": float(near.mean()),
           "ratio": _ratio(colour, target), "diffuse ratio": _ratio(diff_rad, ref_d),
           "specular ratio": _ratio(spec_rad, ref_s)}
    res = {"model": row}
    if oidn:
        from .methods import oidn_method

        o = oidn_method().fn(noisy)
        low, high = _bands(o, target, sigma)
        on_edge, off_edge = _edge_bands(o, target, near)
        res["oidn"] = {"relmse": relmse(o, target), "psnr": psnr(o, target), "low band": low, "high band": high,
                       "edge band": on_edge, "off-edge band": off_edge, "ratio": _ratio(o, target)}
    return res


@dataclass
class SceneFiles:
    scene: str
    folder: str

    def input(self, spp: int) -> str | None:
        found = sorted(glob.glob(os.path.join(self.folder, f"input_{spp}spp_*.exr")))
        return found[0] if found else None

    def reference(self) -> str | None:
        """The reference with the most samples (a refined one, ``ReportConfig.ref_floor_target``, over the first)."""
        found = glob.glob(os.path.join(self.folder, "reference_*.exr"))
        return max(found, key=lambda p: (_spp_of(p), p), default=None)


def _spp_of(path: str) -> int:
    """The sample count in a report render's name (``reference_4096spp_seed0.exr``: 4096), -1 without one."""
    m = re.match(r"[a-z]+_(\d+)spp", os.path.basename(path))
    return int(m.group(1)) if m else -1


def find_renders(root: str) -> list[SceneFiles]:
    """The scenes of a report's renders folder (``<scene>/<W>x<H>-<fingerprint>/`` with a reference), by name."""
    out = []
    for scene in sorted(os.listdir(root)) if os.path.isdir(root) else []:
        for folder in sorted(glob.glob(os.path.join(root, scene, "*x*-*"))):
            sf = SceneFiles(scene, folder)
            if sf.reference():
                out.append(sf)
    if not out:
        raise FileNotFoundError(f"diagnose: no renders with a reference under {root!r} (a report's "
                                f"<out>/<name>/renders folder)")
    return out


def _mean(values) -> float:
    """The mean of the values that are not nan (a ratio is nan where the reference has none of that part), or nan."""
    v = np.asarray(values, dtype=np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else float("nan")


def _line(label: str, row: dict, keys) -> str:
    cells = [f"{row[k]:.3f}" if k.startswith("psnr") else f"{row[k]:.4f}" if "ratio" in k or "share" in k
             else f"{row[k]:.3e}" if "band" in k else f"{row[k]:.6f}" for k in keys]
    return f"| {label} | " + " | ".join(cells) + " |"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m kpcn.report.diagnose", description=__doc__.split("\n\n")[0])
    p.add_argument("--renders", required=True, help="a report's renders folder (<out>/<name>/renders)")
    p.add_argument("--model", default=None, help="weights file or model:tag (default: the shipped default)")
    p.add_argument("--spp", type=int, nargs="+", default=[4])
    p.add_argument("--sigma", type=float, default=3.0, help="the low band's Gaussian (pixels)")
    p.add_argument("--edge-px", type=float, default=1.0,
                   help="the edge band: pixels at most this far from a geometric edge of the reference (default 1)")
    p.add_argument("--no-oidn", action="store_true")
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    from ..baselines import oidn_available
    from ..inference.weights import load_model

    if args.threads:
        torch.set_num_threads(args.threads)
    net = load_model(args.model, device="cpu").eval()
    oidn = not args.no_oidn and oidn_available()
    scenes = find_renders(args.renders)
    for spp in args.spp:
        rows = []
        print(f"\n{spp} spp | " + " | ".join(MODEL_KEYS))
        for sf in scenes:
            path = sf.input(spp)
            if path is None:
                print(f"| {sf.scene} | no {spp}-spp input |")
                continue
            res = diagnose_frame(net, read_exr(path), read_exr(sf.reference()), args.sigma, oidn, args.edge_px)
            rows.append((sf.scene, res))
            print(_line(sf.scene, res["model"], MODEL_KEYS))
        if not rows:
            continue
        print(_line("mean", {k: _mean([r["model"][k] for _, r in rows]) for k in MODEL_KEYS}, MODEL_KEYS))
        if oidn:
            print(f"OIDN, {spp} spp | " + " | ".join(OIDN_KEYS))
            for scene, r in rows:
                print(_line(scene, r["oidn"], OIDN_KEYS))
            print(_line("mean", {k: _mean([r["oidn"][k] for _, r in rows]) for k in OIDN_KEYS}, OIDN_KEYS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
