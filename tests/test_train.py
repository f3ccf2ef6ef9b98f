"""Training on a tiny rendered data set: loss goes down, resume is exact, torchrun agrees."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from kpcn.checkpoint import load_train_state, read_weights, weights_sha256
from kpcn.config import load_config
from kpcn.train import train
from kpcn.train_config import RunConfig


def tiny_cfg(root, tmp_path, name="t", **train_kw):
    cfg = load_config(RunConfig, None, [
        f"data.root={root}", "data.patch_size=24", "data.patches_per_frame=8", "data.val_scenes=1",
        "model.layers=3", "model.width=12", "model.kernel_size=5",
        "train.batch_size=4", "train.lr=3e-3", "train.val_every=1000", "train.log_every=1",
        "train.ckpt_every=3", f"name={name}",
    ])
    cfg.results_dir = str(tmp_path)
    for k, v in train_kw.items():
        setattr(cfg.train, k, v)
    return cfg


def _fixed_batch_loss(model, batch):
    from kpcn.losses import l1

    with torch.no_grad():
        out = model({k: batch[k] for k in ("diffuse", "specular", "albedo")})
        return float(l1(out["diffuse"], batch["y_diffuse"]) + l1(out["specular"], batch["y_specular"]))


def test_training_lowers_the_loss(tiny_dataset, tmp_path):
    from kpcn.data import PatchDataset
    from kpcn.train import build_model, split_pairs

    # the patches of the fixed batch are not augmented: neither are the training ones here
    cfg = tiny_cfg(tiny_dataset, tmp_path, stage1_steps=40, stage2_steps=0, augment=False)
    out = train(cfg, progress=False)
    assert np.isfinite(out["losses"]).all() and len(out["losses"]) == 40
    # the same initial weights as the run (seeded), and the trained ones, on one fixed batch of patches
    torch.manual_seed(cfg.train.seed)
    initial = build_model(cfg)
    trained = build_model(cfg)
    trained.load_state_dict(read_weights(tmp_path / "t" / "model.safetensors")[1])
    ds = PatchDataset(split_pairs(cfg)[0], 24, 8, seed=123)
    batch = torch.utils.data.default_collate([ds[i] for i in range(0, len(ds), max(1, len(ds) // 16))])
    before, after = _fixed_batch_loss(initial, batch), _fixed_batch_loss(trained, batch)
    assert after < 0.85 * before, f"loss did not go down: {before:.4f} -> {after:.4f}"
    run = tmp_path / "t"
    assert (run / "config.yaml").exists() and (run / "checkpoints" / "latest.pt").exists()
    metrics = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert set(metrics[-1]) >= {"relmse", "smape", "psnr", "ssim"}
    assert all(np.isfinite(v) for v in metrics[-1].values())
    assert any(p.name.startswith("events") for p in (run / "tb").iterdir())


def test_resume_continues_exactly(tiny_dataset, tmp_path):
    # stage boundary inside the run, checkpoints every 3 steps
    full = train(tiny_cfg(tiny_dataset, tmp_path, "full", stage1_steps=5, stage2_steps=4), progress=False)
    part_cfg = tiny_cfg(tiny_dataset, tmp_path, "part", stage1_steps=5, stage2_steps=4)
    # "kill" after 6 steps: run a shorter schedule into the same folder, then resume the full one
    short = tiny_cfg(tiny_dataset, tmp_path, "part", stage1_steps=5, stage2_steps=1)
    train(short, progress=False)
    state = load_train_state(tmp_path / "part" / "checkpoints" / "latest.pt")
    assert state["step"] == 6 and state["stage"] == 2
    resumed = train(part_cfg, resume=True, progress=False)
    assert len(resumed["losses"]) == 3
    np.testing.assert_allclose(resumed["losses"], full["losses"][6:], rtol=1e-5)
    a = read_weights(tmp_path / "full" / "model.safetensors")[1]
    b = read_weights(tmp_path / "part" / "model.safetensors")[1]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)


def test_torchrun_two_processes_end_with_identical_weights(tiny_dataset, tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    sets = [f"data.root={tiny_dataset}", "data.patch_size=24", "data.patches_per_frame=8",
            "model.layers=3", "model.width=8", "model.kernel_size=5", "train.stage1_steps=3",
            "train.stage2_steps=2", "train.batch_size=4", "train.ckpt_every=100", "train.val_every=1000",
            "train.lr=1e-3", "train.threads=1"]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone",
           "-m", "kpcn.train", "--no-progress", "--name", "ddp", "--results-dir", str(tmp_path)]
    for s in sets:
        cmd += ["--set", s]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    summary = json.loads(r.stdout[r.stdout.index("{"):])
    assert summary["world"] == 2
    hashes = summary["weight_sha256_per_rank"]
    assert len(hashes) == 2 and hashes[0] == hashes[1], hashes
    # only rank 0 wrote, and what it wrote is the trained model, not the initial one
    record, weights = read_weights(tmp_path / "ddp" / "model.safetensors")
    assert record["step"] == 5
    from kpcn.train import build_model
    torch.manual_seed(0)
    fresh = build_model(load_config(RunConfig, None, sets[3:6]))
    assert weights_sha256(fresh.state_dict()) != hashes[0]
    model = build_model(load_config(RunConfig, None, sets[3:6]))
    model.load_state_dict(weights)
    assert weights_sha256(model.state_dict()) == hashes[0]


def test_onecycle_schedule_and_augmentation_resume_exactly(tiny_dataset, tmp_path):
    """The rate is a function of the step and the transforms of (seed, step), exposures and patches mixed across
    spp included: a resumed run repeats the losses (its Adam in two groups by ``train.lr_mult``)."""
    from kpcn.schedule import lr_at

    kw = dict(stage1_steps=4, stage2_steps=3, schedule="onecycle", augment=True, loss="l1_msssim",
              exposure_augment=0.5, exposure_range=(0.03, 1.0), lr_mult={"*.bias": 5.0})

    def cfg(name, **over):
        c = tiny_cfg(tiny_dataset, tmp_path, name=name, **{**kw, **over})
        c.data.spp_mix = 0.5
        return c

    full = train(cfg("full"), progress=False)["losses"]
    first = train(cfg("cut", stage2_steps=0), progress=False)["losses"]
    rest = train(cfg("cut"), resume=True, progress=False)["losses"]
    np.testing.assert_allclose(first + rest, full, rtol=1e-5)
    # the schedule: warm-up from lr/25 to the peak, then down to far below it, within each stage
    rates = [lr_at(s, 0, 100, 1e-3, "onecycle", 0.2) for s in range(100)]
    assert rates[0] == pytest.approx(1e-3 / 25) and max(rates) == pytest.approx(1e-3, rel=1e-3)
    assert int(np.argmax(rates)) in (19, 20) and rates[-1] < 1e-6
    assert all(a <= b for a, b in zip(rates[:20], rates[1:21])) and all(a >= b for a, b in zip(rates[20:], rates[21:]))


def test_exposure_augmentation_needs_keys_and_a_split_spec(tiny_dataset, tmp_path):
    from kpcn.config import ConfigError

    with pytest.raises(ConfigError, match="exposure_range"):  # a KPCN declares no range of its own
        train(tiny_cfg(tiny_dataset, tmp_path, name="e1", stage1_steps=1, stage2_steps=0, exposure_augment=0.5),
              progress=False)
    can = tiny_cfg(tiny_dataset, tmp_path, name="e2", stage1_steps=1, stage2_steps=0, exposure_augment=0.5,
                   exposure_range=(0.03, 1.0))
    can.model["input_spec"] = "color_albedo_normal"  # one colour branch: its stored features are not rescaled
    with pytest.raises(ConfigError, match="exposure_augment: .*split input spec"):
        train(can, progress=False)
    with pytest.raises(ConfigError, match="exposure_augment"):
        load_config(RunConfig, None, ["train.exposure_augment=1.5"])
    with pytest.raises(ConfigError, match="exposure_range"):
        load_config(RunConfig, None, ["train.exposure_range=[0.5, 0.1]"])
    with pytest.raises(ConfigError, match="data.spp_mix"):
        load_config(RunConfig, None, ["data.spp_mix=2"])
    noise = tiny_cfg(tiny_dataset, tmp_path, name="e3", stage1_steps=1, stage2_steps=0)
    noise.model["input_spec"], noise.data.spp_mix = "color_albedo_normal_noise", 0.5
    with pytest.raises(ConfigError, match="data.spp_mix: .*whole-frame"):
        train(noise, progress=False)


def test_converged_inputs_add_each_training_reference_as_its_own_input(tiny_dataset, tmp_path):
    from kpcn.train_data import CONVERGED_SPP, converged_pairs, split_pairs

    cfg = tiny_cfg(tiny_dataset, tmp_path)
    plain, val = split_pairs(cfg, progress=False)
    cfg.data.converged_inputs = True
    more, val2 = split_pairs(cfg, progress=False)
    extra = [p for p in more if p.spp == CONVERGED_SPP]
    assert val == val2 and len(more) == len(plain) + len(extra)
    assert {p.scene for p in extra} == {p.scene for p in plain}
    assert all(p.input_path == p.reference_path for p in extra)
    cfg.data.converged_weight = 3  # each converged pair listed three times: three times its share of patches
    weighted, _ = split_pairs(cfg, progress=False)
    assert len(weighted) == len(plain) + 3 * len(extra)
    key = lambda p: p.scene  # noqa: E731
    assert sorted((p for p in weighted if p.spp == CONVERGED_SPP), key=key) == sorted(extra * 3, key=key)
    # with the validation frames from their own folder (data.val_root) every training scene is trained on,
    # and its converged pair is still added (they were once dropped on this path)
    cfg.data.val_root = str(tiny_dataset)
    own_val, val3 = split_pairs(cfg, progress=False)
    conv = [p for p in own_val if p.spp == CONVERGED_SPP]
    scenes = {p.scene for p in own_val if p.spp != CONVERGED_SPP}
    assert scenes == {p.scene for p in plain + val} and val3 and all(p.spp != CONVERGED_SPP for p in val3)
    assert sorted(conv, key=key) == sorted(converged_pairs([p for p in own_val if p.spp != CONVERGED_SPP]) * 3, key=key)


def test_extra_roots_add_their_scenes_and_refuse_repeated_names(tiny_dataset, tmp_path):
    from kpcn.render import DatasetError, render_dataset
    from kpcn.train_data import CONVERGED_SPP, split_pairs

    other = tmp_path / "other"
    render_dataset(other, n_scenes=2, spp_list=(4, 8), ref_spp=32, resolution=(32, 32), first_seed=500, progress=False)
    cfg = tiny_cfg(tiny_dataset, tmp_path)
    base_train, base_val = split_pairs(cfg, progress=False)
    cfg.data.extra_roots = [str(other)]
    train_pairs, val_pairs = split_pairs(cfg, progress=False)
    scenes = {p.scene for p in train_pairs + val_pairs}
    assert {p.scene for p in base_train + base_val} < scenes and len(scenes) == len({p.scene for p in base_train + base_val}) + 2
    assert any(str(p.input_path).startswith(str(other)) for p in train_pairs + val_pairs)
    # data.spp_by_root: the folder above `other` lends only its 4-spp inputs, the root keeps both; a longer
    # (nearer) folder wins over a shorter one, and a malformed entry is refused by name
    cfg.data.spp_by_root = {str(tmp_path): [4], str(tmp_path / "nowhere"): [8]}
    by_root = split_pairs(cfg, progress=False)
    from_other = [p for p in by_root[0] + by_root[1] if str(p.input_path).startswith(str(other))]
    from_root = [p for p in by_root[0] + by_root[1] if not str(p.input_path).startswith(str(other))]
    assert from_other and {p.spp for p in from_other} == {4} and {p.spp for p in from_root} == {4, 8}
    # data.balance_spp: every scene trained on (no validation scenes), the root's 3 8-spp pairs against 5 4-spp
    # ones, are listed twice (round(5 / 3))
    cfg.data.val_scenes = 0
    every = split_pairs(cfg, progress=False)[0]
    train4 = [p for p in every if p.spp == 4]
    train8 = [p for p in every if p.spp == 8]
    assert (len(train4), len(train8)) == (5, 3)
    cfg.data.balance_spp = True
    balanced = split_pairs(cfg, progress=False)[0]
    assert sorted(p.spp for p in balanced) == sorted([4] * len(train4) + [8] * 2 * len(train8))
    twice = sorted(str(p.input_path) for p in train8 for _ in range(2))
    assert sorted(str(p.input_path) for p in balanced if p.spp == 8) == twice
    cfg.data.balance_spp, cfg.data.val_scenes = False, 1
    cfg.data.spp_by_root = {str(tmp_path): [4], str(other): [8]}
    assert {p.spp for p in split_pairs(cfg, progress=False)[0] if str(p.input_path).startswith(str(other))} == {8}
    cfg.data.spp_by_root = {str(other): [16]}  # a count the data set was not rendered with
    with pytest.raises(DatasetError, match="16"):
        split_pairs(cfg, progress=False)
    from kpcn.config import ConfigError
    with pytest.raises(ConfigError, match=r"spp_by_root\['x'\]"):
        load_config(RunConfig, None, ["data.root=x", "data.spp_by_root={x: [0]}"])
    cfg.data.spp_by_root = {}
    # converged pairs only from the data sets whose references are clean enough (other's have 32 spp, root's 128)
    cfg.data.converged_inputs = True
    every = {p.scene for p in split_pairs(cfg, progress=False)[0] if p.spp == CONVERGED_SPP}
    cfg.data.converged_min_ref_spp = 64
    clean = {p.scene for p in split_pairs(cfg, progress=False)[0] if p.spp == CONVERGED_SPP}
    other_scenes = {p.scene for p in train_pairs if str(p.input_path).startswith(str(other))}
    assert other_scenes and other_scenes <= every and clean == every - other_scenes and clean
    cfg.data.converged_min_ref_spp = 4096
    with pytest.raises(DatasetError, match="converged_min_ref_spp=4096.*32 128"):
        split_pairs(cfg, progress=False)
    cfg.data.converged_inputs, cfg.data.converged_min_ref_spp = False, 0
    cfg.data.extra_roots = [str(tiny_dataset)]
    with pytest.raises(DatasetError, match="repeats scene names"):
        split_pairs(cfg, progress=False)


def test_init_starts_from_given_weights_and_refuses_other_models(tiny_dataset, tmp_path):
    from kpcn.config import ConfigError

    first = train(tiny_cfg(tiny_dataset, tmp_path, name="a", stage1_steps=3, stage2_steps=0), progress=False)
    assert first["losses"]
    src = tmp_path / "a" / "model.safetensors"
    trained = read_weights(src)[1]
    # one step at a negligible rate: the fine-tuned weights are the file's, not a fresh initialisation
    cfg = tiny_cfg(tiny_dataset, tmp_path, name="b", stage1_steps=1, stage2_steps=0, lr=1e-12, init=str(src))
    train(cfg, progress=False)
    tuned = read_weights(tmp_path / "b" / "model.safetensors")[1]
    fresh_cfg = tiny_cfg(tiny_dataset, tmp_path, name="c", stage1_steps=1, stage2_steps=0, lr=1e-12, seed=5)
    train(fresh_cfg, progress=False)
    fresh = read_weights(tmp_path / "c" / "model.safetensors")[1]
    assert all(torch.allclose(tuned[k], trained[k], atol=1e-6) for k in trained)
    assert not all(torch.allclose(fresh[k], trained[k], atol=1e-3) for k in trained)
    # other hyper-parameters, another model, a missing file: ConfigError naming what differs
    wide = tiny_cfg(tiny_dataset, tmp_path, name="d", stage1_steps=1, init=str(src))
    wide.model["width"] = 16
    with pytest.raises(ConfigError, match="width"):
        train(wide, progress=False)
    with pytest.raises(ConfigError, match="unet_kpcn"):
        train(tiny_cfg(tiny_dataset, tmp_path, name="e", stage1_steps=1, init="unet_kpcn:fast"), progress=False)
    with pytest.raises(ConfigError, match="no weights file"):
        train(tiny_cfg(tiny_dataset, tmp_path, name="f", stage1_steps=1, init=str(tmp_path / "nope.safetensors")),
              progress=False)
    assert not any((tmp_path / n).exists() for n in "def")  # refused before anything was written


def test_init_extend_starts_from_the_narrower_models_outputs(tiny_dataset, tmp_path, render):
    """A model that reads one more input channel (the noise precision) starts as the colour + albedo + normal model
    it is fine-tuned from: same denoised frame, bit for bit up to float rounding."""
    from kpcn.config import ConfigError
    from kpcn.inference import denoise, load_model

    can = dict(input_spec="color_albedo_normal")
    first = tiny_cfg(tiny_dataset, tmp_path, name="a", stage1_steps=3, stage2_steps=0)
    first.model.update(can)
    train(first, progress=False)
    src = tmp_path / "a" / "model.safetensors"
    wide = tiny_cfg(tiny_dataset, tmp_path, name="b", stage1_steps=1, stage2_steps=0, lr=1e-12, init=str(src))
    wide.model.update(input_spec="color_albedo_normal_noise")
    with pytest.raises(ConfigError, match="input_spec"):  # not without saying so
        train(wide, progress=False)
    wide.train.init_extend = True
    train(wide, progress=False)
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    narrow, widened = load_model(str(src), device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    assert widened.input_spec.name == "color_albedo_normal_noise"
    a, b = denoise(frame, narrow, device="cpu"), denoise(frame, widened, device="cpu")
    assert np.abs(a - b).max() <= 1e-5 * np.abs(a).max()
    # with the precision gate added too: within the gate's initial 0.25 % of the narrow model, and the gate opens
    # on its own as the precision rises only once trained (here it is a constant)
    gated = tiny_cfg(tiny_dataset, tmp_path, name="g", stage1_steps=1, stage2_steps=0, lr=1e-12, init=str(src),
                     init_extend=True)
    gated.model.update(input_spec="color_albedo_normal_noise", precision_gate=True)
    train(gated, progress=False)
    g = denoise(frame, load_model(str(tmp_path / "g" / "model.safetensors"), device="cpu"), device="cpu")
    assert 0 < np.abs(a - g).max() <= 0.0025 * np.abs(a - frame["color"]).max() + 1e-6
    # with the demodulation weight added: the same softmax logits as the widened model, and the weight's logit at
    # its initial bias everywhere (zero weights)
    from kpcn.features import frame_to_tensors
    from kpcn.models.kpcn import DEMOD_INIT

    dm_cfg = tiny_cfg(tiny_dataset, tmp_path, name="m", stage1_steps=1, stage2_steps=0, lr=1e-12, init=str(src),
                      init_extend=True)
    dm_cfg.model.update(input_spec="color_albedo_normal_noise", demodulate=True)
    train(dm_cfg, progress=False)
    dm = load_model(str(tmp_path / "m" / "model.safetensors"), device="cpu")
    spec = widened.input_spec
    x = spec.build(frame_to_tensors(spec.select(frame), spec.layers))["color"]
    with torch.no_grad():
        zw, zd = widened.color.logits(x), dm.color.logits(x)
    kk = zw.shape[1]
    assert zd.shape[1] == kk + 1
    torch.testing.assert_close(zd[:, :kk], zw, rtol=0, atol=1e-4)
    s = dm.config.logit_scale
    torch.testing.assert_close(zd[:, kk:], torch.full_like(zd[:, kk:], s * np.tanh(DEMOD_INIT / s)), rtol=0, atol=1e-4)
    # a model of another depth cannot be widened into this one
    deep = tiny_cfg(tiny_dataset, tmp_path, name="c", stage1_steps=1, init=str(src), init_extend=True)
    deep.model.update(input_spec="color_albedo_normal_noise", layers=4)
    with pytest.raises(ConfigError, match="layers"):
        train(deep, progress=False)


def test_init_extend_adds_a_coarser_kernel_level(tiny_dataset, tmp_path, render):
    """A U-Net given one more (coarser) kernel level keeps every kernel of the file's levels; the level that
    gains a coarser neighbour blends it in with its initial weight (zero weights, the model's bias: α = ½),
    and the new level's head is the model's own initialisation. Cutting a level is refused."""
    from kpcn.config import ConfigError
    from kpcn.features import frame_to_tensors
    from kpcn.inference import load_model

    unet = dict(name="unet_kpcn", widths=[8, 12, 16], convs_per_level=1, kernel_size=3, stem="half",
                guide_channels=4, summary_channels=4)

    def ucfg(name, scales, **kw):
        cfg = tiny_cfg(tiny_dataset, tmp_path, name=name, **{"stage1_steps": 3, "stage2_steps": 0, **kw})
        cfg.model = dict(unet, kernel_scales=scales)
        return cfg

    train(ucfg("a", 2), progress=False)
    src = tmp_path / "a" / "model.safetensors"
    with pytest.raises(ConfigError, match="kernel_scales"):  # not without saying so
        train(ucfg("b", 3, init=str(src)), progress=False)
    train(ucfg("b", 3, init=str(src), init_extend=True, lr=1e-12, stage1_steps=1), progress=False)
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    two, three = load_model(str(src), device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    spec = two.input_spec
    x = spec.build(frame_to_tensors(spec.select(frame), spec.layers))["diffuse"]
    with torch.no_grad():
        ks2, ks3 = two.diffuse.kernels(x), three.diffuse.kernels(x)
    assert len(ks3.kernels) == 3 and ks3.alphas[2] is None
    for level in (0, 1):
        torch.testing.assert_close(ks3.kernels[level], ks2.kernels[level], rtol=0, atol=1e-6)
    torch.testing.assert_close(ks3.alphas[0], ks2.alphas[0], rtol=0, atol=1e-6)
    assert ks2.alphas[1] is None
    torch.testing.assert_close(ks3.alphas[1], torch.full_like(ks3.alphas[1], 0.5), rtol=0, atol=1e-6)
    with pytest.raises(ConfigError, match="heads.0.weight.*lacks"):  # a model can be extended, not cut
        train(ucfg("c", 1, init=str(src), init_extend=True), progress=False)
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("up_kernel", [3, 1])
def test_init_extend_widens_a_unet(tiny_dataset, tmp_path, render, up_kernel):
    """A U-Net with wider levels, started from a narrower file, denoises a real render as the file does
    (each channel group keeps its place: a decoder conv reads [upsampled, skip], or with ``up_kernel: 1`` the skip
    and, through its 1x1 child, the coarse level; the summary [mean, std]); its new channels are live (the loss has a
    gradient on the zero weights that read them). Narrowing is refused before anything is written."""
    import kpcn
    from kpcn.config import ConfigError
    from kpcn.inference import load_model

    unet = dict(name="unet_kpcn", convs_per_level=1, kernel_size=3, stem="half", guide_channels=4,
                summary_channels=4, kernel_scales=2, up_kernel=up_kernel)

    def ucfg(name, widths, **kw):
        cfg = tiny_cfg(tiny_dataset, tmp_path, name=name, **{"stage1_steps": 3, "stage2_steps": 0, **kw})
        cfg.model = dict(unet, widths=widths)
        return cfg

    train(ucfg("a", [8, 12, 16]), progress=False)
    src = tmp_path / "a" / "model.safetensors"
    with pytest.raises(ConfigError, match="widths"):  # not without saying so
        train(ucfg("b", [8, 20, 24], init=str(src)), progress=False)
    train(ucfg("b", [8, 20, 24], init=str(src), init_extend=True, lr=1e-12, stage1_steps=1), progress=False)
    narrow, wide = load_model(str(src), device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    assert wide.diffuse.enc[2][0].weight.shape == (24, 20, 3, 3)
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    a, b = kpcn.denoise(frame, narrow, device="cpu"), kpcn.denoise(frame, wide, device="cpu")
    assert np.abs(a - b).max() <= 1e-5 * max(1.0, float(np.abs(a).max()))
    # the file's level-1 decoder conv reads the new bottleneck channels 16..23 through zero weights (moved
    # only by the one step at lr 1e-12), and they learn
    w = wide.diffuse.dec[0][0].weight if up_kernel == 3 else wide.diffuse.dec[0][0].coarse.weight
    assert w[:12, 16:24].abs().max() <= 1e-9
    spec = wide.input_spec
    from kpcn.features import frame_to_tensors
    x = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    w.requires_grad_(True)
    wide.diffuse(x["diffuse"]).square().mean().backward()
    assert w.grad[:12, 16:24].abs().max() > 0
    with pytest.raises(ConfigError, match="can only grow"):
        train(ucfg("c", [8, 12, 12], init=str(src), init_extend=True), progress=False)
    assert not (tmp_path / "c").exists()


def test_init_prune_narrows_the_unet_specular_branch(tiny_dataset, tmp_path, render):
    """``specular_widths`` below a file's widths, with ``train.init_prune``: each of the specular branch's channel
    groups keeps the file's first channels (a decoder conv's [coarse, skip] and the summary's [mean, std] each
    cut group by group), the diffuse branch is the file's and denoises a real render's diffuse as the file does.
    Without ``init_prune`` (or without ``init_extend``) the narrowing is refused before anything is written."""
    from kpcn.config import ConfigError
    from kpcn.features import frame_to_tensors
    from kpcn.inference import load_model

    def ucfg(name, sw=None, **kw):
        return _tiny_unet_cfg(tiny_dataset, tmp_path, name, dict(up_kernel=1, specular_widths=sw), **kw)

    train(ucfg("a"), progress=False)
    src = tmp_path / "a" / "model.safetensors"
    with pytest.raises(ConfigError, match="can only grow without train.init_prune"):
        train(ucfg("b", [6, 8, 12], init=str(src), init_extend=True), progress=False)
    with pytest.raises(ConfigError, match="init_prune: needs train.init_extend"):
        train(ucfg("b", [6, 8, 12], init=str(src), init_prune=True), progress=False)
    assert not (tmp_path / "b").exists()
    train(ucfg("b", [6, 8, 12], init=str(src), init_extend=True, init_prune=True, lr=1e-12, stage1_steps=1),
          progress=False)
    full, cut = load_model(str(src), device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    f, c = full.specular.state_dict(), cut.specular.state_dict()
    close = dict(rtol=0, atol=1e-9)
    torch.testing.assert_close(c["enc.1.0.weight"], f["enc.1.0.weight"][:8, :6], **close)
    torch.testing.assert_close(c["summary.weight"], f["summary.weight"][:, [*range(12), *range(16, 28)]], **close)
    # dec.0 (level 1) reads the bottleneck [12 of 16, 4 summary channels] through its 1x1 child, the skip (8 of 12)
    torch.testing.assert_close(c["dec.0.0.coarse.weight"], f["dec.0.0.coarse.weight"][:8, [*range(12), *range(16, 20)]],
                               **close)
    torch.testing.assert_close(c["dec.0.0.weight"], f["dec.0.0.weight"][:8, :8], **close)
    torch.testing.assert_close(c["head.weight"], f["head.weight"][:, [*range(6), *range(8, 12)]], **close)
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    spec = full.input_spec
    x = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    with torch.no_grad():
        torch.testing.assert_close(cut.diffuse(x["diffuse"]), full.diffuse(x["diffuse"]), rtol=0, atol=1e-5)
        assert cut.specular(x["specular"]).shape == full.specular(x["specular"]).shape


def _tiny_unet_cfg(tiny_dataset, tmp_path, name, model_kw, **train_kw):
    """A 3-step run of a tiny ``stem: half`` U-Net with three kernel levels, its model options ``model_kw``."""
    cfg = tiny_cfg(tiny_dataset, tmp_path, name=name, **{"stage1_steps": 3, "stage2_steps": 0, **train_kw})
    cfg.model = dict(name="unet_kpcn", widths=[8, 12, 16], convs_per_level=1, kernel_size=3, stem="half",
                     guide_channels=4, summary_channels=4, kernel_scales=3)
    cfg.model.update(model_kw)
    return cfg


def _denoises_alike(file_model, extended, render):
    """Assert that a model extended from a file denoises a real render as the file's model does (float32), and return
    the diffuse branch's features of that render ``(1, C, H, W)`` for probing the extension."""
    import kpcn
    from kpcn.features import frame_to_tensors

    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    a = kpcn.denoise(frame, file_model, device="cpu", precision="float32")
    b = kpcn.denoise(frame, extended, device="cpu", precision="float32")
    assert np.abs(a - b).max() <= 1e-5 * max(1.0, float(np.abs(a).max()))
    spec = extended.input_spec
    return spec.build(frame_to_tensors(spec.select(frame), spec.layers))["diffuse"]


