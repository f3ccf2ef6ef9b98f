"""Error against run time: raw Monte Carlo, kpcn models and OIDN on held-out scenes.

Command line::

    python -m kpcn.report                                   # defaults below, into results/report/default/
    python -m kpcn.report --quick --out /tmp/r              # tiny smoke run (24x24, 2 and 4 spp)
    python -m kpcn.report --scenes test:glossy my.xml --spp 2 4 8 --ref-spp 512 \\
        --resolution 64 64 --models kpcn dpcn mine=results/exp1/checkpoints/latest.pt

Python API::

    from kpcn.report import ReportConfig, run_report
    result = run_report(ReportConfig(scenes=["test:glossy"], spp=[2, 4], models=["kpcn"]))
    result.summary["equal_time"]                            # the equal-time figures
    result.paths["markdown"]                                # report.md

What it does, per scene:

1. renders the noisy input at every spp of the ladder (default 2 … 64; each spp
   its own independent seed) and a high-spp reference (default 1024 spp,
   ``role=1``: noise independent of the inputs), caching every render as an EXR
   in ``<out>/<name>/renders/<scene>/<W>x<H>-<scene fingerprint>/`` (written
   atomically; a re-run reuses them, ``--rerender`` forces new ones; the
   fingerprint changes when the scene's content does). Before the first timed
   render of a scene one untimed 2-spp render compiles Mitsuba's kernels, so
   render seconds are the wall time of the sampling, as ``renderTimeSeconds`` says;
2. evaluates raw MC, each model (``kpcn.denoise.denoise`` on the in-memory
   frame, model loaded once beforehand) and OIDN (when ``pyoidn`` imports)
   against the reference: relMSE, SMAPE, PSNR, SSIM (:mod:`kpcn.metrics`);
   denoise seconds are the wall time of the denoise call (OIDN's with albedo
   and normal; ``--repeats N``: median of N) after one untimed warm-up call per
   method, and after a short pause following the renders (:data:`SETTLE_SECONDS`);
   total seconds = render + denoise;
3. writes ``results.csv`` (one row per scene, spp, method), ``report.md`` (mean
   table per method and spp, per-scene table, equal-time table),
   ``error_vs_time.png`` (log-log relMSE against total seconds, one panel per
   scene plus the mean), ``contact_sheet.png`` (tone-mapped crops at one spp)
   and ``summary.json``; all atomically. The Markdown summary is printed.

The equal-time figure: for each scene, the spp at which raw MC reaches the
relMSE of the first model at 8 spp (log-log interpolation along the raw ladder;
outside it, extrapolation with the slope of a least-squares fit of log relMSE
against log spp, MC error ~ 1/spp, flagged as extrapolated), and the time ratio
(raw MC seconds at that spp, from a linear fit ``seconds = overhead + spp ×
seconds-per-sample`` over the scene's renders, divided by the model's render +
denoise seconds at 8 spp).

Models are given as registry names (``kpcn``, ``dpcn``: shipped weights),
checkpoint paths, or ``label=name-or-path``.
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import logging
import math
import os
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .io import Frame, atomic_write, read_exr, write_exr
from .metrics import all_metrics, tonemap

log = logging.getLogger("kpcn.report")

METRICS = ("relmse", "smape", "psnr", "ssim")
TIMES = ("render_s", "denoise_s", "total_s")
CSV_FIELDS = ("scene", "spp", "method", *METRICS, *TIMES, "width", "height", "ref_spp")
MC = "mc"  #: method name of the raw Monte Carlo rows
DEFAULT_SCENES = ("random:900001", "random:900002", "random:900003", "test:glossy", "test:glass")
INPUT_ROLE_BASE = 2  #: input at s spp renders with role 2 + s (as kpcn.render's data sets); reference role 1
WARMUP_ROLE = 10_000_000  #: role of the untimed warm-up render (its noise is never used)
#: pause between a scene's renders and its timed denoising. Mitsuba's worker threads keep
#: spinning briefly after a render; a torch denoiser started at once ran 20x slower (2 cores).
SETTLE_SECONDS = 0.5


# ----------------------------------------------------------------------------- configuration


@dataclass
class ReportConfig:
    """What to render and compare. ``resolution`` is ``(width, height)``."""

    scenes: list[Any] = field(default_factory=lambda: list(DEFAULT_SCENES))
    spp: list[int] = field(default_factory=lambda: [2, 4, 8, 16, 32, 64])
    ref_spp: int = 1024
    resolution: tuple[int, int] = (128, 128)
    models: list[str] = field(default_factory=lambda: ["kpcn", "dpcn"])
    oidn: bool = True  #: include OIDN when pyoidn imports
    out: str = "results/report"
    name: str = "default"
    seed: int = 0
    device: str = "auto"
    tile: int = 256
    repeats: int = 1  #: timed denoise calls per frame; the median is reported (the result of the last is kept)
    equal_time_spp: int = 8  #: the model's spp for the equal-time figure (nearest ladder spp if absent)
    contact_spp: int = 8  #: spp shown in the contact sheet (nearest ladder spp if absent)
    crop: int = 128  #: side of the centre crop in the contact sheet
    rerender: bool = False
    max_depth: int = 8

    @classmethod
    def quick(cls, **overrides) -> "ReportConfig":
        """Tiny settings for tests and smoke runs: two 24x24 scenes (chosen for low firefly noise), 2 and 4 spp, 64-spp reference."""
        base = dict(scenes=["random:900003", "test:textured"], spp=[2, 4], ref_spp=64, resolution=(24, 24), name="quick")
        base.update(overrides)
        return cls(**base)

    def validate(self) -> None:
        if not self.scenes:
            raise ValueError("no scenes to render")
        if not self.spp or min(self.spp) < 2:
            raise ValueError(f"every spp must be >= 2 (variances need two samples), got {self.spp}")
        if self.ref_spp < 2:
            raise ValueError(f"ref_spp must be >= 2, got {self.ref_spp}")
        if self.ref_spp <= max(self.spp):
            log.warning("reference spp %d is not above the largest input spp %d", self.ref_spp, max(self.spp))
        if len(self.resolution) != 2 or min(self.resolution) < 8:
            raise ValueError(f"resolution must be (width, height), each >= 8, got {self.resolution}")

    @property
    def folder(self) -> Path:
        return Path(self.out) / self.name


def nearest_spp(ladder: Sequence[int], want: int) -> int:
    """The ladder spp closest to ``want`` in log scale (ties: the smaller)."""
    return min(sorted(ladder), key=lambda s: abs(math.log(s / want)))


# ----------------------------------------------------------------------------- rendering and caching


def scene_slug(scene: Any) -> str:
    """A folder name for a scene: ``test:glossy`` -> ``test_glossy``, ``a/b.xml`` -> ``b_<hash>``."""
    if isinstance(scene, dict):
        return str(scene.get("kpcn_name", "dict")).replace(":", "_").replace("/", "_")
    s = os.fspath(scene)
    if s.startswith(("test:", "random:")):
        return s.replace(":", "_")
    p = Path(s).resolve()
    return f"{p.stem}_{hashlib.sha1(str(p).encode()).hexdigest()[:8]}"


def scene_label(scene: Any) -> str:
    """A short human-readable name for tables and plots."""
    if isinstance(scene, dict):
        return str(scene.get("kpcn_name", "dict"))
    s = os.fspath(scene)
    return s if s.startswith(("test:", "random:")) else Path(s).stem


@dataclass
class SceneRenders:
    """The renders of one scene: ``inputs[spp]`` and ``reference`` (Frames, layers ``(H, W, C)``)."""

    scene: Any
    label: str
    inputs: dict[int, Frame]
    reference: Frame
    rendered: list[str]  #: paths rendered in this run (the others came from the cache)


def _cached(path: Path, spp: int, resolution: tuple[int, int]) -> Frame | None:
    """The frame at ``path`` if it exists and matches ``spp`` and ``(W, H)``; else None."""
    if not path.exists():
        return None
    try:
        fr = read_exr(path, require=("color", "albedo", "normal"))
    except Exception as exc:  # a damaged cache file is rendered again
        log.warning("%s: unreadable cache (%s), rendering again", path, exc)
        return None
    w, h = resolution
    if fr.spp != spp or fr.shape != (h, w) or "renderTimeSeconds" not in fr.meta:
        log.warning("%s: cached render does not match (spp %s, size %s), rendering again", path, fr.spp, fr.shape)
        return None
    return fr


def _hash_value(h, x: Any) -> None:
    """Feed a canonical encoding of a scene-dict value into the hash ``h``."""
    if isinstance(x, dict):
        h.update(b"{")
        for k in sorted(x, key=str):
            h.update(repr(k).encode())
            _hash_value(h, x[k])
        h.update(b"}")
    elif isinstance(x, (list, tuple)):
        h.update(b"[")
        for v in x:
            _hash_value(h, v)
        h.update(b"]")
    elif isinstance(x, (str, int, float, bool)) or x is None:
        h.update(repr(x).encode())
    else:  # Mitsuba objects: transforms (their matrix), bitmaps (their pixels)
        arr = np.asarray(x.matrix if hasattr(x, "matrix") else x, dtype=np.float64)
        h.update(type(x).__name__.encode() + repr(arr.shape).encode() + arr.tobytes())


def scene_source(scene: Any, resolution: tuple[int, int]) -> tuple[Any, str]:
    """What to render and its fingerprint: ``(dict or path, 12 hex digits)``.

    ``test:``/``random:`` names are built into their scene dicts here, so the
    fingerprint covers the generated content (a change to :mod:`kpcn.scenes`
    invalidates the cache); for an XML file it is the file's bytes (not the
    meshes and textures it references: use ``--rerender`` after changing those).
    """
    h = hashlib.sha1(repr(tuple(resolution)).encode())
    if isinstance(scene, (str, os.PathLike)) and str(scene).startswith(("test:", "random:")):
        from . import scenes

        kind, arg = str(scene).split(":", 1)
        d = scenes.test_scene(arg, resolution=resolution) if kind == "test" else scenes.random_scene(int(arg), resolution=resolution)
        _hash_value(h, d)
        return {**d, "kpcn_name": str(scene)}, h.hexdigest()[:12]
    if isinstance(scene, dict):
        _hash_value(h, scene)
        return scene, h.hexdigest()[:12]
    h.update(Path(scene).read_bytes())
    return scene, h.hexdigest()[:12]


def render_scene(cfg: ReportConfig, scene: Any, progress: Callable[[str], None] = log.info) -> SceneRenders:
    """Render (or load from the cache) the input ladder and the reference of one scene.

    Cache: ``<out>/<name>/renders/<scene>/<W>x<H>-<fingerprint>/input_<spp>spp_seed<seed>.exr``
    and ``reference_<spp>spp_seed<seed>.exr``; a cached file is used when its
    header's spp and its size match.
    """
    from .render import load_scene, render_frame

    w, h = cfg.resolution
    source, fingerprint = scene_source(scene, tuple(cfg.resolution))
    folder = cfg.folder / "renders" / scene_slug(scene) / f"{w}x{h}-{fingerprint}"
    jobs = [(s, folder / f"input_{s}spp_seed{cfg.seed}.exr", INPUT_ROLE_BASE + s) for s in sorted(set(cfg.spp))]
    jobs.append((cfg.ref_spp, folder / f"reference_{cfg.ref_spp}spp_seed{cfg.seed}.exr", 1))
    frames: dict[Path, Frame] = {}
    rendered: list[str] = []
    loaded = None
    for spp, path, role in jobs:
        fr = None if cfg.rerender else _cached(path, spp, cfg.resolution)
        if fr is None:
            if loaded is None:
                loaded = load_scene(source, cfg.resolution)
                # untimed warm-up: the first render of a scene compiles its kernels (~2 s)
                render_frame(source, 2, cfg.seed, cfg.resolution, role=WARMUP_ROLE, loaded=loaded, max_depth=cfg.max_depth)
            fr = render_frame(source, spp, cfg.seed, cfg.resolution, role=role, loaded=loaded, max_depth=cfg.max_depth)
            fr.meta["scene"] = scene_label(scene)
            write_exr(path, fr.layers, fr.meta)
            fr.path = str(path)
            rendered.append(str(path))
            progress(f"rendered {scene_label(scene)} {spp} spp in {fr.meta['renderTimeSeconds']:.2f} s")
        frames[path] = fr
    inputs = {s: frames[p] for s, p, _ in jobs[:-1]}
    return SceneRenders(scene, scene_label(scene), inputs, frames[jobs[-1][1]], rendered)


# ----------------------------------------------------------------------------- methods


@dataclass
class Method:
    """A denoiser under test: ``fn(frame) -> (H, W, 3)`` radiance."""

    name: str
    fn: Callable[[Frame], np.ndarray]
    description: str = ""
    repeats: int = 1
    warmed_up: bool = False

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
    if p.suffix in (".pt", ".pth", ".ckpt") or p.exists():
        return p.stem, spec
    return spec, spec


def model_method(spec: str, cfg: ReportConfig) -> Method:
    """A :class:`Method` running ``kpcn.denoise.denoise`` with the model ``spec``."""
    from .denoise import denoise, load_model

    label, value = parse_model_spec(spec)
    model = load_model(value, cfg.device)  # loaded once: weight loading is not timed

    def fn(frame: Frame) -> np.ndarray:
        return denoise(frame, model=model, tile=cfg.tile, device=cfg.device)

    return Method(label, fn, f"kpcn.denoise with model {value!r}", cfg.repeats)


def oidn_method(repeats: int = 1) -> Method:
    """OIDN (``hdr=True``, colour + albedo + normal) as a :class:`Method`."""
    from .baselines import oidn_denoise, oidn_version

    def fn(frame: Frame) -> np.ndarray:
        return oidn_denoise(frame["color"], frame["albedo"], frame["normal"])

    return Method("oidn", fn, f"Intel Open Image Denoise {oidn_version()} (pyoidn), hdr, albedo + normal", repeats)


def build_methods(cfg: ReportConfig) -> tuple[list[Method], list[str]]:
    """The methods to evaluate and notes on the ones left out (a model that fails to load, no OIDN)."""
    from .baselines import oidn_available

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
        else:
            notes.append("OIDN was not installed (pip install pyoidn): no OIDN rows.")
    return methods, notes


# ----------------------------------------------------------------------------- evaluation


def evaluate_scene(sr: SceneRenders, methods: Sequence[Method], keep_spp: int | None = None):
    """Rows (dicts with :data:`CSV_FIELDS`) for raw MC and every method at every spp of ``sr``.

    Returns ``(rows, images)`` where ``images[method]`` is the ``(H, W, 3)`` result
    at ``keep_spp`` (for the contact sheet), including ``"mc"`` and ``"reference"``.
    """
    ref = sr.reference["color"]
    h, w = sr.reference.shape
    rows, images = [], {"reference": ref}
    for spp, frame in sorted(sr.inputs.items()):
        render_s = float(frame.meta["renderTimeSeconds"])
        results = [(MC, frame["color"], 0.0)]
        for m in methods:
            img, secs = m(frame)
            results.append((m.name, img, secs))
        for name, img, secs in results:
            row = {"scene": sr.label, "spp": spp, "method": name, **all_metrics(img, ref)}
            row.update(render_s=render_s, denoise_s=secs, total_s=render_s + secs, width=w, height=h)
            row["ref_spp"] = sr.reference.spp
            rows.append(row)
            if spp == keep_spp:
                images[name] = img
    return rows, images


def reference_floor(ref: Frame) -> float | None:
    """relMSE the reference's own noise adds: mean(colorVariance / (ref² + 0.01)), or None without variance."""
    var = ref.get("colorVariance")
    if var is None:
        return None
    c = ref["color"].astype(np.float64)
    return float(np.mean(np.broadcast_to(var, c.shape) / (c**2 + 1e-2)))


