"""Blender Cycles: rendering with bpy (kpcn[blender]), reading Cycles multilayer EXRs, denoising them.

The tests that render need Blender's Python module ``bpy`` (``pip install
'kpcn[blender]'``; scripts/setup.sh installs it, so CI runs them) and are
skipped, with that reason, only where it is not installed. The rest (the pass
mapping on synthetic passes, the command line's checks, the missing-bpy error,
kpcn importing without bpy) always run. Renders are tiny (32x32, a few spp) and
run once per module.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from kpcn.io import MissingLayerError, read_exr
from kpcn.io.cycles import convert_cycles
from kpcn.render import cycles as rc
from kpcn.render.cli import main as render_main

HAVE_BPY = rc.blender_available()
needs_bpy = pytest.mark.skipif(not HAVE_BPY, reason="Blender's Python module bpy is not installed "
                                                    "(pip install 'kpcn[blender]'; scripts/setup.sh installs it)")

CONTRACT = ("color", "diffuse", "specular", "albedo", "normal", "depth")
RES = (32, 32)
#: the passes Blender 5 writes for a render_cycles render (in view layer "ViewLayer")
BLENDER5_PASSES = ("Combined", "Depth", "Normal", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color",
                   "Glossy Direct", "Glossy Indirect", "Glossy Color", "Transmission Direct",
                   "Transmission Indirect", "Transmission Color", "Volume Direct", "Volume Indirect", "Emission",
                   "Environment", "Denoising Normal", "Denoising Albedo", "Denoising Depth")


def _rewrite(src: Path, dst: Path, drop) -> None:
    """Copy a multi-part EXR, leaving out the parts whose name ``drop`` accepts."""
    import OpenEXR

    with OpenEXR.File(str(src), separate_channels=True) as f:
        parts = []
        for p in f.parts:
            if drop(p.name()):
                continue
            channels = {n: np.array(c.pixels) for n, c in p.channels.items()}
            parts.append(OpenEXR.Part(dict(p.header), channels, name=p.name()))
    OpenEXR.File(parts).write(str(dst))


def _raw_passes(path: Path, view_layer: str = "ViewLayer") -> dict[str, np.ndarray]:
    """The file's Cycles passes read with OpenEXR alone: ``{pass: (H, W, C)}`` (view layer prefix removed)."""
    import OpenEXR

    out = {}
    with OpenEXR.File(str(path), separate_channels=True) as f:
        for p in f.parts:
            chans = {n.rsplit(".", 1)[1]: np.asarray(c.pixels, dtype=np.float64) for n, c in p.channels.items()}
            order = [c for c in ("R", "G", "B", "X", "Y", "Z", "A") if c in chans]
            out[p.name()[len(view_layer) + 1:]] = np.stack([chans[c] for c in order], axis=-1)
    return out


@pytest.fixture(scope="module")
def cycles_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("cycles")


@pytest.fixture(scope="module")
def noisy(cycles_dir):
    """A generated scene, 32x32, 8 spp, rendered for real: (path, CyclesRender, seconds)."""
    if not HAVE_BPY:
        pytest.skip("bpy is not installed")
    path = cycles_dir / "noisy.exr"
    t0 = time.perf_counter()
    r = rc.render_cycles(None, path, spp=8, seed=1, resolution=RES)
    return path, r, time.perf_counter() - t0


# ----------------------------------------------------------------------------- rendering and reading (bpy)


@needs_bpy
def test_render_writes_every_pass_atomically(noisy, cycles_dir):
    path, r, seconds = noisy
    print(f"generated scene {RES[0]}x{RES[1]}, 8 spp: Cycles {r.seconds:.2f} s, with Blender's start {seconds:.2f} s")
    assert r.resolution == RES and r.spp == 8 and r.seed == 1
    assert set(r.passes) == {f"ViewLayer.{p}" for p in BLENDER5_PASSES}, r.passes
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        names = [p.name() for p in f.parts]
        head = dict(f.parts[0].header)
    assert set(names) == {f"ViewLayer.{p}" for p in BLENDER5_PASSES}
    assert head["spp"] == 8 and head["seed"] == 1 and head["scene"] == "cycles:generated"
    assert head["renderTimeSeconds"] > 0
    assert not [n for n in os.listdir(cycles_dir) if n.endswith(".tmp.exr")]  # no temporary left