def test_init_extend_adds_unet_band_gains(tiny_dataset, tmp_path, render):
    """``band_gain`` added to a trained U-Net with ``train.init_extend``: the new gain channels start at
    β = 1 exactly, so the model denoises a real render as the file does; the gains are live (the loss has a
    gradient on their zero weights), and a gain that is not 1 changes the output."""
    from kpcn.config import ConfigError
    from kpcn.inference import load_model

    def ucfg(name, band_gain, **kw):
        return _tiny_unet_cfg(tiny_dataset, tmp_path, name, dict(band_gain=band_gain), **kw)

    train(ucfg("a", False), progress=False)
    src = tmp_path / "a" / "model.safetensors"
    # a file written before the field existed (its record lacks band_gain) holds its default: a config that
    # states the default starts from it
    import json
    from safetensors import safe_open
    from safetensors.torch import save_file
    with safe_open(str(src), "pt") as fh:
        record, state = json.loads(fh.metadata()["kpcn"]), {k: fh.get_tensor(k) for k in fh.keys()}
    del record["hparams"]["band_gain"]
    older = tmp_path / "older.safetensors"
    save_file(state, str(older), metadata={"kpcn": json.dumps(record)})
    train(ucfg("a2", False, init=str(older)), progress=False)
    with pytest.raises(ConfigError, match="band_gain"):  # not without saying so
        train(ucfg("b", True, init=str(src)), progress=False)
    train(ucfg("b", True, init=str(src), init_extend=True, lr=1e-12, stage1_steps=1), progress=False)
    plain, gained = load_model(str(src), device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    head = gained.diffuse.head
    assert head.out_channels == 3 * 3 + 2 and gained.diffuse.heads[0].out_channels == 3 * 3 + 2
    x = _denoises_alike(plain, gained, render)
    with torch.no_grad():
        ks = gained.diffuse.kernels(x)
    assert ks.gains is not None and ks.gains[2] is None
    torch.testing.assert_close(ks.gains[0], torch.ones_like(ks.gains[0]), rtol=0, atol=1e-6)
    head.weight.requires_grad_(True)
    gained.diffuse(x).square().mean().backward()
    assert head.weight.grad[-1].abs().max() > 0  # the gain's row
    with torch.no_grad():
        head.bias[-1] = -3.0  # β = 2 sigmoid(-3) ≈ 0.095: level 0's high band mostly removed
        c = gained.diffuse(x)
        d = plain.diffuse(x)
    assert (c - d).abs().max() > 1e-3


@pytest.mark.parametrize("others", [dict(albedo_kernel=3), dict(radiance_mix=True), dict(albedo_kernel=3,
                                                                                     radiance_mix=True)])
def test_init_extend_adds_band_gains_before_a_heads_later_rows(tiny_dataset, tmp_path, render, others):
    """The gains sit between a head's blend and its albedo kernel or mixing weight: added to a file that has those,
    they go in their place (not at the head's end), so the model still denoises as the file does."""
    from kpcn.inference import load_model

    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "f", dict(band_gain=False, **others)), progress=False)
    src = tmp_path / "f" / "model.safetensors"
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "g", dict(band_gain=True, **others), init=str(src),
                         init_extend=True, lr=1e-12, stage1_steps=1), progress=False)
    plain, gained = load_model(str(src), device="cpu"), load_model(str(tmp_path / "g" / "model.safetensors"),
                                                                    device="cpu")
    assert gained.diffuse.head.out_channels == plain.diffuse.head.out_channels + 1
    x = _denoises_alike(plain, gained, render)
    with torch.no_grad():
        ks = gained.diffuse.kernels(x)
    torch.testing.assert_close(ks.gains[0], torch.ones_like(ks.gains[0]), rtol=0, atol=1e-6)