def mean_table(rows: Sequence[dict]) -> list[dict]:
    """Mean over scenes of every metric and time, per (method, spp); sorted by method order then spp."""
    order = list(dict.fromkeys(r["method"] for r in rows))
    groups: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["method"], int(r["spp"])), []).append(r)
    out = []
    for (method, spp), rs in sorted(groups.items(), key=lambda kv: (order.index(kv[0][0]), kv[0][1])):
        out.append({"method": method, "spp": spp, "scenes": len(rs), **{k: float(np.mean([r[k] for r in rs])) for k in METRICS + TIMES}})
    return out


def mc_spp_for_error(spp: Sequence[float], err: Sequence[float], target: float) -> tuple[float, bool, float]:
    """Samples per pixel at which raw MC reaches relMSE ``target``.

    Interpolates log(err) against log(spp) between the ladder points (first
    crossing in spp order); outside the ladder, extrapolates from the nearest end
    with the least-squares slope of log(err) on log(spp) (MC theory: -1; a fitted
    slope that does not fall, > -0.05, is replaced by -1).

    Returns ``(spp_star, extrapolated, slope)``.
    """
    s = np.log(np.asarray(spp, dtype=np.float64))
    e = np.log(np.maximum(np.asarray(err, dtype=np.float64), 1e-30))
    idx = np.argsort(s)
    s, e = s[idx], e[idx]
    t = math.log(max(target, 1e-30))
    slope = float(np.polyfit(s, e, 1)[0]) if len(s) >= 2 else -1.0
    if not slope < -0.05:
        slope = -1.0
    for i in range(len(s) - 1):
        lo, hi = sorted((e[i], e[i + 1]))
        if lo <= t <= hi and e[i] != e[i + 1]:
            f = (t - e[i]) / (e[i + 1] - e[i])
            return float(math.exp(s[i] + f * (s[i + 1] - s[i]))), False, slope
    # outside the ladder: extrapolate from the end on the target's side
    j = -1 if t < e[-1] else 0
    return float(math.exp(s[j] + (t - e[j]) / slope)), True, slope


