"""``train.detail_stage``: the network trained for the colour the pipeline gives, its detail stage included."""
import pytest
import torch

from kpcn.train import train
from test_train import _tiny_unet_cfg

STAGE = {"detail_radius": 2, "detail_eps": 0.01, "detail_clip": 0.15}


def _unet_cfg(tiny_dataset, tmp_path, name, model_kw=(), **train_kw):
    """test_train's tiny U-Net, stage 2 only (the stage acts on the colour)."""
    return _tiny_unet_cfg(tiny_dataset, tmp_path, name, dict(model_kw), **{"stage1_steps": 0, "stage2_steps": 2,
                                                                            **train_kw})


def test_detail_stage_trains_and_validates_the_pipelines_output(tiny_dataset, tmp_path):
    """A file trained without the stage starts a run with it (the stage adds no parameter); the run's first loss
    is the loss of the staged colour, so it differs from the same run's without the stage; ``with_detail`` on a
    whole rendered frame gives what ``denoise`` gives; the teacher's targets pass through the stage too; a model
    without a stage is refused."""
    from kpcn.config import ConfigError
    from kpcn.data import FrameDataset, PatchDataset
    from kpcn.inference import load_model
    from kpcn.inference.pipeline import denoise_result
    from kpcn.io import read_exr
    from kpcn.train import split_pairs
    from kpcn.train_steps import distill_targets, model_inputs, validate, with_detail

    train(_unet_cfg(tiny_dataset, tmp_path, "plain", stage2_steps=3, lr=3e-3), progress=False)
    src = str(tmp_path / "plain" / "model.safetensors")
    first = {}
    for name, on in (("staged", True), ("unstaged", False)):
        cfg = _unet_cfg(tiny_dataset, tmp_path, name, STAGE, init=src, lr=1e-12, detail_stage=on)
        first[name] = train(cfg, progress=False)["losses"][0]
    assert first["staged"] != pytest.approx(first["unstaged"], rel=1e-4, abs=0), first

    model = load_model(str(tmp_path / "staged" / "model.safetensors"), device="cpu")
    assert model.detail_regression == (2, 0.01, 0.15)
    pairs = split_pairs(_unet_cfg(tiny_dataset, tmp_path, "x"))[0]
    frames = FrameDataset(pairs[:1])
    f = frames[0]
    with torch.no_grad():
        out = with_detail(model, model({k: v[None] for k, v in model_inputs(model, f).items()}),
                          {k: f[k][None] for k in ("noisy_color", "noisy_normal")})
        raw = model({k: v[None] for k, v in model_inputs(model, f).items()})
    want = denoise_result(read_exr(pairs[0].input_path), model, tile=None, precision="float32").color
    got = out["color"][0].permute(1, 2, 0).numpy()
    assert abs(got - want).max() <= 1e-4 * max(1.0, float(abs(want).max()))
    assert (out["color"] - raw["color"]).abs().max() > 1e-4  # the stage did something on this frame
    kept: list = []
    assert validate(model, frames, "cpu", detail=True, keep=kept)["relmse"] != validate(model, frames, "cpu")["relmse"]
    torch.testing.assert_close(kept[0], out["color"][0])  # TensorBoard's image: the colour validation scored

    ds = PatchDataset(pairs, 24, 8, seed=1, label_spp=True)
    batch = torch.utils.data.default_collate([ds[i] for i in range(len(ds))])
    hi = batch["spp"] >= 8
    got = distill_targets(model, batch, 8, detail_of=model)["y_color"][hi]
    with torch.no_grad():
        sub = {k: v[hi] for k, v in batch.items()}
        want = with_detail(model, model(model_inputs(model, sub)), sub)["color"]
    torch.testing.assert_close(got, want)

    with pytest.raises(ConfigError, match="no detail stage"):
        train(_unet_cfg(tiny_dataset, tmp_path, "refused", detail_stage=True), progress=False)


def test_edge_upsample_trains_from_a_file_without_it(tiny_dataset, tmp_path):
    """``edge_upsample`` adds no parameter: a file trained without it starts a run with it; the run reads the
    batch's noisy normal (``model_inputs``), so its first loss differs from the same run's without it, and what
    training's inputs give on a whole frame is what ``denoise`` gives."""
    from kpcn.data import FrameDataset
    from kpcn.inference import load_model
    from kpcn.inference.pipeline import denoise_result
    from kpcn.io import read_exr
    from kpcn.train import split_pairs
    from kpcn.train_steps import model_inputs

    train(_unet_cfg(tiny_dataset, tmp_path, "flat", stage2_steps=3, lr=3e-3), progress=False)
    src = str(tmp_path / "flat" / "model.safetensors")
    first = {}
    for name, kw in (("edged", {"edge_upsample": 0.3}), ("bilinear", {})):
        first[name] = train(_unet_cfg(tiny_dataset, tmp_path, name, kw, init=src, lr=1e-12),
                            progress=False)["losses"][0]
    assert first["edged"] != pytest.approx(first["bilinear"], rel=1e-5, abs=0), first
    model = load_model(str(tmp_path / "edged" / "model.safetensors"), device="cpu")
    assert model.reads_normal and model.config.edge_upsample == 0.3
    pairs = split_pairs(_unet_cfg(tiny_dataset, tmp_path, "y"))[0]
    f = FrameDataset(pairs[:1])[0]
    inputs = {k: v[None] for k, v in model_inputs(model, f).items()}
    assert "normal" in inputs
    with torch.no_grad():
        got = model(inputs)["color"][0].permute(1, 2, 0).numpy()
    want = denoise_result(read_exr(pairs[0].input_path), model, tile=None, precision="float32").color
    assert abs(got - want).max() <= 1e-4 * max(1.0, float(abs(want).max()))