def test_init_extend_adds_unet_deep_blocks(tiny_dataset, tmp_path, render):
    """``deep_blocks`` added to a trained U-Net with ``train.init_extend``: the model denoises a real render as the
    file does (each block's second conv starts at zero); the blocks are live (the loss has a gradient on that
    zero conv), a block that is not the identity changes the output, ``train_only`` can train them alone, and
    ``train.lr_mult`` at their own rate."""
    from kpcn.config import ConfigError
    from kpcn.inference import load_model

    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "a", {}), progress=False)
    src = str(tmp_path / "a" / "model.safetensors")
    with pytest.raises(ConfigError, match="deep_blocks"):  # not without saying so
        train(_tiny_unet_cfg(tiny_dataset, tmp_path, "b", dict(deep_blocks=2), init=src), progress=False)
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "b", dict(deep_blocks=2), init=src, init_extend=True, lr=1e-12,
                         stage1_steps=1), progress=False)
    plain, deep = load_model(src, device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    assert len(deep.diffuse.deep) == 2 and len(deep.specular.deep) == 2 and not hasattr(plain.diffuse.deep, "0")
    x = _denoises_alike(plain, deep, render)
    conv2 = deep.diffuse.deep[1].conv2
    conv2.weight.requires_grad_(True)
    deep.diffuse(x).square().mean().backward()
    assert conv2.weight.grad.abs().max() > 0
    with torch.no_grad():
        conv2.weight.normal_(0.0, 0.1)
        assert (deep.diffuse(x) - plain.diffuse(x)).abs().max() > 1e-4
    # the blocks trained alone: they move, nothing else does
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "c", dict(deep_blocks=1), init=src, init_extend=True, lr=1e-2,
                         train_only=["*.deep.*"]), progress=False)
    trained = load_model(str(tmp_path / "c" / "model.safetensors"), device="cpu").state_dict()
    before = plain.state_dict()
    assert all(torch.equal(trained[k], v) for k, v in before.items())
    assert float(trained["diffuse.deep.0.conv2.weight"].abs().max()) > 0
    # train.lr_mult instead: the blocks at 1e10 times a rate of 1e-12 that leaves everything else where it was
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "d", dict(deep_blocks=1), init=src, init_extend=True, lr=1e-12,
                         lr_mult={"*.deep.*": 1e10}), progress=False)
    trained = load_model(str(tmp_path / "d" / "model.safetensors"), device="cpu").state_dict()
    assert all(float((trained[k] - v).abs().max()) < 1e-9 for k, v in before.items())
    assert float(trained["diffuse.deep.0.conv2.weight"].abs().max()) > 1e-4
    with pytest.raises(ConfigError, match="lr_mult: '\\*.nothing.\\*' name no parameter of the model that is trained"):
        train(_tiny_unet_cfg(tiny_dataset, tmp_path, "e", {}, init=src, lr_mult={"*.nothing.*": 2.0}), progress=False)