def render_time_model(spp: Sequence[float], seconds: Sequence[float]) -> tuple[float, float]:
    """Fit ``seconds = overhead + spp * per_sample`` (least squares; overhead >= 0, per_sample > 0).

    Returns ``(overhead, per_sample)``; falls back to ``(0, sum(seconds) / sum(spp))``.
    """
    x = np.asarray(spp, dtype=np.float64)
    y = np.asarray(seconds, dtype=np.float64)
    if len(x) >= 2 and np.ptp(x) > 0:
        b, a = np.polyfit(x, y, 1)
        if b > 0 and a >= 0:
            return float(a), float(b)
        if b > 0:  # negative intercept: force it to 0
            return 0.0, float(np.sum(x * y) / np.sum(x * x))
    return 0.0, float(y.sum() / x.sum())


def equal_time(rows: Sequence[dict], renders: dict[str, SceneRenders], model: str, model_spp: int) -> list[dict]:
    """The equal-time figure of every scene for ``model`` at ``model_spp`` (see the module docstring)."""
    out = []
    for label, sr in renders.items():
        mc = sorted((r for r in rows if r["scene"] == label and r["method"] == MC), key=lambda r: r["spp"])
        mr = [r for r in rows if r["scene"] == label and r["method"] == model and r["spp"] == model_spp]
        if not mc or not mr:
            continue
        target = mr[0]["relmse"]
        s_star, extrap, slope = mc_spp_for_error([r["spp"] for r in mc], [r["relmse"] for r in mc], target)
        times = [(s, float(f.meta["renderTimeSeconds"])) for s, f in sr.inputs.items()]
        times.append((sr.reference.spp, float(sr.reference.meta["renderTimeSeconds"])))
        overhead, per_sample = render_time_model(*zip(*times))
        mc_s = overhead + per_sample * s_star
        out.append({
            "scene": label, "model": model, "model_spp": model_spp, "model_relmse": target,
            "model_seconds": mr[0]["total_s"], "mc_spp": s_star, "extrapolated": extrap,
            "beyond_reference": s_star > sr.reference.spp, "slope": slope, "mc_seconds": mc_s,
            "seconds_per_sample": per_sample, "render_overhead_s": overhead,
            "time_ratio": mc_s / mr[0]["total_s"], "reference_floor_relmse": reference_floor(sr.reference),
        })
    return out