@needs_bpy
def test_split_sums_to_combined(noisy):
    path, _, _ = noisy
    raw = _raw_passes(path)
    frame = read_exr(path)
    color = raw["Combined"][..., :3]
    assert np.all(raw["Combined"][..., 3] == 1)  # opaque film
    # the mapping, computed here from the raw passes
    diffuse = (raw["Diffuse Direct"] + raw["Diffuse Indirect"]) * raw["Diffuse Color"]
    specular = ((raw["Glossy Direct"] + raw["Glossy Indirect"]) * raw["Glossy Color"]
                + (raw["Transmission Direct"] + raw["Transmission Indirect"]) * raw["Transmission Color"]
                + raw["Emission"] + raw["Environment"] + raw["Volume Direct"] + raw["Volume Indirect"])
    np.testing.assert_allclose(frame["diffuse"], diffuse, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(frame["specular"], specular, rtol=1e-6, atol=1e-7)
    total = frame["diffuse"].astype(np.float64) + frame["specular"]
    lit = color > 1e-3
    rel = np.abs(total - color)[lit] / color[lit]
    print(f"diffuse + specular vs Combined: max relative error {rel.max():.2e}, "
          f"sum|diff|/sum|Combined| {frame.meta['cycles_split_error']:.2e}")
    assert rel.max() < 1e-5
    assert np.abs(total - color).max() < 1e-5 * max(1.0, color.max())
    assert frame.meta["cycles_split_error"] < 1e-6
    # every component is there: the scene has diffuse, glossy, transmitted and environment light
    for name in ("Diffuse Direct", "Glossy Direct", "Transmission Indirect", "Environment"):
        assert raw[name].max() > 0, name


@needs_bpy
def test_read_exr_gives_the_contract_layers(noisy):
    path, _, _ = noisy
    frame = read_exr(path, require=CONTRACT)
    h, w = RES[1], RES[0]
    for name in CONTRACT:
        assert frame[name].shape == (h, w, 1 if name == "depth" else 3), name
        assert frame[name].dtype == np.float32 and np.isfinite(frame[name]).all(), name
    meta = frame.meta
    assert meta["source_layout"] == "cycles" and meta["cycles_view_layer"] == "ViewLayer"
    assert meta["spp"] == 8 and meta["seed"] == 1
    assert meta["cycles_passes"]["albedo"] == "Diffuse Color"
    assert meta["cycles_passes"]["normal"] == "Normal"
    assert meta["cycles_passes"]["depth"] == "Denoising Depth"
    raw = _raw_passes(path)
    np.testing.assert_array_equal(frame["color"], raw["Combined"][..., :3].astype(np.float32))
    assert np.abs(frame["normal"]).max() <= 1 + 1e-5
    sky = raw["Depth"][..., 0] >= 1e9  # Cycles' "no hit" (at the pixel's first sample)
    assert sky.any() and (~sky).any()
    assert frame["depth"].min() == 0 and frame["depth"].max() < 100  # 0 where nothing was hit, not 1e10
    # the Cycles passes stay in the frame next to the contract layers
    assert "ViewLayer.Diffuse Direct" in frame
    # OIDN's albedo beside the diffuse one: they differ on the metal and glass spheres (Diffuse Color is 0 there)
    np.testing.assert_array_equal(frame["denoisingAlbedo"], raw["Denoising Albedo"][..., :3].astype(np.float32))
    assert meta["cycles_passes"]["denoisingAlbedo"] == "Denoising Albedo"
    no_diffuse = frame["albedo"].max(-1) == 0
    assert no_diffuse.any() and (frame["denoisingAlbedo"][no_diffuse].max(-1) > 0.05).mean() > 0.5


@needs_bpy
def test_colour_albedo_normal_models_and_oidn_read_oidns_albedo(noisy):
    """The colour + albedo + normal spec and OIDN read Denoising Albedo where a file has it; the split specs
    keep the diffuse albedo; a file without it (Mitsuba's) is read as it is."""
    from kpcn.baselines import oidn_guides
    from kpcn.inputs import get_input_spec

    path, _, _ = noisy
    frame = read_exr(path, require=CONTRACT)
    can = get_input_spec("color_albedo_normal").select(frame)
    assert can["albedo"] is frame["denoisingAlbedo"] and can.meta["layers_from"] == {"albedo": "denoisingAlbedo"}
    assert frame["albedo"] is not frame["denoisingAlbedo"]  # the caller's frame is untouched
    assert get_input_spec("split_novar").select(frame)["albedo"] is frame["albedo"]
    assert oidn_guides(frame)[0] is frame["denoisingAlbedo"]
    del frame.layers["denoisingAlbedo"]
    assert get_input_spec("color_albedo_normal").select(frame) is frame and oidn_guides(frame)[0] is frame["albedo"]


@needs_bpy
def test_missing_glossy_passes_are_named_with_how_to_enable_them(noisy, cycles_dir):
    path, _, _ = noisy
    bad = cycles_dir / "no_glossy.exr"
    _rewrite(path, bad, drop=lambda name: "Glossy" in name)
    frame = read_exr(bad)  # nothing required: what can be derived is
    assert "diffuse" in frame and "specular" not in frame and frame.meta["source_layout"] == "cycles"
    with pytest.raises(MissingLayerError) as err:
        read_exr(bad, require=CONTRACT)
    msg = str(err.value)
    print(msg)
    assert err.value.missing == ["specular"]
    for text in ("Glossy Direct", "Glossy Indirect", "Glossy Color", "View Layer Properties → Passes",
                 "Light → Glossy: Direct, Indirect, Color", "view_layer.use_pass_glossy_direct",
                 "view_layer.use_pass_glossy_indirect", "view_layer.use_pass_glossy_color"):
        assert text in msg, text
    assert "Transmission" not in msg.split("found:")[0]  # only what is missing is named


@needs_bpy
def test_without_denoising_data(noisy, cycles_dir):
    path, _, _ = noisy
    fallback = cycles_dir / "no_denoising.exr"
    _rewrite(path, fallback, drop=lambda name: "Denoising" in name)
    frame = read_exr(fallback, require=CONTRACT)  # depth from the Depth pass
    assert frame.meta["cycles_passes"]["albedo"] == "Diffuse Color"
    assert frame.meta["cycles_passes"]["depth"] == "Depth"
    assert frame.meta["cycles_passes"]["normal"] == "Normal"
    assert frame["depth"].min() == 0 and frame["depth"].max() < 100  # Cycles' 1e10 "no hit" is 0
    bare = cycles_dir / "no_data.exr"
    _rewrite(path, bare, drop=lambda name: name.split(".", 1)[1] in ("Denoising Normal", "Denoising Depth",
                                                                      "Denoising Albedo", "Normal", "Depth"))
    with pytest.raises(MissingLayerError) as err:
        read_exr(bare, require=CONTRACT)
    msg = str(err.value)
    assert err.value.missing == ["depth", "normal"]
    for text in ("Denoising Data", "view_layer.cycles.denoising_store_passes", "view_layer.use_pass_normal",
                 "Normal or Denoising Normal"):
        assert text in msg, text


@needs_bpy
def test_blend_file_transparent_film_and_dotted_view_layer(cycles_dir):
    """A saved .blend: its size and view layer are kept, the changed settings logged; a transparent film
    (background not in Combined, but in the Environment pass) still splits exactly."""
    blend = cycles_dir / "scene.blend"
    code = ("import bpy, sys; from kpcn.render.cycles_scene import build_scene\n"
            "bpy.ops.wm.read_factory_settings(use_empty=True); s = bpy.context.scene; build_scene(bpy, s)\n"
            "s.render.resolution_x, s.render.resolution_y = 24, 16; s.render.film_transparent = True\n"
            "s.view_layers[0].name = 'Layer.One'; s.cycles.samples = 1024\n"
            "bpy.ops.wm.save_as_mainfile(filepath=sys.argv[1])\n")
    subprocess.run([sys.executable, "-c", code, str(blend)], check=True, capture_output=True)
    out = cycles_dir / "from_blend.exr"
    r = rc.render_cycles(blend, out, spp=4, seed=3)
    assert r.resolution == (24, 16)
    assert any(n.startswith("cycles.samples: 1024 -> 4") for n in r.notes), r.notes
    frame = read_exr(out, require=CONTRACT)
    assert frame.meta["cycles_view_layer"] == "Layer.One"
    assert frame.meta.get("cycles_transparent_film") is True
    assert "Environment" not in frame.meta["cycles_passes"]["specular"]
    assert frame.meta["cycles_split_error"] < 1e-6
    raw = _raw_passes(out, "Layer.One")
    assert raw["Combined"][..., 3].min() == 0 and raw["Environment"].max() > 0  # the case it handles


@needs_bpy
def test_denoise_cycles_file(noisy, cycles_dir):
    import torch

    import kpcn
    from kpcn.models import create_model

    path, _, _ = noisy
    torch.manual_seed(0)
    net = create_model("kpcn", input_spec="split_novar", layers=2, width=8, kernel_size=5)
    out = kpcn.denoise(path, model=net, out_path=cycles_dir / "denoised.exr")
    assert out.shape == (RES[1], RES[0], 3) and out.dtype == np.float32
    assert np.isfinite(out).all() and out.min() >= 0
    written = read_exr(cycles_dir / "denoised.exr")
    assert written.meta["spp"] == 8 and "albedo" in written and "depth" in written


@needs_bpy
def test_adaptive_sampling_gives_each_pixel_its_sample_count(noisy, cycles_dir):
    """Cycles' adaptive sampling, rendered for real: the Debug Sample Count pass is read as the sampleCount layer
    (each pixel's samples, from Cycles' minimum to --spp, more where the image is noisier), and the denoised file
    keeps it; a render without adaptive sampling has no count."""
    import torch

    import kpcn
    from kpcn.io import SAMPLE_COUNT
    from kpcn.models import create_model

    path = cycles_dir / "adaptive.exr"
    rc.render_cycles(None, path, spp=64, seed=2, resolution=(48, 48), adaptive_threshold=0.05)
    frame = read_exr(path)
    n = frame.sample_count()
    assert frame.meta["spp"] == 64 and "Debug Sample Count" in frame.meta["cycles_passes"][SAMPLE_COUNT]
    assert np.array_equal(n, np.round(n)) and 1 <= n.min() < n.max() == 64
    assert 0.1 < float((n < 64).mean()) < 1  # some pixels stopped early, not all
    # the pixels that got every sample are the noisier ones: a higher relative variance between neighbours
    lum = frame["color"].mean(-1)
    rough = np.abs(lum - np.roll(lum, 1, 0)) / (lum + 0.05)
    assert rough[n == 64].mean() > rough[n < 64].mean()
    assert SAMPLE_COUNT not in read_exr(noisy[0])  # without adaptive sampling there is no count pass
    torch.manual_seed(0)
    net = create_model("kpcn", input_spec="split_novar", layers=2, width=8, kernel_size=5)
    kpcn.denoise(path, model=net, out_path=cycles_dir / "adaptive_denoised.exr")
    np.testing.assert_array_equal(read_exr(cycles_dir / "adaptive_denoised.exr")[SAMPLE_COUNT][..., 0], n)


@needs_bpy
def test_variance_model_on_cycles_file_says_why(noisy):
    from kpcn.inference import load_model

    path, _, _ = noisy
    spec = load_model("kpcn:small", "cpu").input_spec
    with pytest.raises(MissingLayerError) as err:
        read_exr(path, require=spec.layers)
    assert "Cycles writes no variance passes" in str(err.value) and "split_novar" in str(err.value)


@needs_bpy
def test_cli_renders_generated_scene(cycles_dir, capsys):
    out = cycles_dir / "cli.exr"
    assert render_main(["cycles", "--generated", "--spp", "2", "--seed", "5", "--resolution", "16", "8",
                        "--out", str(out)]) == 0
    assert "16x8, 2 spp" in capsys.readouterr().out
    frame = read_exr(out, require=CONTRACT)
    assert frame.shape == (8, 16) and frame.meta["seed"] == 5 and frame.meta["spp"] == 2


QUALITY_RES = (64, 64)


@needs_bpy
def test_novar_model_beats_noisy_input_against_reference(cycles_dir):
    """kpcn:novar_small on a Cycles render: relMSE against a 512-spp Cycles reference (another seed)
    below the noisy input's; OIDN's on the same file is printed beside it."""
    from kpcn import denoise
    from kpcn.baselines import oidn_available, oidn_denoise, oidn_guides
    from kpcn.metrics import relmse
    from kpcn.models import list_weights

    if "kpcn:novar_small" not in list_weights():
        pytest.skip(f"the split_novar model kpcn:novar_small is not registered yet (shipped: {list_weights()})")
    noisy_path, ref_path = cycles_dir / "q_noisy.exr", cycles_dir / "q_ref.exr"
    rc.render_cycles(None, noisy_path, spp=8, seed=11, resolution=QUALITY_RES)
    rc.render_cycles(None, ref_path, spp=512, seed=12, resolution=QUALITY_RES)
    frame, ref = read_exr(noisy_path, require=CONTRACT), read_exr(ref_path, require=("color",))["color"]
    out = denoise(noisy_path, model="kpcn:novar_small")
    scores = {"noisy": relmse(frame["color"], ref), "kpcn:novar_small": relmse(out, ref)}
    if oidn_available():
        scores["oidn"] = relmse(oidn_denoise(frame["color"], *oidn_guides(frame)), ref)
    print("relMSE against 512 spp (8 spp input): " + ", ".join(f"{k} {v:.4f}" for k, v in scores.items()))
    assert scores["kpcn:novar_small"] < scores["noisy"]


# ----------------------------------------------------------------------------- no bpy needed


def _fake_cycles(h=4, w=5, prefix="ViewLayer", short=False, seed=0):
    """Synthetic Cycles passes (named like Blender 5, or ``short`` like Blender 2.8-4.x) whose sum is Combined."""
    rng = np.random.default_rng(seed)
    names = {"dd": ("Diffuse Direct", "DiffDir"), "di": ("Diffuse Indirect", "DiffInd"),
             "dc": ("Diffuse Color", "DiffCol"), "gd": ("Glossy Direct", "GlossDir"),
             "gi": ("Glossy Indirect", "GlossInd"), "gc": ("Glossy Color", "GlossCol"),
             "td": ("Transmission Direct", "TransDir"), "ti": ("Transmission Indirect", "TransInd"),
             "tc": ("Transmission Color", "TransCol"), "em": ("Emission", "Emit"), "env": ("Environment", "Env"),
             "al": ("Denoising Albedo", "Denoising Albedo"), "n": ("Normal", "Normal"), "z": ("Depth", "Depth")}
    p = {k: rng.random((h, w, 3), dtype=np.float32) for k in names}
    p["z"] = np.where(rng.random((h, w, 1)) < 0.3, 1e10, 5 * rng.random((h, w, 1))).astype(np.float32)
    combined = ((p["dd"] + p["di"]) * p["dc"] + (p["gd"] + p["gi"]) * p["gc"] + (p["td"] + p["ti"]) * p["tc"]
                + p["em"] + p["env"])
    layers = {f"{prefix}.{names[k][short]}" if prefix else names[k][short]: v for k, v in p.items()}
    layers[f"{prefix}.Combined" if prefix else "Combined"] = combined
    return layers, combined


@pytest.mark.parametrize("short", [False, True], ids=["blender5-names", "blender4-names"])
def test_mapping_on_synthetic_passes(short):
    layers, combined = _fake_cycles(prefix="My.View.Layer", short=short)
    meta: dict = {}
    header = {"cycles.My.View.Layer.samples": b"16", "cycles.My.View.Layer.total_time": "01:02.50"}
    cf = convert_cycles(layers, {}, meta, header)
    assert cf is not None and cf.view_layer == "My.View.Layer" and not cf.missing
    np.testing.assert_allclose(layers["diffuse"] + layers["specular"], combined, rtol=1e-6)
    assert meta["spp"] == 16 and meta["renderTimeSeconds"] == pytest.approx(62.5)
    assert meta["source_layout"] == "cycles"
    assert layers["depth"].max() < 5 and (layers["depth"] == 0).any()  # Depth's 1e10 (no hit) -> 0
    assert meta["cycles_passes"]["depth"] == "Depth"


def test_partial_passes_derive_what_they_can():
    layers, _ = _fake_cycles(prefix="ViewLayer")
    del layers["ViewLayer.Diffuse Color"]
    meta: dict = {}
    cf = convert_cycles(layers, {}, meta, {})
    assert "diffuse" not in layers and "specular" in layers and "color" in layers
    assert meta["cycles_passes"]["albedo"] == "Denoising Albedo"  # the fallback
    assert cf.missing["diffuse"] == [["diffuse_color"]]
    assert "Diffuse Color" in cf.explain(["diffuse"]) and "use_pass_diffuse_color" in cf.explain(["diffuse"])


def test_mapping_leaves_other_files_alone():
    layers = {"color": np.ones((2, 2, 3), np.float32), "diffuse": np.ones((2, 2, 3), np.float32),
              "specular": np.zeros((2, 2, 3), np.float32), "ViewLayer.Combined": np.ones((2, 2, 3), np.float32)}
    before = dict(layers)
    meta: dict = {}
    assert convert_cycles(layers, {}, meta, {}) is None
    assert layers == before and meta == {}
    assert convert_cycles({"albedo": np.ones((2, 2, 3), np.float32)}, {}, {}, {}) is None


def test_transparent_film_on_synthetic_passes():
    layers, combined = _fake_cycles(prefix="ViewLayer")
    env = layers["ViewLayer.Environment"]
    alpha = np.ones(combined.shape[:2], np.float32)
    alpha[0] = 0.0
    layers["ViewLayer.Combined"] = combined - env  # the film drops the background seen directly
    meta: dict = {}
    convert_cycles(layers, {"ViewLayer.Combined.A": alpha}, meta, {})
    assert meta["cycles_transparent_film"] is True
    np.testing.assert_allclose(layers["diffuse"] + layers["specular"], combined - env, rtol=1e-5, atol=1e-6)


def test_sum_mismatch_warns():
    layers, combined = _fake_cycles(prefix="ViewLayer")
    layers["ViewLayer.Combined"] = combined * 1.1  # light the passes do not carry (volumes without passes)
    meta: dict = {}
    with pytest.warns(RuntimeWarning, match="differ from Combined.*Volume Direct"):
        convert_cycles(layers, {}, meta, {}, path="x.exr")
    assert meta["cycles_split_error"] > 0.05


def test_render_cycles_without_bpy_says_how_to_install(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(rc, "blender_available", lambda: False)
    with pytest.raises(rc.BlenderUnavailable, match=r"pip install 'kpcn\[blender\]'"):
        rc.render_cycles(None, tmp_path / "x.exr", spp=4, seed=0)
    assert render_main(["cycles", "--generated", "--spp", "4", "--out", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install 'kpcn[blender]'" in err
    assert not (tmp_path / "x.exr").exists()


_REAL_RUN = subprocess.run


def _child_dies_first(monkeypatch, how: str, times: int) -> list:
    """``subprocess.run`` in :mod:`kpcn.render.cycles` replaced: its first ``times`` children run ``how`` (Python
    code that kills or ends the process) instead of the render; later ones render. Returns the list of calls."""
    real, calls = _REAL_RUN, []

    def run(args, **kw):
        calls.append(args)
        if len(calls) <= times:
            args = [sys.executable, "-c", how]
        return real(args, **kw)

    monkeypatch.setattr(rc.subprocess, "run", run)
    monkeypatch.setattr(rc, "blender_available", lambda: True)
    return calls


@needs_bpy
def test_a_child_killed_by_a_signal_is_rendered_again(monkeypatch, tmp_path, caplog):
    # the one abort on record (forty-second session): Cycles' heap corrupted in a fresh child, signal 6
    calls = _child_dies_first(monkeypatch, "import os, signal; os.kill(os.getpid(), signal.SIGABRT)", 1)
    with caplog.at_level("WARNING", logger="kpcn.render"):
        r = rc.render_cycles(None, tmp_path / "x.exr", spp=2, seed=0, resolution=(16, 16))
    assert len(calls) == 2 and r.resolution == (16, 16)
    assert read_exr(tmp_path / "x.exr")["color"].shape == (16, 16, 3)
    assert "died of signal 6" in caplog.text


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_a_child_crashing_twice_killed_or_failing_is_not_retried_further(monkeypatch, tmp_path):
    calls = _child_dies_first(monkeypatch, "import os, signal; os.kill(os.getpid(), signal.SIGABRT)", 2)
    with pytest.raises(RuntimeError, match="killed by signal 6, 2 times"):
        rc.render_cycles(None, tmp_path / "x.exr", spp=2, seed=0, resolution=(16, 16))
    assert len(calls) == 2 and not (tmp_path / "x.exr").exists()
    # an exit status is Blender's answer, not an accident of the process: no second try
    calls = _child_dies_first(monkeypatch, "import sys; print('boom'); sys.exit(3)", 5)
    with pytest.raises(RuntimeError, match=r"exit status 3\): boom"):
        rc.render_cycles(None, tmp_path / "x.exr", spp=2, seed=0, resolution=(16, 16))
    assert len(calls) == 1
    # nor a kill from outside (the out-of-memory killer's SIGKILL would come again)
    calls = _child_dies_first(monkeypatch, "import os, signal; os.kill(os.getpid(), signal.SIGKILL)", 5)
    with pytest.raises(RuntimeError, match=r"killed by signal 9\)"):
        rc.render_cycles(None, tmp_path / "x.exr", spp=2, seed=0, resolution=(16, 16))
    assert len(calls) == 1


@pytest.mark.parametrize("argv, text", [
    (["cycles", "--spp", "4", "--out", "x.exr"], "give a .blend file"),
    (["cycles", "a.blend", "--generated", "--out", "x.exr"], "either a .blend file or --generated"),
    (["cycles", "--generated", "--spp", "0", "--out", "x.exr"], "--spp"),
    (["cycles", "--generated", "--seed", "-1", "--out", "x.exr"], "--seed"),
    (["cycles", "--generated", "--resolution", "0", "4", "--out", "x.exr"], "--resolution"),
    (["cycles", "missing.blend", "--out", "x.exr"], "no such .blend file"),
    (["cycles", "--generated", "--adaptive-threshold", "0", "--out", "x.exr"], "--adaptive-threshold"),
])
def test_cli_usage_errors(argv, text, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert render_main(argv) == 2
    err = capsys.readouterr().err
    assert text in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.exr").exists()


def test_kpcn_imports_without_bpy():
    code = ("import sys, kpcn, kpcn.io, kpcn.render, kpcn.render.cycles, kpcn.render.cli\n"
            "assert 'bpy' not in sys.modules, 'bpy was imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_generated_scene_variants_are_drawn_from_their_seed():
    from kpcn.render.cycles_scene import scene_params

    fixed = scene_params(None)
    assert fixed["glossy"] == ((-1.1, 0.3), 1.0) and fixed["azimuth"] == 0.0  # the layout the tests above render
    assert scene_params(7) == scene_params(7)
    assert scene_params(7) != scene_params(8) and scene_params(7) != fixed
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="variant"):
            scene_params(bad)


@needs_bpy
def test_a_variant_renders_another_scene(cycles_dir):
    base, var = cycles_dir / "var_base.exr", cycles_dir / "var_5.exr"
    rc.render_cycles(None, base, spp=4, seed=3, resolution=(24, 24))
    rc.render_cycles(None, var, spp=4, seed=3, resolution=(24, 24), variant=5)
    a, b = read_exr(base)["albedo"], read_exr(var)["albedo"]  # albedo: noise-free enough to compare
    assert np.abs(a - b).mean() > 0.02
    with pytest.raises(ValueError, match="variant is for the generated scene"):
        rc.render_cycles(base, cycles_dir / "x.exr", spp=1, variant=1)


def test_cli_variant_needs_generated(tmp_path, capsys):
    assert render_main(["cycles", str(tmp_path / "a.blend"), "--variant", "2", "--out", str(tmp_path / "o.exr")]) == 2
    assert "--variant: only with --generated" in capsys.readouterr().err


@needs_bpy
def test_cycles_data_set_trains_a_model_without_variances(tmp_path):
    """`render dataset --renderer cycles`: variants of the generated scene in the contract layout (no variance
    layers), resumable like Mitsuba data sets, and a split-without-variances model trains on it."""
    import json

    from kpcn.config import load_config
    from kpcn.data import read_manifest
    from kpcn.train import train
    from kpcn.train_config import RunConfig

    out = tmp_path / "cyc"
    args = ["dataset", "--renderer", "cycles", "--out", str(out), "--scenes", "2", "--first-seed", "40",
            "--spp", "2", "4", "--ref-spp", "16", "--resolution", "24", "24"]
    assert render_main(args) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["complete"] and [s["source"] for s in manifest["scenes"]] == ["cycles:generated:40",
                                                                               "cycles:generated:41"]
    pairs = read_manifest(out)
    frame = read_exr(pairs[0].input_path)
    assert set(frame.layers) == {*CONTRACT, "denoisingAlbedo"} and frame.spp == 2  # OIDN's albedo kept too
    assert not list(out.rglob("*.cycles.exr"))  # Blender's own files are not left behind
    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*.exr")}
    assert render_main(args) == 0  # a second run renders nothing
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.exr")} == mtimes
    cfg = load_config(RunConfig, None, [f"data.root={out}", "data.patch_size=16", "data.patches_per_frame=4",
                                        "data.val_scenes=1", "data.sampling=uniform", "model.input_spec=split_novar", "model.layers=2",
                                        "model.width=8", "model.kernel_size=3", "train.batch_size=2",
                                        "train.stage1_steps=2", "train.stage2_steps=1", "name=t"])
    cfg.results_dir = str(tmp_path / "runs")
    result = train(cfg, progress=False)
    assert len(result["losses"]) == 3 and np.isfinite(result["losses"]).all()