def test_lr_mult_keeps_each_groups_factor_through_the_schedule():
    """``train.lr_mult``: every trained parameter in exactly one Adam group, those the first matching glob names at
    the schedule's rate times its factor at every step (warm-up, peak, decay); a frozen parameter in none; a bad
    factor is refused when the config is read."""
    from kpcn.config import ConfigError
    from kpcn.models import create_model
    from kpcn.train_steps import _make_optimizer, set_lr

    model = create_model("unet_kpcn", stem="half", kernel_scales=2, widths=[8, 12], summary_channels=4)
    model.specular.enc[0][0].weight.requires_grad_(False)
    cfg = load_config(RunConfig, None, ["train.stage1_steps=0", "train.stage2_steps=100", "train.schedule=onecycle",
                                        "train.lr=1e-3"])
    cfg.train.lr_mult = {"*.head.*": 10, "diffuse.*": 3}  # the first glob wins for diffuse.head
    opt = _make_optimizer(model, cfg.train.lr, cfg.train.lr_mult)
    factor = {id(p): g["lr_mult"] for g in opt.param_groups for p in g["params"]}
    trained = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    assert sum(len(g["params"]) for g in opt.param_groups) == len(trained) == len(factor)
    for n, p in trained:
        assert factor[id(p)] == (10 if ".head." in n else 3 if n.startswith("diffuse.") else 1), n
    for step in (0, 3, 50, 99):
        lr = set_lr(opt, step, cfg)
        assert lr > 0 and all(g["lr"] == pytest.approx(lr * g["lr_mult"]) for g in opt.param_groups)
    for bad in ('{"*.head.*": 0}', '{"*.head.*": .nan}', '{"": 2}', '{"*.head.*": true}'):
        with pytest.raises(ConfigError, match="train.lr_mult"):
            load_config(RunConfig, None, [f"train.lr_mult={bad}"])