def _geomean(xs: Sequence[float]) -> float | None:
    xs = [x for x in xs if x and x > 0 and math.isfinite(x)]
    return float(math.exp(np.mean(np.log(xs)))) if xs else None


# ----------------------------------------------------------------------------- outputs


def write_csv(path: Path, rows: Sequence[dict]) -> None:
    """One row per (scene, spp, method) with :data:`CSV_FIELDS`."""
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=CSV_FIELDS, extrasaction="ignore", lineterminator="\n")
    wr.writeheader()
    for r in rows:
        wr.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    atomic_write(path, lambda tmp: Path(tmp).write_text(buf.getvalue()))


def _fmt(v: Any, key: str = "") -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (str, int, np.integer)):
        return str(v)
    if key in ("psnr",):
        return f"{v:.2f}"
    if key in ("ssim",):
        return f"{v:.4f}"
    if key.endswith("_s") or key.endswith("seconds"):
        return f"{v:.3f}"
    return f"{v:.4g}"


def _md_table(rows: Sequence[dict], cols: Sequence[tuple[str, str]]) -> str:
    head = "| " + " | ".join(title for _, title in cols) + " |"
    sep = "|" + "|".join("---" for _ in cols) + "|"
    body = ["| " + " | ".join(_fmt(r.get(k), k) for k, _ in cols) + " |" for r in rows]
    return "\n".join([head, sep, *body])


