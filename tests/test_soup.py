"""kpcn.soup: weight-space blends of two runs of one network, on a real render."""
import hashlib
import json

import numpy as np
import pytest
import torch

from kpcn import denoise
from kpcn.checkpoint import CheckpointError, read_weights, save_weights
from kpcn.models import create_model
from kpcn.soup import blend_files, blend_state, main

CFG = dict(widths=[8, 8, 12], stem="half", kernel_scales=3, band_gain=True, albedo_kernel=3, out_init_gain=5.0)


def _net(seed, **over):
    torch.manual_seed(seed)
    return create_model("unet_kpcn", **{**CFG, **over}).eval()


@pytest.fixture
def two_runs(tmp_path):
    """Two weights files of the same small U-Net, different weights."""
    a, b = tmp_path / "a.safetensors", tmp_path / "b.safetensors"
    save_weights(a, _net(1))
    save_weights(b, _net(2))
    return a, b


def test_blend_endpoints_denoise_a_render_as_their_source(two_runs, render, tmp_path):
    a, b = two_runs
    frame = render("test:glossy", spp=4)
    out_a, out_b = denoise(frame, str(a), tile=None), denoise(frame, str(b), tile=None)
    assert np.abs(out_a - out_b).max() > 1e-3  # the two runs differ on this frame
    for alpha, want in ((1.0, out_a), (0.0, out_b)):
        path = tmp_path / f"s{alpha}.safetensors"
        assert main([str(a), str(b), "--alpha", str(alpha), "--out", str(path)]) == 0
        np.testing.assert_allclose(denoise(frame, str(path), tile=None), want, rtol=0, atol=1e-6)
    # in between: the blended file holds alpha * a + (1 - alpha) * b, tensor by tensor, and still denoises
    path = tmp_path / "s03.safetensors"
    assert main([str(a), str(b), "--alpha", "0.3", "--out", str(path)]) == 0
    (_, sa), (_, sb), (record, s) = read_weights(a), read_weights(b), read_weights(path)
    for k in sa:
        if sa[k].is_floating_point():
            torch.testing.assert_close(s[k], (0.3 * sa[k].double() + 0.7 * sb[k].double()).to(sa[k].dtype))
    mid = denoise(frame, str(path), tile=None)
    assert np.isfinite(mid).all() and np.abs(mid - out_a).max() > 1e-4 and np.abs(mid - out_b).max() > 1e-4
    # the recipe is in the file: sources, their digests and the coefficients
    src = record["soup"]["sources"]
    assert [s_["alpha"] for s_ in src] == [0.3, 0.7] and [s_["name"] for s_ in src] == [str(a), str(b)]
    assert all(len(s_["sha256"]) == 64 for s_ in src) and src[0]["sha256"] != src[1]["sha256"]


def test_different_networks_are_refused_naming_what_differs(two_runs, tmp_path):
    a, _ = two_runs
    c = tmp_path / "c.safetensors"
    save_weights(c, _net(3, widths=[8, 8, 16]))
    with pytest.raises(CheckpointError, match=r"widths.*not the same network"):
        blend_files([a, c], [0.5, 0.5])


def test_a_run_with_the_detail_stage_blends_with_one_without_and_keeps_its_stage(two_runs, tmp_path):
    """The detail stage's settings add no parameter: a file trained with the stage blends with one without, and
    the blend has the first source's stage (the same network; other fields still refuse, above)."""
    a, b = two_runs
    staged = tmp_path / "staged.safetensors"
    save_weights(staged, _net(1, detail_radius=4, detail_eps=0.02, detail_clip=0.1))
    model, _ = blend_files([staged, b], [0.5, 0.5])
    assert model.detail_regression == (4, 0.02, 0.1)
    assert blend_files([b, staged], [0.5, 0.5])[0].detail_regression is None


def test_settings_without_weights_do_not_make_another_network(two_runs, tmp_path):
    """The normal-guided blend and the exposure gain add no parameter either (``NO_WEIGHT_SETTINGS``): a file
    trained with them blends with one without, and the blend takes the first source's."""
    _, b = two_runs
    guided = tmp_path / "guided.safetensors"
    save_weights(guided, _net(1, edge_upsample=0.5, exposure_gain=1.5))
    model, _ = blend_files([guided, b], [0.5, 0.5])
    assert model.config.edge_upsample == 0.5 and model.exposure_gain == 1.5 and model.reads_normal
    other = blend_files([b, guided], [0.5, 0.5])[0]
    assert other.config.edge_upsample == 0.0 and other.exposure_gain == 1.0


