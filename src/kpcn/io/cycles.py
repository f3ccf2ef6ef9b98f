"""Blender Cycles multilayer EXRs read into the kpcn contract: :func:`convert_cycles`.

Cycles writes one layer per render pass, named ``<view layer>.<pass>``
(``ViewLayer.Diffuse Direct.R``; Blender before 5.0 used short names,
``ViewLayer.DiffDir.R``). When a file has Cycles passes and no ``diffuse`` /
``specular`` layers, :func:`kpcn.io.read_exr` derives the contract layers from
them (``frame.meta["source_layout"] = "cycles"``):

==============  ================================================================================
layer           Cycles passes
==============  ================================================================================
``color``       Combined (RGB; premultiplied by alpha, as Cycles writes it)
``diffuse``     (Diffuse Direct + Diffuse Indirect) × Diffuse Color
``specular``    (Glossy Direct + Glossy Indirect) × Glossy Color
                + (Transmission Direct + Transmission Indirect) × Transmission Color
                + Emission + Environment (+ Volume Direct + Volume Indirect when present)
``albedo``      Diffuse Color (the diffuse albedo at the first hit); without it, Denoising Albedo
``normal``      Normal (world space, first hit); without it, Denoising Normal (camera space)
``depth``       Denoising Depth (distance along the camera ray, 0 where nothing was hit);
                without it, Depth (distance along the view axis; Cycles' 1e10 for "no hit" -> 0)
``denoisingAlbedo``  Denoising Albedo (optional): the albedo OIDN takes, which follows mirrors and glass
                to the next rough surface; the ``color_albedo_normal`` spec reads it in place of
                ``albedo`` when a frame has it (:attr:`kpcn.inputs.InputSpec.prefer`)
``sampleCount`` Debug Sample Count (optional) × the render's samples: each pixel's samples under adaptive
                sampling (Cycles writes them as a fraction of the render's samples)
==============  ================================================================================

Cycles stores each light pass divided by its colour pass, so the products above
give back the radiance, and ``diffuse + specular`` equals Combined to float
rounding. The albedo is Diffuse Color rather than Denoising Albedo (which
follows mirrors and glass to the next rough surface, for OIDN): ``diffuse /
albedo`` is then exactly the untextured light, as in kpcn's Mitsuba data, and
``kpcn:novar_small`` denoises about a third better with it (relMSE 0.0064
against 0.0099 at 4 spp, 0.0023 against 0.0030 at 16 spp, on the generated
scene); the choice of normal and depth pass changed nothing measurable. The
Denoising passes stay in the frame under their Cycles names.

With a transparent film (Combined's alpha below 1) the directly seen
background is not in Combined but is still in the Environment pass; the
Environment pass is then left out of ``specular`` when that is what makes the
sum match Combined. When the sum still differs from Combined (passes the file
lacks, e.g. volumes rendered without the Volume passes), a warning gives the
difference. Cycles has no variance passes: Cycles files go with the
``split_novar`` input spec.

The view layer may have any name; a file with several is read from the one with
the most Cycles passes (``frame.meta["cycles_view_layer"]``). The Cycles layers
themselves are kept in the frame next to the contract layers.
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from typing import Iterable, Mapping

import numpy as np

from ..constants import OIDN_ALBEDO
from .frame import SAMPLE_COUNT

__all__ = ["CYCLES_PASSES", "CyclesFile", "convert_cycles", "cycles_pass_help"]

#: kpcn's key of each Cycles pass -> its layer names (Blender 5 first, then the short names of Blender 2.8-4.x)
CYCLES_PASSES: dict[str, tuple[str, ...]] = {
    "combined": ("Combined",),
    "diffuse_direct": ("Diffuse Direct", "DiffDir"),
    "diffuse_indirect": ("Diffuse Indirect", "DiffInd"),
    "diffuse_color": ("Diffuse Color", "DiffCol"),
    "glossy_direct": ("Glossy Direct", "GlossDir"),
    "glossy_indirect": ("Glossy Indirect", "GlossInd"),
    "glossy_color": ("Glossy Color", "GlossCol"),
    "transmission_direct": ("Transmission Direct", "TransDir"),
    "transmission_indirect": ("Transmission Indirect", "TransInd"),
    "transmission_color": ("Transmission Color", "TransCol"),
    "subsurface_direct": ("Subsurface Direct", "SubsurfaceDir"),
    "subsurface_indirect": ("Subsurface Indirect", "SubsurfaceInd"),
    "subsurface_color": ("Subsurface Color", "SubsurfaceCol"),
    "volume_direct": ("Volume Direct", "VolumeDir"),
    "volume_indirect": ("Volume Indirect", "VolumeInd"),
    "emission": ("Emission", "Emit"),
    "environment": ("Environment", "Env"),
    "denoising_albedo": ("Denoising Albedo",),
    "denoising_normal": ("Denoising Normal",),
    "denoising_depth": ("Denoising Depth",),
    "normal": ("Normal",),
    "depth": ("Depth", "Z"),
    "sample_count": ("Debug Sample Count",),
}

# Where each pass is switched on: (View Layer Properties → Passes → section, its checkbox, the bpy property)
_HOW = {
    "combined": ("Data", "Combined", "view_layer.use_pass_combined"),
    "diffuse_direct": ("Light → Diffuse", "Direct", "view_layer.use_pass_diffuse_direct"),
    "diffuse_indirect": ("Light → Diffuse", "Indirect", "view_layer.use_pass_diffuse_indirect"),
    "diffuse_color": ("Light → Diffuse", "Color", "view_layer.use_pass_diffuse_color"),
    "glossy_direct": ("Light → Glossy", "Direct", "view_layer.use_pass_glossy_direct"),
    "glossy_indirect": ("Light → Glossy", "Indirect", "view_layer.use_pass_glossy_indirect"),
    "glossy_color": ("Light → Glossy", "Color", "view_layer.use_pass_glossy_color"),
    "transmission_direct": ("Light → Transmission", "Direct", "view_layer.use_pass_transmission_direct"),
    "transmission_indirect": ("Light → Transmission", "Indirect", "view_layer.use_pass_transmission_indirect"),
    "transmission_color": ("Light → Transmission", "Color", "view_layer.use_pass_transmission_color"),
    "volume_direct": ("Light → Volume", "Direct", "view_layer.cycles.use_pass_volume_direct"),
    "volume_indirect": ("Light → Volume", "Indirect", "view_layer.cycles.use_pass_volume_indirect"),
    "emission": ("Light → Other", "Emission", "view_layer.use_pass_emit"),
    "environment": ("Light → Other", "Environment", "view_layer.use_pass_environment"),
    "denoising_albedo": ("Data", "Denoising Data", "view_layer.cycles.denoising_store_passes"),
    "denoising_normal": ("Data", "Denoising Data", "view_layer.cycles.denoising_store_passes"),
    "denoising_depth": ("Data", "Denoising Data", "view_layer.cycles.denoising_store_passes"),
    "normal": ("Data", "Normal", "view_layer.use_pass_normal"),
    "depth": ("Data", "Z", "view_layer.use_pass_z"),
    "sample_count": ("Data", "Debug Sample Count", "view_layer.cycles.pass_debug_sample_count"),
}

_DIFFUSE = (("diffuse_direct", "diffuse_indirect", "diffuse_color"),)
_SPECULAR = (("glossy_direct", "glossy_indirect", "glossy_color"),
             ("transmission_direct", "transmission_indirect", "transmission_color"))
_SPECULAR_ADDED = ("emission", "environment")
_OPTIONAL_DIFFUSE = ("subsurface_direct", "subsurface_indirect", "subsurface_color")  # Blender < 3.0 files
_OPTIONAL_SPECULAR = ("volume_direct", "volume_indirect")

#: per contract layer: the passes it needs (all of them), or alternatives (the first complete one is used)
_NEEDS: dict[str, tuple[tuple[str, ...], ...]] = {
    "color": (("combined",),),
    "diffuse": (tuple(p for g in _DIFFUSE for p in g),),
    "specular": (tuple(p for g in _SPECULAR for p in g) + _SPECULAR_ADDED,),
    "albedo": (("diffuse_color",), ("denoising_albedo",)),
    "normal": (("normal",), ("denoising_normal",)),
    "depth": (("denoising_depth",), ("depth",)),
}

#: Cycles' depth for "nothing hit" is 1e10; anything this far is taken as a miss
_NO_HIT_DEPTH = 1e9
#: relative difference sum|Combined - (diffuse + specular)| / sum|Combined| above which a warning is given
SPLIT_TOLERANCE = 1e-4

_ALIAS_INDEX = sorted(((alias, key) for key, aliases in CYCLES_PASSES.items() for alias in aliases),
                      key=lambda a: -len(a[0]))


def _match_pass(layer: str) -> tuple[str, str] | None:
    """``(view layer, pass key)`` of a layer name like ``ViewLayer.Diffuse Direct`` (None: not a Cycles pass)."""
    for alias, key in _ALIAS_INDEX:
        if layer == alias:
            return "", key
        if layer.endswith("." + alias):
            return layer[: -len(alias) - 1], key
    return None


def cycles_pass_help(keys: Iterable[str]) -> str:
    """Where to switch the passes ``keys`` on in Blender, and their bpy property names (one sentence)."""
    keys = [k for k in dict.fromkeys(keys) if k in _HOW]
    sections: dict[str, list[str]] = {}
    for k in keys:
        items = sections.setdefault(_HOW[k][0], [])
        if _HOW[k][1] not in items:
            items.append(_HOW[k][1])
    ui = [f"{section}: {', '.join(items)}" for section, items in sections.items()]
    props = list(dict.fromkeys(_HOW[k][2] for k in keys))
    return (f"enable them in Blender under View Layer Properties → Passes → {'; '.join(ui)} "
            f"(bpy: {', '.join(f'{p} = True' for p in props)}) and render again, or render with "
            "`python -m kpcn.render cycles scene.blend`, which enables every pass kpcn reads")


@dataclass
class CyclesFile:
    """What :func:`convert_cycles` found: the view layer, the passes used and those missing per layer."""

    view_layer: str
    passes: dict[str, str]  # pass key -> layer name in the file
    used: dict[str, str] = field(default_factory=dict)  # contract layer -> the passes it came from
    #: contract layer -> the pass keys it lacks, per alternative (any one complete alternative would do)
    missing: dict[str, list[list[str]]] = field(default_factory=dict)

    def explain(self, missing_layers: Iterable[str]) -> str:
        """A note for :class:`~kpcn.io.MissingLayerError`: the Cycles passes behind ``missing_layers``."""
        missing_layers = list(missing_layers)
        vl = f"view layer {self.view_layer!r}" if self.view_layer else "no view-layer prefix"
        bits, keys = [], []
        for layer in missing_layers:
            options = self.missing.get(layer)
            if options:
                names = " or ".join(", ".join(CYCLES_PASSES[k][0] for k in o) for o in options)
                bits.append(f"{layer} needs the Cycles pass{'es' if len(options[0]) > 1 else ''} {names}")
                keys += [k for o in options for k in o]
        text = f"a Blender Cycles render ({vl})"
        if bits:
            text += f": {'; '.join(bits)}, which the file lacks; {cycles_pass_help(keys)}"
        if any(n.endswith("Variance") for n in missing_layers):
            text += ("; Cycles writes no variance passes: denoise Cycles files with a model of the "
                     "split_novar input spec (kpcn:novar_small)")
        return text


def _seconds(text) -> float | None:
    """Blender's ``[HH:]MM:SS.cc`` render time in seconds (None if it does not parse)."""
    if isinstance(text, bytes):
        text = text.decode("ascii", "replace")
    if not isinstance(text, str) or not re.fullmatch(r"\d+(:\d+){0,2}(\.\d+)?", text.strip()):
        return None
    total = 0.0
    for part in text.strip().split(":"):
        total = total * 60 + float(part)
    return total