_ROW_COLS = [("relmse", "relMSE"), ("smape", "SMAPE"), ("psnr", "PSNR dB"), ("ssim", "SSIM"),
             ("render_s", "render s"), ("denoise_s", "denoise s"), ("total_s", "total s")]


def equal_time_markdown(eq: Sequence[dict], summary: dict | None) -> str:
    """The equal-time table and its explanation."""
    if not eq:
        return "No equal-time figure (the model or raw MC rows are missing)."
    m, s = eq[0]["model"], eq[0]["model_spp"]
    rows = [{**e, "mc_spp_txt": f"{e['mc_spp']:.1f}" + (" (extrapolated)" if e["extrapolated"] else "")
             + (" (beyond reference spp)" if e["beyond_reference"] else "")} for e in eq]
    cols = [("scene", "scene"), ("model_relmse", f"{m} relMSE @ {s} spp"), ("mc_spp_txt", "raw MC spp for that relMSE"),
            ("slope", "fitted MC slope"), ("mc_seconds", "raw MC seconds"), ("model_seconds", f"{m} seconds"),
            ("time_ratio", "time ratio (MC / model)"), ("reference_floor_relmse", "reference noise relMSE")]
    lines = [
        f"For each scene: the spp at which raw Monte Carlo reaches the relMSE of **{m} at {s} spp** "
        "(log-log interpolation along the raw ladder; outside it, extrapolation with the fitted slope of "
        "log relMSE against log spp, marked *extrapolated*), and the ratio of the raw MC render time at that "
        f"spp (fit `seconds = overhead + spp × seconds-per-sample` over the scene's renders) to {m}'s "
        "render + denoise seconds. A ratio above 1 means the denoiser reaches that error faster. "
        "The last column is the relMSE the reference's own noise contributes (from its variance buffer): "
        "errors near it are not resolved by this reference.",
        "",
        _md_table(rows, cols),
    ]
    if summary and summary.get("equal_time_geomean"):
        g = summary["equal_time_geomean"]
        lines += ["", f"Geometric mean over scenes: raw MC needs **{g['mc_spp']:.1f} spp** "
                      f"and **{g['time_ratio']:.2f}×** the time of {m} at {s} spp."]
    return "\n".join(lines)


