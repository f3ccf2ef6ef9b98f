"""The model contract: every registered model, its input spec, tiling, weights and configs.

Renders are real (Mitsuba, tiny); the models are random-init (the contract
must hold whatever the weights), with sharp kernels (large output gain) so
that a wrong halo, alignment or context shows up as a large error.
"""
from __future__ import annotations

import glob
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from kpcn import inference
from kpcn.checkpoint import CheckpointError, load_model_file, read_weights, save_weights
from kpcn.config import ConfigError, load_config
from kpcn.inputs import get_input_spec, list_input_specs
from kpcn.io import Frame, MissingLayerError
from kpcn.models import DenoiserModel, create_model, list_models, model_config_class
from kpcn.models.unet_branch import DeepBlock, FullResLevel

ROOT = Path(__file__).resolve().parents[1]
FRAME_RES = (150, 117)  # larger than two halos of the U-Net, not a multiple of its alignment


def _variants():
    """Every registered model with its default config, plus each other input spec it takes."""
    out = []
    for name in list_models():
        out.append((name, {}))
        fields = model_config_class(name).__dataclass_fields__
        if "input_spec" in fields:
            default = fields["input_spec"].default
            out += [(name, {"input_spec": s}) for s in list_input_specs() if s != default]
        out += [(name, kw) for kw in OPTION_VARIANTS.get(name, [])]
    return out


#: options that change how a model reconstructs (each runs through the contract tests too)
OPTION_VARIANTS = {"kpcn": [{"input_spec": "color_albedo_normal_noise", "precision_gate": True},
                            {"input_spec": "color_albedo_normal_noise", "demodulate": True}],
                   "unet_kpcn": [{"kernel_scales": 3}, {"kernel_scales": 2, "input_spec": "color_albedo_normal"},
                                 {"stem": "half", "kernel_scales": 3}, {"stem": "half", "kernel_scales": 1},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True, "up_kernel": 1},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True, "albedo_kernel": 3},
                                 {"stem": "half", "kernel_scales": 3, "up_kernel": 1,
                                  "specular_widths": [8, 12, 16, 24]},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True, "radiance_pool": True},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True, "radiance_pool": True,
                                  "radiance_mix": True, "albedo_kernel": 3},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True, "deep_blocks": 2},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True, "kernel_size": 3,
                                  "coarse_kernel": 5, "albedo_kernel": 3},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True, "albedo_kernel": 3,
                                  "edge_upsample": 0.5},
                                 {"kernel_scales": 3, "edge_upsample": 0.3},
                                 {"stem": "half", "kernel_scales": 3, "band_gain": True, "albedo_kernel": 3,
                                  "edge_upsample": 0.5, "fullres_channels": 4}]}


#: CPU-sized settings for models whose defaults are paper-sized (a new model runs with its defaults)
SMALL = {
    "kpcn": {"layers": 4, "width": 16},
    "dpcn": {"layers": 4, "width": 16},
    "mskpcn": {"width": 8, "blocks": 2, "tail_layers": 2, "kernel_size": 7},
}


def _sharp(name: str, **kw) -> DenoiserModel:
    torch.manual_seed(0)
    extra = {"out_init_gain": 5.0} if "out_init_gain" in model_config_class(name).__dataclass_fields__ else {}
    extra.update(SMALL.get(name, {}))
    extra.update(kw)
    model = create_model(name, **extra).eval()
    with torch.no_grad():  # a new deep block passes its input unchanged (second conv at zero): make it do something
        for m in model.modules():
            if isinstance(m, DeepBlock):
                m.conv2.weight.normal_(0.0, 0.05)
            if isinstance(m, FullResLevel):  # nor does a new full-resolution level (its output at zero)
                m.out.weight.normal_(0.0, 0.5)
    return model


@pytest.fixture(scope="module")
def frame(render) -> Frame:
    return render("test:glossy", spp=4, seed=1, resolution=FRAME_RES)