def _header_meta(header: Mapping, view_layer: str) -> dict:
    """``spp`` and ``renderTimeSeconds`` from the attributes Blender writes (``cycles.<view layer>.samples``)."""
    meta = {}
    samples = header.get(f"cycles.{view_layer}.samples")
    if isinstance(samples, bytes):
        samples = samples.decode("ascii", "replace")
    try:
        meta["spp"] = int(str(samples).strip())
    except ValueError:
        pass
    for key in (f"cycles.{view_layer}.total_time", "RenderTime"):
        seconds = _seconds(header.get(key))
        if seconds is not None:
            meta["renderTimeSeconds"] = seconds
            break
    return meta


def convert_cycles(
    layers: dict[str, np.ndarray],
    channels: Mapping[str, np.ndarray],
    meta: dict,
    header: Mapping | None = None,
    *,
    path: str = "",
) -> CyclesFile | None:
    """Add the contract layers derived from Cycles passes to ``layers`` (in place); None if not a Cycles file.

    Applies when ``layers`` has no ``diffuse`` and no ``specular`` and holds
    Cycles passes (Combined or a light pass). Contract layers already present
    are kept. A contract layer whose passes are missing is left out, and the
    returned :class:`CyclesFile` says which passes it lacks (for the missing-layer
    error). ``meta`` gets ``source_layout = "cycles"``, ``cycles_view_layer``,
    ``cycles_passes`` (contract layer -> passes used) and, from Blender's header
    attributes when the file has none of its own, ``spp`` and ``renderTimeSeconds``.

    Args:
        layers: the layers read (``{name: (H, W, C)}``), Cycles' among them.
        channels: the raw channels (for Combined's alpha).
        meta: the frame's metadata, updated in place.
        header: the first part's header (Blender's render attributes).
        path: for the warnings.
    """
    if "diffuse" in layers or "specular" in layers:
        return None
    found: dict[str, dict[str, str]] = {}
    for name in layers:
        m = _match_pass(name)
        if m is not None:
            found.setdefault(m[0], {}).setdefault(m[1], name)
    light = {"combined", *(p for g in _DIFFUSE + _SPECULAR for p in g)}  # not Emission alone: a common name
    candidates = {vl: passes for vl, passes in found.items() if light & set(passes)}
    if not candidates:
        return None
    order = list(candidates)
    view_layer = max(order, key=lambda vl: (len(candidates[vl]), -order.index(vl)))
    cf = CyclesFile(view_layer, candidates[view_layer])

    def get(key: str) -> np.ndarray:
        return layers[cf.passes[key]]

    def pick(target: str) -> tuple[str, ...] | None:
        for option in _NEEDS[target]:
            if all(k in cf.passes for k in option):
                cf.used[target] = ", ".join(CYCLES_PASSES[k][0] for k in option)
                return option
        cf.missing[target] = [[k for k in o if k not in cf.passes] for o in _NEEDS[target]]
        return None

    derived: dict[str, np.ndarray] = {}
    if pick("color"):
        derived["color"] = get("combined")
    if pick("diffuse"):
        groups = _DIFFUSE + ((_OPTIONAL_DIFFUSE,) if all(k in cf.passes for k in _OPTIONAL_DIFFUSE) else ())
        derived["diffuse"] = sum((get(d) + get(i)) * get(c) for d, i, c in groups)
        cf.used["diffuse"] = ", ".join(CYCLES_PASSES[k][0] for g in groups for k in g)
    if pick("specular"):
        spec = sum((get(d) + get(i)) * get(c) for d, i, c in _SPECULAR) + get("emission")
        volumes = [k for k in _OPTIONAL_SPECULAR if k in cf.passes]
        for k in volumes:
            spec = spec + get(k)
        env = get("environment")
        with_env = spec + env
        extra = ["emission", "environment", *volumes]
        alpha = channels.get(f"{cf.passes['combined']}.A") if "combined" in cf.passes else None
        if alpha is not None and np.any(alpha < 1) and "diffuse" in derived and np.any(env != 0):
            # transparent film: the background seen directly is in Environment but not in Combined
            color, diffuse = derived["color"], derived["diffuse"]
            if np.abs(diffuse + spec - color).sum() < np.abs(diffuse + with_env - color).sum():
                with_env = spec
                extra.remove("environment")
                meta["cycles_transparent_film"] = True
        derived["specular"] = with_env
        cf.used["specular"] = ", ".join(CYCLES_PASSES[k][0] for k in
                                        [p for g in _SPECULAR for p in g] + extra)
    option = pick("albedo")
    if option:
        derived["albedo"] = get(option[0])
    if "denoising_albedo" in cf.passes:  # optional: for models that take OIDN's albedo
        derived[OIDN_ALBEDO] = get("denoising_albedo")
        cf.used[OIDN_ALBEDO] = CYCLES_PASSES["denoising_albedo"][0]
    option = pick("normal")
    if option:
        derived["normal"] = get(option[0])
        if option[0] == "denoising_normal":
            meta["cycles_normal_space"] = "camera"
    option = pick("depth")
    if option:
        depth = get(option[0])
        if option[0] == "depth":
            depth = np.where(depth >= _NO_HIT_DEPTH, np.float32(0), depth).astype(np.float32)
        derived["depth"] = depth

    header_meta = _header_meta(header or {}, view_layer)
    spp = meta.get("spp", header_meta.get("spp"))
    if "sample_count" in cf.passes and spp:
        # Cycles writes each pixel's samples over the render's (adaptive sampling); measured: multiples of
        # 16/64 at 64 samples, 1 everywhere without adaptive sampling
        derived[SAMPLE_COUNT] = np.round(get("sample_count")[..., :1] * float(spp))
        cf.used[SAMPLE_COUNT] = f"{CYCLES_PASSES['sample_count'][0]} × {int(spp)} samples"
    added = [n for n in derived if n not in layers]
    for name in added:
        layers[name] = np.ascontiguousarray(derived[name], dtype=np.float32)
    meta["source_layout"] = "cycles"
    meta["cycles_view_layer"] = view_layer
    meta["cycles_passes"] = {n: cf.used[n] for n in added}
    for key, value in header_meta.items():
        meta.setdefault(key, value)

    if "color" in layers and "diffuse" in added and "specular" in added:
        color = layers["color"].astype(np.float64)
        total = np.abs(color).sum()
        diff = np.abs(layers["diffuse"] + layers["specular"] - color).sum()
        err = float(diff / total) if total > 0 else float(diff > 0)
        meta["cycles_split_error"] = err
        if err > SPLIT_TOLERANCE:
            absent = [k for k in _OPTIONAL_SPECULAR if k not in cf.passes]
            why = (f" (not in the file: {', '.join(CYCLES_PASSES[k][0] for k in absent)}: {cycles_pass_help(absent)})"
                   if absent else " (shadow catcher, holdout, light paths kpcn does not split?)")
            warnings.warn(
                f"{path or 'frame'}: Cycles passes: diffuse + specular differ from Combined by {err:.2%} of its "
                f"total; the file lacks passes that carry light{why}",
                RuntimeWarning,
                stacklevel=3,
            )
    return cf