def markdown_report(rows: Sequence[dict], means: Sequence[dict], eq: Sequence[dict], summary: dict) -> str:
    """The full Markdown report (also printed, mean table and equal-time figure first)."""
    cfg = summary["config"]
    rep = f" (median of {cfg['repeats']})" if cfg["repeats"] > 1 else ""
    parts = [
        f"# kpcn report: {cfg['name']}",
        "",
        f"{len(summary['scenes'])} scenes at {cfg['resolution'][0]}×{cfg['resolution'][1]}, "
        f"spp {', '.join(map(str, cfg['spp']))}, reference {cfg['ref_spp']} spp (independent seed). "
        f"Methods: {', '.join(summary['methods'])}.",
        "",
        "Times: render seconds are the wall time of the sampling (kernels compiled by an untimed warm-up render); "
        f"denoise seconds are the wall time of one denoise call{rep} (model: `kpcn.denoise.denoise` on the in-memory frame; "
        "OIDN: `pyoidn.denoise` with albedo and normal), after one untimed warm-up call per method so that "
        "first-call set-up is not counted, and after a pause that lets the renderer's threads go idle; "
        "total = render + denoise. "
        f"Machine: {summary['machine']}.",
    ]
    if summary["notes"]:
        parts += ["", "Notes:", *[f"- {n}" for n in summary["notes"]]]
    parts += ["", "## Mean over scenes", "", _md_table(means, [("method", "method"), ("spp", "spp"), *_ROW_COLS])]
    parts += ["", "## Equal time", "", equal_time_markdown(eq, summary)]
    parts += ["", "## Per scene", "", _md_table(rows, [("scene", "scene"), ("spp", "spp"), ("method", "method"), *_ROW_COLS])]
    parts += ["", "Figures: `error_vs_time.png` (relMSE against total seconds), `contact_sheet.png` "
                  f"({cfg['contact_spp']} spp)."]
    return "\n".join(parts) + "\n"