def test_the_cli_never_overwrites_a_source_and_checks_the_coefficients(two_runs, capsys):
    a, b = two_runs
    before = a.read_bytes()
    assert main([str(a), str(b), "--out", str(a)]) == 2
    assert "would replace the input" in capsys.readouterr().err and a.read_bytes() == before
    for alphas, msg in ((["1.5"], "in \\[0, 1\\]"), (["0.2", "0.2", "0.6"], "need 2 coefficients")):
        assert main([str(a), str(b), "--alpha", *alphas, "--out", str(a.with_name("x.safetensors"))]) == 2
        assert msg.replace("\\", "") in capsys.readouterr().err
    assert not a.with_name("x.safetensors").exists()
    assert main([str(a), "--out", str(a.with_name("x.safetensors"))]) == 2
    assert "at least two" in capsys.readouterr().err


def test_blend_state_keeps_integer_tensors_and_refuses_differing_ones():
    s1 = {"w": torch.tensor([1.0, 2.0]), "n": torch.tensor([3])}
    s2 = {"w": torch.tensor([3.0, 6.0]), "n": torch.tensor([3])}
    out = blend_state([s1, s2], [0.25, 0.75])
    assert out["w"].tolist() == [2.5, 5.0] and out["n"].tolist() == [3] and out["n"].dtype == torch.int64
    with pytest.raises(CheckpointError, match="integer tensor 'n' differs"):
        blend_state([s1, {**s2, "n": torch.tensor([4])}], [0.5, 0.5])
    with pytest.raises(CheckpointError, match="different tensors"):
        blend_state([s1, {"w": s2["w"]}], [0.5, 0.5])


def test_shipped_blends_are_the_blends_their_metadata_records():
    """unet_kpcn:wide64h's file names its sources; the shipped one of them is unet_kpcn:wide64c. The default's
    file, wide64v's, names its four runs (not shipped: results/) at an eighth each and wide64neg (shipped) at half;
    wide64q's names two of those runs at a quarter each and wide64neg at half, as wide64n's names its two runs and
    wide64e; wide64f's names its two runs with equal parts, and wide64m its three."""
    from kpcn.inference.weights import resolve_weights

    runs = {}
    for tag, base, n in (("unet_kpcn", "unet_kpcn:wide64neg", 4), ("unet_kpcn:wide64q", "unet_kpcn:wide64neg", 2),
                         ("unet_kpcn:wide64n", "unet_kpcn:wide64e", 2)):
        record, _ = read_weights(resolve_weights(tag))
        src = record["soup"]["sources"]
        assert [s["alpha"] for s in src] == [0.5 / n] * n + [0.5] and src[n]["name"] == base
        assert len({s["sha256"] for s in src[:n]}) == n  # different runs, not one run twice
        assert src[n]["sha256"] == hashlib.sha256(resolve_weights(base).read_bytes()).hexdigest()
        runs[tag] = {s["sha256"] for s in src[:n]}
    assert runs["unet_kpcn:wide64q"] < runs["unet_kpcn"]  # the default blends wide64q's two runs and two more
    record, _ = read_weights(resolve_weights("unet_kpcn:wide64f"))
    src = record["soup"]["sources"]
    assert len(src) == 2 and all(s["alpha"] == pytest.approx(1 / 2) and len(s["sha256"]) == 64 for s in src)
    assert src[0]["sha256"] != src[1]["sha256"]
    record, _ = read_weights(resolve_weights("unet_kpcn:wide64m"))
    src = record["soup"]["sources"]
    assert len(src) == 3 and all(s["alpha"] == pytest.approx(1 / 3) and len(s["sha256"]) == 64 for s in src)
    record, _ = read_weights(resolve_weights("unet_kpcn:wide64h"))
    src = record["soup"]["sources"]
    assert [s["alpha"] for s in src] == [0.7, 0.3] and src[1]["name"] == "unet_kpcn:wide64c"
    digest = hashlib.sha256(resolve_weights("unet_kpcn:wide64c").read_bytes()).hexdigest()
    assert src[1]["sha256"] == digest
    json.dumps(record)  # plain JSON all through