def _rel(a, b) -> float:
    return float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-12))


@pytest.mark.parametrize("name,kw", _variants(), ids=lambda v: v if isinstance(v, str) else ",".join(f"{k}={x}" for k, x in v.items()) or "default")
def test_every_model_tiled_equals_untiled(frame, name, kw):
    # float32: the property is the maths'. In bfloat16 (the default on CPUs with it) a hidden value that a tile's
    # convolution sums in another order can round to the next bfloat16 (seen: 1.4e-5 on an AVX-512 BF16 CPU without
    # AMX); tests/test_precision.py checks bfloat16 tiles and rows at its own tolerance
    model = _sharp(name, **kw)
    whole = inference.denoise(frame, model, tile=0, device="cpu", skip=False, precision="float32")
    assert whole.shape == frame["albedo"].shape and np.isfinite(whole).all()
    for tile in (24, 37):  # 37 is not a multiple of the U-Net's alignment: it is rounded up
        res = inference.denoise_result(frame, model, tile=tile, device="cpu", skip=False, precision="float32")
        assert res.stats.tiles > 4, "the frame must really be cut into tiles"
        assert _rel(whole, res.color) < 1e-5, f"{name} {kw} tile {tile}: {_rel(whole, res.color):.3g}"


def test_frame_context_and_alignment_matter(frame, monkeypatch):
    """Negative controls for the test above: a per-crop summary or unaligned crops break equality."""
    from kpcn.models import UNetKPCN

    model = _sharp("unet_kpcn")
    assert model.uses_frame_context and model.alignment == 8
    whole = inference.denoise(frame, model, tile=0, device="cpu", skip=False)
    monkeypatch.setattr(model, "uses_frame_context", False)  # each tile summarises its own crop
    assert _rel(whole, inference.denoise(frame, model, tile=24, device="cpu", skip=False)) > 1e-4
    monkeypatch.setattr(model, "uses_frame_context", True)
    monkeypatch.setattr(UNetKPCN, "alignment", property(lambda self: 1))
    assert _rel(whole, inference.denoise(frame, model, tile=20, device="cpu", skip=False)) > 1e-4


@pytest.mark.parametrize("name,kw", [(n, {}) for n in list_models()] + [(n, kw) for n, kws in OPTION_VARIANTS.items() for kw in kws],
                         ids=lambda v: v if isinstance(v, str) else ",".join(f"{k}={x}" for k, x in v.items()) or "default")