def _method_colors(methods: Sequence[str]) -> dict[str, str]:
    fixed = {MC: "black", "oidn": "tab:green", "kpcn": "tab:blue", "dpcn": "tab:orange"}
    spare = iter(["tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:gray"])
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


def plot_error_vs_time(path: Path, rows: Sequence[dict], means: Sequence[dict]) -> None:
    """Log-log relMSE against total seconds; one panel per scene plus the mean; one line per method."""
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


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def _machine() -> str:
    import torch

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    dev = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, {dev}, "
            f"torch {torch.__version__} with {torch.get_num_threads()} threads, load average {load:.2f} at start")


# ----------------------------------------------------------------------------- driver


@dataclass
class ReportResult:
    """What :func:`run_report` produced: CSV rows, mean rows, equal-time rows, summary.json content, Markdown, file paths."""

    rows: list[dict]
    means: list[dict]
    equal_time: list[dict]
    summary: dict
    markdown: str
    paths: dict[str, Path]
    rendered: list[str]  #: EXRs rendered in this run (empty when everything came from the cache)


def build_summary(cfg: ReportConfig, scenes: Sequence[str], methods: Sequence[Method], means: Sequence[dict],
                  eq: Sequence[dict], notes: list[str], machine: str, contact_spp: int, eq_spp: int) -> dict:
    """The content of ``summary.json``: config, mean metrics per method and spp, equal-time figures."""
    scene_names = [scene_label(s) if isinstance(s, dict) else os.fspath(s) for s in cfg.scenes]
    return {
        "config": {**asdict(cfg), "scenes": scene_names, "resolution": list(cfg.resolution),
                   "contact_spp": contact_spp, "equal_time_spp": eq_spp},
        "scenes": list(scenes),
        "methods": [MC] + [m.name for m in methods],
        "method_descriptions": {m.name: m.description for m in methods},
        "machine": machine,
        "notes": notes,
        "mean": {m: {str(r["spp"]): {k: r[k] for k in METRICS + TIMES} for r in means if r["method"] == m}
                 for m in dict.fromkeys(r["method"] for r in means)},
        "equal_time": list(eq),
        "equal_time_geomean": ({"model": eq[0]["model"], "model_spp": eq_spp,
                                "mc_spp": _geomean([e["mc_spp"] for e in eq]),
                                "time_ratio": _geomean([e["time_ratio"] for e in eq])} if eq else None),
    }


def write_outputs(folder: Path, rows, means, images, summary: dict, markdown: str, contact_spp: int, crop: int) -> dict[str, Path]:
    """Write the CSV, Markdown, plots and summary (each atomically); returns their paths."""
    paths = {"csv": folder / "results.csv", "markdown": folder / "report.md", "plot": folder / "error_vs_time.png",
             "contact_sheet": folder / "contact_sheet.png", "summary": folder / "summary.json"}
    write_csv(paths["csv"], rows)
    _write_text(paths["markdown"], markdown)
    plot_error_vs_time(paths["plot"], rows, means)
    contact_sheet(paths["contact_sheet"], images, rows, contact_spp, crop)
    _write_text(paths["summary"], json.dumps(summary, indent=1, default=_json_default))
    return paths