def test_init_resizes_unet_kernels_from_their_centre_taps(tiny_dataset, tmp_path, render):
    """``train.init_prune`` into a U-Net with smaller full-resolution kernels (``kernel_size`` 5 -> 3, the coarser
    levels kept at 5 by ``coarse_kernel``): on a real render its level-0 kernels are the file's centre 3x3 taps,
    renormalised; the coarser levels' kernels and every blending weight are the file's. Larger kernels (7x7, and a
    5x5 albedo kernel, ``init_extend`` alone) are the file's over its taps (renormalised), and their new outer taps
    start with some weight and a gradient."""
    from kpcn.config import ConfigError
    from kpcn.features import frame_to_tensors
    from kpcn.inference import load_model

    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "a", dict(kernel_size=5, band_gain=True, albedo_kernel=3)),
          progress=False)
    src = str(tmp_path / "a" / "model.safetensors")
    kw = dict(init=src, init_extend=True, lr=1e-12, stage1_steps=1)
    small = dict(kernel_size=3, coarse_kernel=5, band_gain=True, albedo_kernel=3)
    with pytest.raises(ConfigError, match="cropping them needs train.init_prune"):
        train(_tiny_unet_cfg(tiny_dataset, tmp_path, "b", small, **kw), progress=False)
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "b", small, init_prune=True, **kw), progress=False)
    old, new = load_model(src, device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    spec = new.input_spec
    x = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    for b in ("diffuse", "specular"):
        with torch.no_grad():
            ko, kn = getattr(old, b).kernels(x[b]), getattr(new, b).kernels(x[b])
        centre = ko.kernels[0].unflatten(1, (5, 5))[:, 1:4, 1:4].flatten(1, 2)
        torch.testing.assert_close(kn.kernels[0], centre / centre.sum(1, keepdim=True), rtol=1e-4, atol=1e-6)
        assert float((ko.kernels[0].sum(1) - centre.sum(1)).abs().max()) > 1e-3  # the file's 5x5 reached further
        for a, c in zip(kn.kernels[1:], ko.kernels[1:]):
            torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-6)
        for a, c in zip(kn.alphas + kn.gains, ko.alphas + ko.gains):
            if a is not None:
                torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-6)
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "c", dict(kernel_size=7, band_gain=True, albedo_kernel=5), **kw),
          progress=False)
    grown = load_model(str(tmp_path / "c" / "model.safetensors"), device="cpu")
    assert grown.diffuse.head.out_channels == 49 + 2 + 26 and grown.diffuse.heads[0].out_channels == 49 + 2
    x = x["diffuse"]
    with torch.no_grad():
        kg, ko = grown.diffuse.kernels(x), old.diffuse.kernels(x)
    for k, (new_k, old_k) in {7: (kg.kernels[0], ko.kernels[0]), 5: (kg.albedo[0], ko.albedo[0])}.items():
        taps = new_k.unflatten(1, (k, k))
        inner = taps[:, 1:-1, 1:-1].flatten(1, 2)
        # over the file's taps the grown kernels are the file's, renormalised
        torch.testing.assert_close(inner / inner.sum(1, keepdim=True), old_k, rtol=1e-4, atol=1e-6)
        ring = 1.0 - inner.sum(1)  # the new taps' weight: some, less than the file's taps carry
        assert 1e-3 < float(ring.mean()) < 0.5
    head = grown.diffuse.head
    head.weight.requires_grad_(True)
    grown.diffuse(x).square().mean().backward()
    outer = torch.ones(7, 7, dtype=torch.bool)
    outer[1:-1, 1:-1] = False
    assert float(head.weight.grad[outer.flatten().nonzero()[:, 0]].abs().max()) > 0


