"""bfloat16 hidden layers (:mod:`kpcn.inference.precision`, ``DenoiserModel.set_compute_dtype``,
``train.precision``).

bfloat16 keeps 8 bits of mantissa, so its results are compared with float32 ones on a real render by how
much they move the error against the reference, not bit for bit. The properties that hold by the
model's construction in float32 (a zero branch stays zero, a constant image stays constant) must hold in
bfloat16 too, since the kernels and their application stay float32.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from kpcn import inference
from kpcn.features import frame_to_tensors
from kpcn.inference import precision as prec
from kpcn.metrics import relmse
from kpcn.models import create_model

RES = (64, 48)


def _unet(**kw):
    torch.manual_seed(0)
    cfg = dict(widths=[8, 8, 12, 12], stem="half", kernel_scales=3, out_init_gain=5.0)
    cfg.update(kw)
    return create_model("unet_kpcn", **cfg).eval()


def test_auto_is_bfloat16_only_where_it_is_native_and_the_model_can(monkeypatch):
    unet, kpcn = _unet(), create_model("kpcn", layers=2, width=4)
    monkeypatch.delenv("KPCN_PRECISION", raising=False)
    monkeypatch.setattr(prec, "native_bfloat16", lambda device="cpu": True)
    assert prec.resolve_precision("auto", unet, "cpu") == torch.bfloat16
    assert prec.resolve_precision("auto", kpcn, "cpu") == torch.float32  # it cannot: float32, no error
    monkeypatch.setattr(prec, "native_bfloat16", lambda device="cpu": False)
    assert prec.resolve_precision("auto", unet, "cpu") == torch.float32
    assert prec.resolve_precision("bfloat16", unet, "cpu") == torch.bfloat16  # asked for: given, if slowly
    monkeypatch.setenv("KPCN_PRECISION", "bfloat16")
    assert prec.resolve_precision("auto", unet, "cpu") == torch.bfloat16
    assert prec.resolve_precision("float32", unet, "cpu") == torch.float32  # an explicit choice wins
    monkeypatch.setenv("KPCN_PRECISION", "half")
    with pytest.raises(ValueError, match="KPCN_PRECISION must be one of auto, float32, bfloat16, got 'half'"):
        prec.resolve_precision("auto", unet, "cpu")
    with pytest.raises(ValueError, match="precision must be one of"):
        prec.resolve_precision("fp16", unet, "cpu")
    with pytest.raises(ValueError, match="cannot run in bfloat16.*float32"):
        prec.resolve_precision("bfloat16", kpcn, "cpu")
    with pytest.raises(ValueError, match="cannot compute in 'bfloat16'; it can in: float32"):
        kpcn.set_compute_dtype("bfloat16")


def test_bfloat16_stays_close_to_float32_on_a_real_render(render):
    """The shipped default on a real 4-spp render: bfloat16 moves the error against the 1024-spp reference by
    under 2 % of itself, and the output against float32 by far less than the denoising error."""
    noisy = render("test:glossy", spp=4, seed=3, resolution=RES)
    ref = render("test:glossy", spp=1024, seed=4, role=1, resolution=RES)["color"]
    fp32 = inference.denoise_result(noisy, device="cpu", precision="float32")
    bf16 = inference.denoise_result(noisy, device="cpu", precision="bfloat16")
    assert fp32.stats.precision == "float32" and bf16.stats.precision == "bfloat16"
    assert np.isfinite(bf16.color).all() and bf16.color.min() >= 0
    e32, e16 = relmse(fp32.color, ref), relmse(bf16.color, ref)
    drift = relmse(bf16.color, fp32.color)
    assert abs(e16 - e32) < 0.02 * e32, (e32, e16)
    assert drift < 0.05 * e32, (drift, e32)
    assert drift > 0, "the bfloat16 call ran in float32"


def _inputs(model, layers):
    spec = model.input_spec
    tensors = frame_to_tensors(layers, spec.layers, (slice(None), slice(None)), "cpu")
    return spec.build(tensors, spec.frame_value(layers), spec.branches)


@pytest.mark.parametrize("guide_kernel", [1, 3])
def test_bfloat16_keeps_the_construction_properties(render, monkeypatch, guide_kernel):
    """A zero branch stays exactly zero, a constant colour stays constant, tiles and row bands equal the whole
    frame, and the caller's model is left computing in what it computed in before the call (a 3x3 guide runs
    in bfloat16 too)."""
    from kpcn.inference import rows

    model = _unet(guide_kernel=guide_kernel)
    frame = render("test:glossy", spp=4, seed=1, resolution=RES)
    res = inference.denoise_result(frame, model, device="cpu", precision="bfloat16")
    assert res.stats.precision == "bfloat16" and model.compute_dtype == torch.float32

    with torch.inference_mode():
        model.set_compute_dtype("bfloat16")
        inputs = _inputs(model, frame)
        inputs["diffuse"][:, :3] = 0.37  # a constant colour (in the branch's space) ...
        inputs["specular"][:, :3] = 0  # ... and a zero one, under the render's own features
        y = model(inputs)
        model.set_compute_dtype("float32")
    assert torch.count_nonzero(y["specular"]) == 0
    assert torch.allclose(y["diffuse"], torch.full_like(y["diffuse"], 0.37), rtol=1e-5), \
        float((y["diffuse"] - 0.37).abs().max())

    whole = inference.denoise(frame, model, tile=0, device="cpu", precision="bfloat16", rows=False)
    tiled = inference.denoise(frame, model, tile=16, device="cpu", precision="bfloat16")
    assert np.abs(whole - tiled).max() <= 1e-5 * max(float(np.abs(whole).max()), 1e-12)
    monkeypatch.setattr(rows, "ROWS_MIN_PIXELS", 0)
    banded = inference.denoise_result(frame, model, tile=0, device="cpu", precision="bfloat16", skip=False)
    assert banded.stats.row_bands > 0
    assert np.abs(whole - banded.color).max() <= 1e-5 * max(float(np.abs(whole).max()), 1e-12)
    fp32 = inference.denoise(frame, model, tile=0, device="cpu", precision="float32", rows=False)
    assert np.abs(whole - fp32).max() > 0, "the bfloat16 calls ran in float32"


def test_a_bfloat16_training_step_gives_float32_gradients(render):
    model = _unet()
    model.train().set_compute_dtype("bfloat16")
    frame = render("test:glossy", spp=4, seed=1, resolution=RES)
    out = model(_inputs(model, frame))
    assert out["color"].dtype == torch.float32
    out["color"].abs().mean().backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and g.dtype == torch.float32 and torch.isfinite(g).all() for g in grads)
    assert all(p.dtype == torch.float32 for p in model.parameters())
    assert model.diffuse.enc[0][0].weight.grad.abs().sum() > 0