def run_report(cfg: ReportConfig | None = None, progress: Callable[[str], None] | None = None) -> ReportResult:
    """Render, evaluate and write the report for ``cfg`` (default :class:`ReportConfig`)."""
    cfg = cfg or ReportConfig()
    cfg.validate()
    say = progress or log.info
    machine = _machine()
    cfg.folder.mkdir(parents=True, exist_ok=True)

    methods, notes = build_methods(cfg)
    contact_spp = nearest_spp(cfg.spp, cfg.contact_spp)
    eq_spp = nearest_spp(cfg.spp, cfg.equal_time_spp)
    if eq_spp != cfg.equal_time_spp:
        notes.append(f"equal-time figure at {eq_spp} spp ({cfg.equal_time_spp} is not on the ladder)")

    rows, renders, images, rendered = [], {}, {}, []
    for scene in cfg.scenes:
        sr = render_scene(cfg, scene, say)
        if sr.label in renders:  # two XML files with the same name
            sr.label = f"{sr.label}#{len(renders)}"
        renders[sr.label] = sr
        rendered += sr.rendered
        if sr.rendered:
            time.sleep(SETTLE_SECONDS)
        r, imgs = evaluate_scene(sr, methods, keep_spp=contact_spp)
        rows += r
        images[sr.label] = imgs
        say(f"evaluated {sr.label}")

    means = mean_table(rows)
    model_names = [m.name for m in methods if m.name != "oidn"]
    eq = equal_time(rows, renders, model_names[0], eq_spp) if model_names else []
    if not model_names:
        notes.append("no kpcn model was evaluated: no equal-time figure")
    summary = build_summary(cfg, list(renders), methods, means, eq, notes, machine, contact_spp, eq_spp)
    md = markdown_report(rows, means, eq, summary)
    paths = write_outputs(cfg.folder, rows, means, images, summary, md, contact_spp, cfg.crop)
    return ReportResult(rows, means, eq, summary, md, paths, rendered)


def _parse_args(argv=None) -> tuple[ReportConfig, argparse.Namespace]:
    p = argparse.ArgumentParser(prog="python -m kpcn.report", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", help=f"XML paths, test:<name>, random:<seed> (default: {' '.join(DEFAULT_SCENES)})")
    p.add_argument("--spp", type=int, nargs="+", help="input spp ladder, each >= 2 (default: 2 4 8 16 32 64)")
    p.add_argument("--ref-spp", type=int, help="reference spp (default: 1024)")
    p.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), help="default: 128 128")
    p.add_argument("--models", nargs="+", help="registry names, checkpoint paths or label=path (default: kpcn dpcn)")
    p.add_argument("--no-oidn", action="store_true", help="leave OIDN out even if pyoidn is installed")
    p.add_argument("--out", help="results root (default: results/report)")
    p.add_argument("--name", help="report name: files go to <out>/<name>/ (default: default, or quick)")
    p.add_argument("--seed", type=int, help="base render seed (default: 0)")
    p.add_argument("--device", help="auto, cpu or cuda (default: auto)")
    p.add_argument("--tile", type=int, help="denoise tile size (default: 256)")
    p.add_argument("--repeats", type=int, help="timed denoise calls per frame, median reported (default: 1)")
    p.add_argument("--equal-time-spp", type=int, help="model spp of the equal-time figure (default: 8)")
    p.add_argument("--contact-spp", type=int, help="spp of the contact sheet (default: 8)")
    p.add_argument("--rerender", action="store_true", help="render again even when cached EXRs exist")
    p.add_argument("--quick", action="store_true", help="tiny run: 2 scenes at 24x24, spp 2 4, reference 64")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the Markdown summary")
    a = p.parse_args(argv)
    given = {
        "scenes": a.scenes, "spp": a.spp, "ref_spp": a.ref_spp,
        "resolution": tuple(a.resolution) if a.resolution else None, "models": a.models, "out": a.out,
        "name": a.name, "seed": a.seed, "device": a.device, "tile": a.tile, "repeats": a.repeats,
        "equal_time_spp": a.equal_time_spp, "contact_spp": a.contact_spp,
    }
    given = {k: v for k, v in given.items() if v is not None}
    if a.no_oidn:
        given["oidn"] = False
    if a.rerender:
        given["rerender"] = True
    cfg = ReportConfig.quick(**given) if a.quick else ReportConfig(**given)
    return cfg, a


def main(argv=None) -> int:
    cfg, args = _parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(name)s: %(message)s")
    logging.getLogger("kpcn.render").setLevel(logging.WARNING)  # its per-render override notes
    from .render import RendererUnavailable

    try:
        result = run_report(cfg)
    except RendererUnavailable as exc:
        print(f"error: {exc}")
        return 2
    md = result.markdown
    # stdout: the mean table and the equal-time figure (the per-scene table is in the file)
    print(md.split("\n## Per scene")[0].rstrip())
    print(f"\nwrote {', '.join(str(p) for p in result.paths.values())}")
    left_out = [n for n in result.summary["notes"] if n.startswith("model ")]
    if left_out:
        print(f"WARNING: {len(left_out)} of {len(cfg.models)} model(s) could not be loaded and are not in the report (see Notes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