def test_init_reopen_restarts_a_blending_weight(tiny_dataset, tmp_path, render):
    """``train.init_reopen: ["specular:1"]``: on a real render, the specular branch's level-1 blending weight is
    sigmoid(-1) at every pixel after init (the file's varies), and everything else is the file's: the diffuse
    branch's output, the specular kernels and level-0 weight; the gate has a gradient; bad entries are refused."""
    from kpcn.config import ConfigError
    from kpcn.features import frame_to_tensors
    from kpcn.inference import load_model

    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "a", dict(band_gain=True)), progress=False)
    src = str(tmp_path / "a" / "model.safetensors")
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "b", dict(band_gain=True), init=src, init_reopen=["specular:1"],
                         lr=1e-12, stage1_steps=1), progress=False)
    old, new = load_model(src, device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    spec = new.input_spec
    x = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    with torch.no_grad():
        ko, kn = old.specular.kernels(x["specular"]), new.specular.kernels(x["specular"])
        torch.testing.assert_close(new.diffuse(x["diffuse"]), old.diffuse(x["diffuse"]), rtol=1e-5, atol=1e-6)
    expect = torch.sigmoid(torch.tensor(-1.0))
    torch.testing.assert_close(kn.alphas[1], torch.full_like(kn.alphas[1], float(expect)), rtol=0, atol=1e-6)
    assert float(ko.alphas[1].std()) > 1e-4  # the file's weight varies over the frame
    torch.testing.assert_close(kn.alphas[0], ko.alphas[0], rtol=1e-5, atol=1e-6)
    for a, b in zip(kn.kernels, ko.kernels):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    head = new.specular.heads[0]
    head.weight.requires_grad_(True)
    new.specular(x["specular"]).square().mean().backward()
    assert head.weight.grad[3 * 3].abs().max() > 0  # the reopened gate's row learns
    for bad, match in ((["specular:2"], "blends in no coarser level"), (["glossy:1"], "no U-Net branch"),
                       (["specular-1"], "entries are")):
        with pytest.raises(ConfigError, match=match):
            train(_tiny_unet_cfg(tiny_dataset, tmp_path, "c", dict(band_gain=True), init=src, init_reopen=bad),
                  progress=False)


def test_train_only_trains_the_radiance_mix_heads_alone(tiny_dataset, tmp_path, render):
    """``radiance_mix`` added with ``train.init_extend`` and trained with ``train.train_only`` on the specular heads:
    every other parameter is the file's bit for bit, the heads moved (the mixing rows from their zero start), each
    mixing weight starts at sigmoid(RADIANCE_MIX_INIT) on a real render; a pattern naming no parameter is refused."""
    from kpcn.config import ConfigError
    from kpcn.features import frame_to_tensors
    from kpcn.inference import load_model
    from kpcn.models.unet_config import RADIANCE_MIX_INIT

    kw = dict(band_gain=True, radiance_pool=True)
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "a", kw), progress=False)
    src = str(tmp_path / "a" / "model.safetensors")
    heads = ["specular.head.*", "specular.heads.*"]
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "b", dict(kw, radiance_mix=True), init=src, init_extend=True,
                         lr=1e-12, stage1_steps=1), progress=False)
    start = load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    spec = start.input_spec
    x = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    with torch.no_grad():
        ks = start.specular.kernels(x["specular"])
    for m in ks.mixes:
        torch.testing.assert_close(m, torch.full_like(m, float(torch.sigmoid(torch.tensor(RADIANCE_MIX_INIT)))),
                                   rtol=0, atol=1e-6)
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "c", dict(kw, radiance_mix=True), init=src, init_extend=True,
                         lr=1e-2, stage1_steps=3, train_only=heads), progress=False)
    old = load_model(src, device="cpu").state_dict()
    new = load_model(str(tmp_path / "c" / "model.safetensors"), device="cpu").state_dict()
    moved = []
    for k, v in new.items():
        if k.startswith(("specular.head.", "specular.heads.")):
            moved.append(not torch.equal(v[: old[k].shape[0]], old[k]))
            if k.endswith("weight"):
                assert v[-1].abs().max() > 0, f"{k}: the mixing row did not learn"
        else:
            assert torch.equal(v, old[k]), f"{k} was trained though train_only leaves it out"
    assert moved and all(moved)
    # "<glob>[-1]": only the last row (the mixing logit) of each specular head learns, the kernels stay the file's
    train(_tiny_unet_cfg(tiny_dataset, tmp_path, "e", dict(kw, radiance_mix=True), init=src, init_extend=True,
                         lr=1e-2, stage1_steps=3, train_only=["specular.head.*[-1]", "specular.heads.*[-1]"]),
          progress=False)
    rows = load_model(str(tmp_path / "e" / "model.safetensors"), device="cpu").state_dict()
    first = start.state_dict()  # the mixing rows as init_extend starts them
    for k, v in rows.items():
        if k.startswith(("specular.head.", "specular.heads.")):
            assert torch.equal(v[:-1], old[k]) and not torch.equal(v[-1], first[k][-1]), k
        else:
            assert torch.equal(v, old[k]), k
    with pytest.raises(ConfigError, match="name no parameter"):
        train(_tiny_unet_cfg(tiny_dataset, tmp_path, "d", kw, train_only=["specular.nothing*"]), progress=False)