def test_declared_receptive_radius_bounds_the_dependence(name, kw):
    """Changing inputs just beyond the declared radius leaves the centre pixel unchanged."""
    model = _sharp(name, **kw)
    spec = model.input_spec
    r = model.receptive_radius
    size = 2 * r + 9
    g = torch.Generator().manual_seed(3)
    inputs = {b: torch.rand(1, spec.channels, size, size, generator=g) for b in spec.branches}
    inputs["albedo"] = torch.rand(1, 3, size, size, generator=g)
    if model.reads_normal:  # a guide the model reads beside the features (edge_upsample): its reach counts too
        inputs["normal"] = torch.rand(1, 3, size, size, generator=g) * 2 - 1
    c = size // 2
    with torch.no_grad():
        ctx = model.frame_context(inputs)
        base = model(inputs, ctx)["color"][0, :, c, c]
        far = {k: v.clone() for k, v in inputs.items()}
        ring = torch.ones(size, size, dtype=torch.bool)
        ring[c - r : c + r + 1, c - r : c + r + 1] = False  # everything farther than r from the centre
        for v in far.values():
            v[..., ring] = torch.rand(int(ring.sum()), generator=g) * 5
        moved = model(far, ctx)["color"][0, :, c, c]
        near = {k: v.clone() for k, v in inputs.items()}
        for v in near.values():
            v[..., c, c] += 3.0
        changed = model(near, ctx)["color"][0, :, c, c]
    torch.testing.assert_close(moved, base, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(changed, base), "the centre pixel should depend on its own input"


def test_input_specs_declare_their_layers(frame):
    for name in list_input_specs():
        spec = get_input_spec(name)
        buffers = {n: torch.from_numpy(np.ascontiguousarray(frame[n].transpose(2, 0, 1)))[None] for n in spec.layers}
        built = spec.build(buffers)
        assert set(built) == {*spec.branches, "albedo"}
        for b in spec.branches:
            assert built[b].shape[1] == spec.channels
        # every declared layer is needed: building without any one of them fails
        for missing in spec.layers:
            with pytest.raises(KeyError, match=missing):
                spec.build({k: v for k, v in buffers.items() if k != missing})


@pytest.mark.parametrize("spec", ["kpcn_split", "color_albedo_normal"])
def test_missing_layer_is_refused_naming_missing_and_found(frame, tmp_path, spec):
    from kpcn.io import write_exr

    model = _sharp("unet_kpcn", input_spec=spec)
    drop = "normal"
    path = tmp_path / "partial.exr"
    write_exr(path, {k: v for k, v in frame.layers.items() if k != drop})
    with pytest.raises(MissingLayerError) as err:
        inference.denoise(path, model, device="cpu")
    assert drop in err.value.missing and "albedo" in err.value.found and "normal" in str(err.value)


def test_color_albedo_normal_model_needs_only_those_layers(frame):
    model = _sharp("kpcn", input_spec="color_albedo_normal")
    only = Frame({k: frame[k] for k in ("color", "albedo", "normal")})
    out = inference.denoise(only, model, device="cpu", tile=40)
    assert out.shape == frame["color"].shape and np.isfinite(out).all() and out.min() >= 0


# ----------------------------------------------------------------------------- weights and checkpoints


def test_denoise_is_a_plain_function():
    import kpcn
    from kpcn import denoise

    assert callable(denoise) and denoise is inference.denoise and type(kpcn).__name__ == "module"
    assert type(sys.modules["kpcn.inference"]).__name__ == "module"


def test_shipped_weights_load_without_unpickling(monkeypatch):
    import pickle

    def refuse(*a, **k):
        raise AssertionError("shipped weights must not be unpickled")

    monkeypatch.setattr(pickle, "Unpickler", refuse)
    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(torch, "load", refuse)
    inference.weights._load_cached.cache_clear()
    from kpcn.models import list_weights

    for entry in list_weights():
        m = inference.load_model(entry, device="cpu")
        assert isinstance(m, DenoiserModel) and m.name == entry.split(":")[0]
    inference.weights._load_cached.cache_clear()


def test_weights_round_trip_exactly(tmp_path, frame):
    model = _sharp("unet_kpcn", input_spec="split_novar")
    path = save_weights(tmp_path / "m.safetensors", model, step=3)
    record, _ = read_weights(path)
    assert record["model"] == "unet_kpcn" and record["step"] == 3 and record["hparams"]["input_spec"] == "split_novar"
    again = load_model_file(path).eval()
    a = inference.denoise(frame, model, device="cpu", tile=0)
    b = inference.denoise(frame, again, device="cpu", tile=0)
    np.testing.assert_array_equal(a, b)


def _damaged(tmp_path, model):
    good = save_weights(tmp_path / "good.safetensors", model)
    data = good.read_bytes()
    (tmp_path / "truncated.safetensors").write_bytes(data[: len(data) // 2])
    (tmp_path / "empty.safetensors").write_bytes(b"")
    (tmp_path / "garbage.pt").write_bytes(b"\x00not a checkpoint" * 10)
    return good


def test_bad_checkpoints_give_clear_errors(tmp_path):
    model = _sharp("kpcn", layers=2, width=4, kernel_size=3)
    _damaged(tmp_path, model)
    for name, words in [("truncated.safetensors", "not a readable"), ("empty.safetensors", "empty"),
                        ("garbage.pt", "not a readable"), ("absent.safetensors", "not found")]:
        with pytest.raises(CheckpointError) as err:
            load_model_file(tmp_path / name)
        assert str(tmp_path / name) in str(err.value) and words in str(err.value), str(err.value)
    # an unknown model name, and hyper-parameters the model does not take
    from safetensors.torch import save_file

    state = {k: v.contiguous() for k, v in model.state_dict().items()}
    save_file(state, tmp_path / "unknown.safetensors", metadata={"kpcn": '{"model": "unet9000", "hparams": {}}'})
    with pytest.raises(CheckpointError, match=r"unknown.safetensors: model 'unet9000' is not registered"):
        load_model_file(tmp_path / "unknown.safetensors")
    save_file(state, tmp_path / "badkey.safetensors", metadata={"kpcn": '{"model": "kpcn", "hparams": {"layerz": 2}}'})
    with pytest.raises(CheckpointError, match=r"badkey.safetensors: .*layerz: unknown key; did you mean 'layers'"):
        load_model_file(tmp_path / "badkey.safetensors")


def test_pickle_checkpoints_need_an_explicit_trust_flag(tmp_path):
    model = _sharp("kpcn", layers=2, width=4, kernel_size=3)
    path = tmp_path / "old.pt"
    torch.save({"model": model.state_dict(), "model_name": "kpcn", "model_kwargs": model.hparams(),
                "rng": np.random.get_state()}, path)  # NumPy objects: only full unpickling loads them
    with pytest.raises(CheckpointError, match=r"old.pt: .*trust"):
        load_model_file(path)
    loaded = load_model_file(path, trust_pickle=True)
    for k, v in model.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[k], v)
    # a plain-tensor checkpoint loads with weights_only=True and no flag
    torch.save({"model": model.state_dict(), "model_name": "kpcn", "hparams": model.hparams()}, tmp_path / "plain.pt")
    assert isinstance(load_model_file(tmp_path / "plain.pt"), DenoiserModel)


def test_cli_bad_checkpoint_is_one_line_error(tmp_path, frame):
    from kpcn.io import write_exr

    _damaged(tmp_path, _sharp("kpcn", layers=2, width=4, kernel_size=3))
    exr = tmp_path / "in.exr"
    write_exr(exr, frame.layers)
    r = subprocess.run([sys.executable, "-m", "kpcn.inference", str(exr), "--model", str(tmp_path / "truncated.safetensors")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "truncated.safetensors: not a readable safetensors file" in r.stderr
    assert not (tmp_path / "in_denoised.exr").exists()


# ----------------------------------------------------------------------------- configs


@pytest.mark.parametrize("path", sorted(glob.glob(str(ROOT / "configs" / "*.yaml"))), ids=os.path.basename)
def test_every_config_loads_and_builds_its_model(path):
    from kpcn.train import build_model
    from kpcn.train_config import RunConfig

    cfg = load_config(RunConfig, path)
    model = build_model(cfg)
    assert isinstance(model, DenoiserModel) and model.name == cfg.model["name"]
    assert sum(p.numel() for p in model.parameters()) > 0


def test_config_errors_name_the_key_and_the_file(tmp_path):
    from kpcn.train_config import RunConfig

    bad = tmp_path / "bad.yaml"
    bad.write_text("model: {name: kpcn, layerz: 3}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: model.layerz: unknown key; did you mean 'layers'"):
        load_config(RunConfig, bad)
    bad.write_text("trian: {lr: 1}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: trian: unknown key; did you mean 'train'"):
        load_config(RunConfig, bad)
    bad.write_text("train: {batch_size: abc}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: train.batch_size: expected an integer, got 'abc'"):
        load_config(RunConfig, bad)
    bad.write_text("train: [unclosed\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: not valid YAML \(line"):
        load_config(RunConfig, bad)
    with pytest.raises(ConfigError, match=r"train.stage1_steps: expected an integer, got 'ten'"):
        load_config(RunConfig, None, ["train.stage1_steps=ten"])
    with pytest.raises(ConfigError, match=r"train.lrr: unknown key; did you mean 'lr'"):
        load_config(RunConfig, None, ["train.lrr=1e-3"])
    with pytest.raises(ConfigError, match=r"model.name: unknown model 'unet9000'"):
        load_config(RunConfig, None, ["model.name=unet9000"])
    cfg = load_config(RunConfig, None, ["train.lr=3e-4", "model.layers=3"])  # YAML 1.1 reads 3e-4 as a string
    assert cfg.train.lr == pytest.approx(3e-4) and cfg.model["layers"] == 3


def test_train_cli_reports_config_errors_in_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "kpcn.train", "--results-dir", str(tmp_path), "--set", "train.batch_size=abc"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "train.batch_size: expected an integer, got 'abc'" in r.stderr
    assert not any(tmp_path.iterdir()), "nothing may be written for a config that does not load"


def test_malformed_checkpoint_contents_name_the_file(tmp_path):
    model = _sharp("kpcn", layers=2, width=4, kernel_size=3)
    cases = {
        "list_model.pt": {"model": [1, 2], "model_name": "kpcn", "hparams": {}},
        "str_hparams.pt": {"model": model.state_dict(), "model_name": "kpcn", "hparams": "abc"},
        "empty_hparams.pt": {"model": model.state_dict(), "model_name": "kpcn", "hparams": {"layerz": 1}},
    }
    for fname, content in cases.items():
        torch.save(content, tmp_path / fname)
        with pytest.raises(CheckpointError, match=fname):
            load_model_file(tmp_path / fname)
    import pickle

    (tmp_path / "plain.pkl.pt").write_bytes(pickle.dumps({"model": 1}, protocol=4))
    with pytest.raises(CheckpointError, match=r"plain.pkl.pt: .*--trust-checkpoint"):
        load_model_file(tmp_path / "plain.pkl.pt")


def test_command_configs_share_one_system(tmp_path, capsys):
    """Bench, render-dataset and report settings: flags, --set and --config files, checked the same way."""
    from kpcn.bench.denoise import DenoiseBenchConfig
    from kpcn.config import parse_config
    from kpcn.render.dataset import DatasetConfig
    from kpcn.report import ReportConfig

    f = tmp_path / "b.yaml"
    f.write_text("models: [small_unet]\nspp: 8\n")
    cfg = parse_config(DenoiseBenchConfig, ["--config", str(f), "--set", "tile=64", "--no-oidn", "--spp", "16"], "b")
    assert (cfg.models, cfg.tile, cfg.oidn, cfg.spp, cfg.scene) == (["small_unet"], 64, False, 16, "random:3")
    with pytest.raises(SystemExit) as err:
        parse_config(DenoiseBenchConfig, ["--set", "tiel=64"], "b")
    assert err.value.code == 2 and "tiel: unknown key; did you mean 'tile'" in capsys.readouterr().err
    assert load_config(DatasetConfig, None, ["resolution=[32, 24]"]).resolution == (32, 24)
    with pytest.raises(ConfigError, match="spp and ref_spp: every sample count must be >= 2"):
        load_config(DatasetConfig, None, ["spp=[1, 4]"])
    with pytest.raises(ConfigError, match="scenez: unknown key; did you mean 'scenes'"):
        load_config(ReportConfig, None, ["scenez=[a]"])


def test_multiply_adds_per_pixel_match_a_hand_count():
    from kpcn.models import macs_per_pixel

    # KPCN, per branch: conv 27->4 (3x3), conv 4->9 (3x3), then a 3x3 kernel on RGB; two branches
    kpcn = create_model("kpcn", layers=2, width=4, conv_size=3, kernel_size=3)
    assert macs_per_pixel(kpcn) == 2 * (27 * 4 * 9 + 4 * 9 * 9 + 3 * 9)
    # U-Net, one branch (colour+albedo+normal, 9 ch), widths 4/6, 1 conv a level, no summary, 3x3 kernels:
    # enc0 9->4 at full res, enc1 4->6 at 1/4 of the pixels, dec0 (6+4)->4, head 4->9 (1x1), apply 3*9;
    # at inference dec0's 3x3 taps over the upsampled 6 channels collapse to 2x2 (4 taps) per output pixel
    unet = create_model("unet_kpcn", input_spec="color_albedo_normal", widths=[4, 6], convs_per_level=1,
                        kernel_size=3, summary_channels=0)
    assert macs_per_pixel(unet, 32, 32) == 9 * 4 * 9 + 4 * 6 * 9 / 4 + (4 * 9 + 6 * 4) * 4 + 4 * 9 + 3 * 9
    # the same with stem: half: every 3x3 conv at a quarter of the pixels or fewer, a 9->2 1x1 guide at full
    # resolution, the head's 4->9 part at half resolution and its 2->9 part at full
    half = create_model("unet_kpcn", input_spec="color_albedo_normal", widths=[4, 6], convs_per_level=1,
                        kernel_size=3, summary_channels=0, stem="half", guide_channels=2)
    assert macs_per_pixel(half, 32, 32) == (9 * 4 * 9 / 4 + 4 * 6 * 9 / 16 + (4 * 9 + 6 * 4) * 4 / 4 + 9 * 2
                                            + 4 * 9 / 4 + 2 * 9 + 3 * 9)
    # with up_kernel: 1 dec0 is a 3x3 of the 4 skip channels and a 1x1 of the 6 coarse ones at their resolution
    up1 = create_model("unet_kpcn", input_spec="color_albedo_normal", widths=[4, 6], convs_per_level=1,
                       kernel_size=3, summary_channels=0, stem="half", guide_channels=2, up_kernel=1)
    assert macs_per_pixel(up1, 32, 32) == (9 * 4 * 9 / 4 + 4 * 6 * 9 / 16 + 4 * 9 * 4 / 4 + 6 * 4 / 16 + 9 * 2
                                           + 4 * 9 / 4 + 2 * 9 + 3 * 9)


def test_specular_widths_multiply_adds_are_the_two_branches_own():
    """A model with ``specular_widths`` costs its diffuse branch's multiply-adds (a model of ``widths``, halved: two
    equal branches) plus its specular branch's (a model of the specular widths, halved)."""
    from kpcn.models import macs_per_pixel

    kw = dict(convs_per_level=1, kernel_size=3, summary_channels=2, stem="half", guide_channels=2, kernel_scales=2,
              up_kernel=1)
    wide, narrow = create_model("unet_kpcn", widths=[8, 12], **kw), create_model("unet_kpcn", widths=[4, 6], **kw)
    mixed = create_model("unet_kpcn", widths=[8, 12], specular_widths=[4, 6], **kw)
    assert macs_per_pixel(mixed, 32, 32) == (macs_per_pixel(wide, 32, 32) + macs_per_pixel(narrow, 32, 32)) / 2
    assert macs_per_pixel(mixed, 32, 32) < macs_per_pixel(wide, 32, 32)


def test_albedo_kernel_multiply_adds_match_a_hand_count():
    """``albedo_kernel: 3`` adds to the diffuse branch alone: 9 + 1 head outputs (the kernel's logits and the gate),
    each a 1x1 of the finest decoder level's 4 channels at half resolution and of the 2 guide channels at full,
    and the 3x3 kernel applied to the albedo's 3 channels."""
    from kpcn.models import macs_per_pixel

    kw = dict(widths=[4, 6], convs_per_level=1, kernel_size=3, summary_channels=0, stem="half", guide_channels=2,
              kernel_scales=2, up_kernel=1)
    plain, filt = create_model("unet_kpcn", **kw), create_model("unet_kpcn", albedo_kernel=3, **kw)
    assert macs_per_pixel(filt, 32, 32) - macs_per_pixel(plain, 32, 32) == 10 * (4 / 4 + 2) + 3 * 9