def test_init_extend_adds_unet_albedo_kernels(tiny_dataset, tmp_path, render):
    """``albedo_kernel`` added to a trained U-Net with ``train.init_extend``: the diffuse head's new rows start with
    the gate at 0 exactly, so the model denoises a real render as the file does and remodulates with the input's
    albedo; the gate is live (the colour loss has a gradient on its zero weights); an open gate changes the colour,
    and it leaves a constant albedo constant (each albedo kernel sums to one)."""
    import kpcn
    from kpcn.config import ConfigError
    from kpcn.features import frame_to_tensors
    from kpcn.inference import load_model

    def ucfg(name, ka, **kw):
        return _tiny_unet_cfg(tiny_dataset, tmp_path, name, dict(band_gain=True, albedo_kernel=ka), **kw)

    train(ucfg("a", 0), progress=False)
    src = tmp_path / "a" / "model.safetensors"
    train(ucfg("b", 3, init=str(src), init_extend=True, lr=1e-12, stage1_steps=0, stage2_steps=1), progress=False)
    plain, filt = load_model(str(src), device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    head = filt.diffuse.head
    assert head.out_channels == 3 * 3 + 2 + 3 * 3 + 1 and filt.specular.head.out_channels == 3 * 3 + 2
    frame = render("test:textured", spp=4, seed=1, resolution=(40, 40))
    a = kpcn.denoise(frame, plain, device="cpu", precision="float32")
    b = kpcn.denoise(frame, filt, device="cpu", precision="float32")
    assert np.abs(a - b).max() <= 1e-5 * max(1.0, float(np.abs(a).max()))
    spec = filt.input_spec
    inputs = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    with torch.no_grad():
        ks = filt.diffuse.kernels(inputs["diffuse"])
        assert ks.albedo is not None and ks.albedo[1].abs().max() <= 1e-6  # g = tanh(0)
        assert torch.equal(filt(inputs)["albedo"], inputs["albedo"].clamp_min(0))
    head.weight.requires_grad_(True)
    filt(inputs)["color"].square().mean().backward()
    assert head.weight.grad[-1].abs().max() > 0  # the gate's row
    with torch.no_grad():
        head.bias[-1] = 2.0  # g = tanh(2) ≈ 0.96: the albedo mostly filtered
        out = filt(inputs)
        assert (out["albedo"] - inputs["albedo"]).abs().max() > 1e-2  # test:textured's albedo is not smooth
        assert (out["color"] - plain(inputs)["color"]).abs().max() > 1e-3
        flat = dict(inputs, albedo=torch.full_like(inputs["albedo"], 0.37))
        torch.testing.assert_close(filt(flat)["albedo"], flat["albedo"], rtol=0, atol=1e-6)
    # the file's trained gates read through another gain would be other gates: refused
    cfg = ucfg("c", 3, init=str(tmp_path / "b" / "model.safetensors"), init_extend=True, stage1_steps=0, stage2_steps=1)
    cfg.model["albedo_gate_gain"] = 8.0
    with pytest.raises(ConfigError, match="albedo_gate_gain"):
        train(cfg, progress=False)
    assert not (tmp_path / "c").exists()


def test_init_extend_turns_unet_up_convs_into_1x1(tiny_dataset, tmp_path, render):
    """``up_kernel: 1`` from a trained ``up_kernel: 3`` U-Net with ``train.init_extend``: each decoder level's first
    conv keeps the skip's taps and gets the coarse taps summed into its 1x1; where the file's coarse taps are all at
    the centre that is the same function, so the model denoises a real render as the file does."""
    import json

    import kpcn
    from kpcn.config import ConfigError
    from kpcn.inference import load_model
    from safetensors import safe_open
    from safetensors.torch import save_file

    def ucfg(name, up_kernel, **kw):
        return _tiny_unet_cfg(tiny_dataset, tmp_path, name, dict(up_kernel=up_kernel), **kw)

    train(ucfg("a", 3), progress=False)
    with safe_open(str(tmp_path / "a" / "model.safetensors"), "pt") as fh:
        record, state = json.loads(fh.metadata()["kpcn"]), {k: fh.get_tensor(k) for k in fh.keys()}
    coarse_in = {"dec.0.0": 16 + 4, "dec.1.0": 12}  # the summary's channels join the bottleneck's
    centred = dict(state)
    for b in ("diffuse", "specular"):
        for m, cc in coarse_in.items():
            w = state[f"{b}.{m}.weight"].clone()
            w[:, :cc] = 0
            w[:, :cc, 1, 1] = state[f"{b}.{m}.weight"][:, :cc].sum(dim=(2, 3))  # the sum, all at the centre
            centred[f"{b}.{m}.weight"] = w
    src = tmp_path / "centred.safetensors"
    save_file(centred, str(src), metadata={"kpcn": json.dumps(record)})
    with pytest.raises(ConfigError, match="up_kernel"):  # not without saying so
        train(ucfg("b", 1, init=str(src)), progress=False)
    train(ucfg("b", 1, init=str(src), init_extend=True, lr=1e-12, stage1_steps=1), progress=False)
    file_model, up1 = load_model(str(src), device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    for m, cc in coarse_in.items():
        conv = up1.diffuse.get_submodule(m)
        torch.testing.assert_close(conv.weight.detach(), state[f"diffuse.{m}.weight"][:, cc:], rtol=0, atol=1e-6)
        torch.testing.assert_close(conv.coarse.weight.detach()[:, :, 0, 0],
                                   state[f"diffuse.{m}.weight"][:, :cc].sum(dim=(2, 3)), rtol=0, atol=1e-6)
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    a = kpcn.denoise(frame, file_model, device="cpu", precision="float32")
    b = kpcn.denoise(frame, up1, device="cpu", precision="float32")
    assert np.abs(a - b).max() <= 1e-5 * max(1.0, float(np.abs(a).max()))
    # the file as trained (taps off the centre) is a different function: the conversion is not a no-op
    c = kpcn.denoise(frame, load_model(str(tmp_path / "a" / "model.safetensors"), device="cpu"), device="cpu",
                     precision="float32")
    assert np.abs(c - b).max() > 1e-4


def test_bfloat16_training_runs_and_is_refused_where_the_model_cannot(tiny_dataset, tmp_path):
    """``train.precision: bfloat16``: a U-Net trains (finite losses, float32 weights written); KPCN, whose
    layers only compute in float32, is refused before anything is written; an unknown name is a ConfigError."""
    from kpcn.config import ConfigError
    from kpcn.train_config import TrainConfig

    with pytest.raises(ConfigError, match="train.precision: expected float32 or bfloat16, got 'half'"):
        TrainConfig(precision="half")
    with pytest.raises(ConfigError, match="train.precision: .*cannot compute in 'bfloat16'"):
        train(tiny_cfg(tiny_dataset, tmp_path, name="k", stage1_steps=2, stage2_steps=0, precision="bfloat16"),
              progress=False)
    assert not (tmp_path / "k").exists()
    cfg = tiny_cfg(tiny_dataset, tmp_path, name="u", stage1_steps=0, stage2_steps=3, precision="bfloat16")
    cfg.model = {"name": "unet_kpcn", "widths": [8, 8, 12], "stem": "half", "kernel_scales": 2}
    res = train(cfg, progress=False)
    assert len(res["losses"]) == 3 and all(np.isfinite(res["losses"]))
    weights = read_weights(tmp_path / "u" / "model.safetensors")[1]
    assert all(v.dtype == torch.float32 for v in weights.values())


def test_init_extend_grows_the_unet_guide(tiny_dataset, tmp_path, render):
    """A ``stem: half`` U-Net whose full-resolution guide grows from a 1x1 conv of 4 channels to a 3x3 conv of
    8, started from the smaller file, denoises a real render as the file does (the file's weights are the
    centre taps, the head reads the new channels through zero weights); the new taps learn."""
    import kpcn
    from kpcn.config import ConfigError
    from kpcn.features import frame_to_tensors
    from kpcn.inference import load_model

    unet = dict(name="unet_kpcn", widths=[8, 12, 16], convs_per_level=1, kernel_size=3, stem="half",
                summary_channels=4, kernel_scales=2)

    def ucfg(name, guide_kernel, guide_channels, **kw):
        cfg = tiny_cfg(tiny_dataset, tmp_path, name=name, **{"stage1_steps": 3, "stage2_steps": 0, **kw})
        cfg.model = dict(unet, guide_kernel=guide_kernel, guide_channels=guide_channels)
        return cfg

    train(ucfg("a", 1, 4), progress=False)
    src = tmp_path / "a" / "model.safetensors"
    with pytest.raises(ConfigError, match="guide_kernel"):  # not without saying so
        train(ucfg("b", 3, 8, init=str(src)), progress=False)
    train(ucfg("b", 3, 8, init=str(src), init_extend=True, lr=1e-12, stage1_steps=1), progress=False)
    small, big = load_model(str(src), device="cpu"), load_model(str(tmp_path / "b" / "model.safetensors"), device="cpu")
    g = big.diffuse.guide.weight
    assert g.shape[0] == 8 and g.shape[2:] == (3, 3)
    frame = render("test:glossy", spp=4, seed=1, resolution=(40, 40))
    a = kpcn.denoise(frame, small, device="cpu", precision="float32")
    b = kpcn.denoise(frame, big, device="cpu", precision="float32")
    assert np.abs(a - b).max() <= 1e-5 * max(1.0, float(np.abs(a).max()))
    ring = torch.ones(3, 3, dtype=torch.bool)
    ring[1, 1] = False
    assert g[:4][..., ring].abs().max() <= 1e-9  # the file's channels: centre taps only
    spec = big.input_spec
    x = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    g.requires_grad_(True)
    big.diffuse(x["diffuse"]).square().mean().backward()
    assert g.grad[:4][..., ring].abs().max() > 0


def test_converged_max_noise_leaves_out_the_noisy_pixels_of_converged_patches(tiny_dataset, tmp_path):
    from kpcn.config import ConfigError
    from kpcn.data import CONVERGED_SPP, PatchDataset, read_pair
    from kpcn.inputs import get_input_spec
    from kpcn.train_data import split_pairs
    from kpcn.train_steps import compute_loss, unconverged_pixels

    spec = get_input_spec("kpcn_split")
    cfg = tiny_cfg(tiny_dataset, tmp_path)
    cfg.data.converged_inputs = True
    pairs = split_pairs(cfg, progress=False)[0]
    ds = PatchDataset(pairs, 24, 8, seed=1, spec=spec)
    batch = torch.utils.data.default_collate([ds[i] for i in range(len(ds))])
    from_converged = torch.tensor([ds.pairs[int(f)].spp == CONVERGED_SPP for f in ds.index[:, 0]])
    assert batch["converged"].dtype == torch.bool and torch.equal(batch["converged"], from_converged)
    assert from_converged.any() and not from_converged.all()
    # the colour variance the features carry is the renderer's (RGB means of each branch: close, not equal)
    noisy, _ = read_pair(pairs[0], spec)
    whole = PatchDataset(pairs[:1], 48, 1, sampling="uniform", spec=spec)[0]
    var = spec.colour_variance({k: v[None] for k, v in whole.items()})[0, 0].numpy()
    rendered = noisy["colorVariance"].mean(-1)
    ratio = var[rendered > 1e-8] / rendered[rendered > 1e-8]
    assert 0.8 < np.median(ratio) < 1.25 and np.mean((ratio > 0.5) & (ratio < 2)) > 0.9
    # which pixels are left out: noisy ones (relative noise above the threshold) of converged patches only
    skip = unconverged_pixels(batch, spec, 0.02)
    rel = spec.colour_variance(batch).clamp_min(0).sqrt() / (batch["y_color"].mean(1, keepdim=True) ** 2 + 0.01).sqrt()
    assert torch.equal(skip, (rel > 0.02) & from_converged.view(-1, 1, 1, 1))
    assert skip.any() and (~skip[from_converged]).any()  # the tiny references have both
    assert unconverged_pixels({**batch, "converged": torch.zeros_like(from_converged)}, spec, 0.02) is None
    # they add nothing to the loss's gradient; every other pixel does
    out = {k: (batch[f"y_{k}"] + 0.1 * torch.randn_like(batch[f"y_{k}"])).requires_grad_()
           for k in ("diffuse", "specular", "color")}
    cfg.data.converged_max_noise = 0.02
    for stage, key in ((1, "diffuse"), (2, "color")):
        (grad,) = torch.autograd.grad(compute_loss(out, batch, stage, cfg, spec.branches, spec), out[key])
        assert (grad.abs().sum(1, keepdim=True)[skip] == 0).all()
        assert (grad.abs().sum(1, keepdim=True)[~skip] > 0).float().mean() > 0.99
    cfg.data.converged_max_noise = None
    (grad,) = torch.autograd.grad(compute_loss(out, batch, 2, cfg, spec.branches, spec), out["color"])
    assert (grad.abs().sum(1, keepdim=True)[skip] > 0).float().mean() > 0.99
    # a training run with it; refused for a model whose inputs carry no variance
    cfg = tiny_cfg(tiny_dataset, tmp_path, name="cmn", stage1_steps=2, stage2_steps=2)
    cfg.data.converged_inputs, cfg.data.converged_max_noise = True, 0.02
    assert np.isfinite(train(cfg, progress=False)["losses"]).all()
    cfg.name, cfg.model["input_spec"] = "cmn2", "split_novar"
    with pytest.raises(ConfigError, match="converged_max_noise.*split_novar"):
        train(cfg, progress=False)


def test_distill_min_spp_teaches_the_init_files_outputs_on_high_spp_patches(tiny_dataset, tmp_path):
    """``train.distill_min_spp``: patches with that many spp or more are taught the ``init`` file's own outputs (a
    run from a file on 8-spp patches alone starts at a loss of 0, the same run without the option does not); in a
    batch of 4- and 8-spp patches only the 8-spp ones get the teacher's targets; refused without ``init``."""
    from kpcn.config import ConfigError
    from kpcn.data import PatchDataset
    from kpcn.inference import load_model
    from kpcn.train import split_pairs
    from kpcn.train_steps import distill_targets, model_inputs

    train(tiny_cfg(tiny_dataset, tmp_path, name="a", stage1_steps=3, stage2_steps=0), progress=False)
    src = str(tmp_path / "a" / "model.safetensors")
    losses = {}
    for name, extra in (("dist", {"distill_min_spp": 8}), ("ref", {})):
        cfg = tiny_cfg(tiny_dataset, tmp_path, name=name, init=src, lr=1e-12, stage1_steps=2, stage2_steps=1, **extra)
        cfg.data.spp = [8]
        losses[name] = train(cfg, progress=False)["losses"]
    assert max(losses["dist"]) < 1e-6, losses["dist"]
    assert min(losses["ref"]) > 1e-3, losses["ref"]

    ds = PatchDataset(split_pairs(tiny_cfg(tiny_dataset, tmp_path))[0], 24, 8, seed=1, label_spp=True)
    batch = torch.utils.data.default_collate([ds[i] for i in range(len(ds))])
    assert sorted(set(batch["spp"].tolist())) == [4, 8]
    teacher = load_model(src, device="cpu")
    got = distill_targets(teacher, batch, 8)
    hi = batch["spp"] >= 8
    with torch.no_grad():
        want = teacher({k: v[hi] for k, v in model_inputs(teacher, batch).items()})
    for k in ("diffuse", "specular", "color"):
        torch.testing.assert_close(got[f"y_{k}"][hi], want[k])
        assert not torch.allclose(batch[f"y_{k}"][hi], want[k]), f"y_{k}: the references were the teacher's already"
        assert torch.equal(got[f"y_{k}"][~hi], batch[f"y_{k}"][~hi])
    with pytest.raises(ConfigError, match="needs train.init"):
        train(tiny_cfg(tiny_dataset, tmp_path, name="d", distill_min_spp=8), progress=False)


def test_resume_keeps_the_configs_lr_mult_factors():
    """A resume restores Adam's moments from the checkpoint but each group's ``train.lr_mult`` factor from the config
    it runs with (a changed factor is one of the settings a resume may change; Adam's ``load_state_dict`` alone puts
    the file's back)."""
    from kpcn.checkpoint import rng_state
    from kpcn.models import create_model
    from kpcn.runs import _restore_optimizer
    from kpcn.train_steps import _make_optimizer

    model = create_model("unet_kpcn", stem="half", kernel_scales=2, widths=[8, 12], summary_channels=4)
    saved = _make_optimizer(model, 1e-3, {"*.head.*": 10})
    for p in model.parameters():
        p.grad = torch.ones_like(p)
    saved.step()
    resumed = _make_optimizer(model, 1e-3, {"*.head.*": 3})
    _restore_optimizer(resumed, {"optimizer": saved.state_dict(), "rng": rng_state()}, "ckpt")
    assert sorted(g["lr_mult"] for g in resumed.param_groups) == [1.0, 3]
    head = next(p for n, p in model.named_parameters() if ".head." in n)
    assert torch.equal(resumed.state[head]["exp_avg"], saved.state[head]["exp_avg"])
    assert float(resumed.state[head]["step"]) == 1
