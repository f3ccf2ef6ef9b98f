"""kpcn.inference: tiled == untiled, skipping what a scene does not need, weights loading, EXR output, CLI."""
from __future__ import annotations

import os
import pickle
import subprocess
import sys

import numpy as np
import pytest
import torch

from kpcn import inference as dn
from kpcn.checkpoint import CheckpointError, save_train_state, save_weights
from kpcn.features import branch_features, frame_to_tensors, make_features
from kpcn.inference.cli import main as cli_main
from kpcn.io import Frame, MissingLayerError, read_exr, write_exr
from kpcn.models import create_model, weights_entry

# conv radius 2 (5x5), k = 5: receptive radius 4, halo 5
SMALL = dict(layers=2, width=8, conv_size=5, kernel_size=5, out_init_gain=1.0)
# k = 11 > an 8x8 frame
WIDE_K = dict(layers=2, width=8, conv_size=5, kernel_size=11, out_init_gain=1.0)
# dilated 3x3 convs (as configs/small.yaml): receptive radius (1 + 3) * 1 = 4
DILATED = dict(layers=2, width=8, conv_size=3, kernel_size=5, dilations=[1, 3], out_init_gain=1.0)


def _model(name="kpcn", seed=0, **cfg):
    torch.manual_seed(seed)
    return create_model(name, **(cfg or SMALL)).eval()


def _copy(frame: Frame, **changes) -> Frame:
    layers = {k: v.copy() for k, v in frame.layers.items()}
    layers.update(changes)
    return Frame(layers, dict(frame.meta))


def _close(a, b, rtol=1e-5):
    scale = max(float(np.abs(b).max()), 1e-6)
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale)


def _direct(model, frame):
    """The model run untiled on make_features of the whole frame (no kpcn.inference code involved)."""
    f = make_features(frame_to_tensors(frame))
    with torch.no_grad():
        out = model({"diffuse": f.x_diffuse, "specular": f.x_specular, "albedo": f.albedo})
        return out["color"][0].permute(1, 2, 0).numpy()


# ----------------------------------------------------------------------------- features


def test_branch_subsets_and_crops_match_full_features(render):
    frame = render("test:glossy", 4, 1, resolution=(40, 30))
    buf = frame_to_tensors(frame)
    ref = make_features(buf)
    got = branch_features(buf)
    assert torch.equal(got["diffuse"], ref.x_diffuse)
    assert torch.equal(got["specular"], ref.x_specular)
    assert torch.equal(got["albedo"], ref.albedo)
    # one branch: only that branch's buffers are needed and its tensor is the same
    only = {k: v for k, v in buf.items() if not k.startswith("specular")}
    d = branch_features(only, branches=("diffuse",))
    assert set(d) == {"albedo", "diffuse"} and torch.equal(d["diffuse"], ref.x_diffuse)
    # the whole frame's depth scale on a crop gives the whole frame's features of that crop
    scale = float(frame["depth"].max())
    crop = {k: v[..., 5:20, 7:30] for k, v in buf.items()}
    c = branch_features(crop, scale)
    torch.testing.assert_close(c["diffuse"][..., :-1, :-1], ref.x_diffuse[..., 5:19, 7:29], rtol=0, atol=0)


def test_plan_tiles_cover_the_frame_once():
    for h, w, t, halo in [(50, 70, 24, 5), (8, 8, 24, 6), (8, 8, 3, 6), (33, 17, 16, 0)]:
        cover = np.zeros((h, w), int)
        for tile in dn.plan_tiles(h, w, t, halo):
            cover[tile.interior] += 1
            assert tile.cy0 == max(0, tile.y0 - halo) and tile.cx1 == min(w, tile.x1 + halo)
        assert (cover == 1).all()
    assert len(list(dn.plan_tiles(50, 70, None, 5))) == 1
    # aligned crops (a model that pools by `alignment`): corners on the grid, the halo still covered
    for h, w, t, halo, a in [(50, 70, 24, 5, 8), (8, 8, 3, 6, 4), (33, 17, 16, 0, 2), (40, 40, 10, 3, 8)]:
        cover = np.zeros((h, w), int)
        size = dn.tile_size(t, a)
        assert size % a == 0 and t <= size < t + a
        for tile in dn.plan_tiles(h, w, t, halo, alignment=a):
            cover[tile.interior] += 1
            assert tile.y0 % a == 0 and tile.x0 % a == 0
            # the crop starts at the grid point at or before interior - halo, so it holds the whole halo
            assert tile.cy0 == max(0, (tile.y0 - halo) // a * a) and tile.cx0 == max(0, (tile.x0 - halo) // a * a)
            assert tile.cy0 % a == 0 and tile.cx0 % a == 0
            assert tile.cy1 == min(h, tile.y1 + halo) and tile.cx1 == min(w, tile.x1 + halo)
        assert (cover == 1).all()


# ----------------------------------------------------------------------------- tiling


@pytest.mark.parametrize(
    "name, cfg, res, tile",
    [
        ("kpcn", SMALL, (70, 50), 24),  # non-multiple sizes: 3 x 3 tiles with remainders
        ("kpcn", SMALL, (33, 17), 16),
        ("kpcn", SMALL, (20, 12), 64),  # smaller than one tile
        ("kpcn", WIDE_K, (8, 8), 3),  # smaller than the kernel, tiles smaller than the halo
        ("kpcn", WIDE_K, (8, 8), 256),
        ("dpcn", SMALL, (70, 50), 24),
        ("kpcn", DILATED, (70, 50), 24),
    ],
)
def test_tiled_equals_untiled(render, name, cfg, res, tile):
    frame = render("test:glossy", 4, 1, resolution=res)
    model = _model(name, **cfg)
    full = dn.denoise(frame, model, tile=None, skip=False)
    tiled = dn.denoise_result(frame, model, tile=tile, skip=False)
    assert tiled.color.shape == (res[1], res[0], 3) and tiled.color.dtype == np.float32
    _close(tiled.color, full)
    _close(full, _direct(model, frame))  # untiled denoise == the model on make_features
    n_tiles = -(-res[0] // tile) * -(-res[1] // tile)
    assert tiled.stats.tiles == tiled.stats.tiles_run == n_tiles
    # skipping (per-tile zero branches, KPCN only) does not change a tiled KPCN result
    if name == "kpcn":
        np.testing.assert_array_equal(dn.denoise(frame, model, tile=tile), tiled.color)


# ----------------------------------------------------------------------------- skipping


class _Counter:
    def __init__(self, module, monkeypatch):
        self.calls = 0
        orig = module.forward

        def wrapped(*a, **k):
            self.calls += 1
            return orig(*a, **k)

        monkeypatch.setattr(module, "forward", wrapped)


@pytest.mark.parametrize("name", ["kpcn", "dpcn"])
def test_zero_specular_branch_is_not_run(render, monkeypatch, name):
    src = render("test:diffuse_box", 4, 2, resolution=(48, 40))
    z = np.zeros_like(src["specular"])
    frame = _copy(src, specular=z, specularVariance=np.zeros_like(src["specularVariance"]),
                  color=src["diffuse"].copy(), colorVariance=src["diffuseVariance"].copy())
    model = _model(name)
    # the specular features are never built either (the kpcn_split spec builds them with branch_features)
    import kpcn.inputs

    built = []
    orig_bf = kpcn.inputs.branch_features
    monkeypatch.setattr(kpcn.inputs, "branch_features",
                        lambda b, s, br, **kw: built.append(tuple(br)) or orig_bf(b, s, br, **kw))
    spec = _Counter(model.specular, monkeypatch)
    diff = _Counter(model.diffuse, monkeypatch)
    res = dn.denoise_result(frame, model, tile=16)
    assert spec.calls == 0 and diff.calls == res.stats.tiles == 9
    assert set(built) == {("diffuse",)}
    assert res.stats.branches_skipped == ("specular",)
    assert res.stats.branch_tiles_skipped == {"diffuse": 0, "specular": 9}
    full = dn.denoise(frame, model, tile=16, skip=False)
    assert spec.calls == 9
    if name == "kpcn":
        # a KPCN of an all-zero branch is exactly zero: skipping is exact
        np.testing.assert_array_equal(res.color, full)
        _close(res.color, _direct(model, frame))
    else:
        # a DPCN adds a residual even to a zero input; skipping sets that component to 0
        f = make_features(frame_to_tensors(frame))
        with torch.no_grad():
            want = model({"diffuse": f.x_diffuse, "specular": None, "albedo": f.albedo})["color"][0].permute(1, 2, 0).numpy()
        _close(res.color, want)


def test_kpcn_skips_specular_on_tiles_without_it(render, monkeypatch):
    # the light is the only specular thing in the box: most tiles do not need the specular branch
    frame = render("test:diffuse_box", 4, 3, resolution=(64, 64))
    assert frame["specular"].max() > 0
    model = _model("kpcn")
    res = dn.denoise_result(frame, model, tile=16)
    s = res.stats
    assert s.branches_skipped == () and 0 < s.branch_tiles_run["specular"] < s.tiles
    assert s.branch_tiles_skipped["specular"] == s.tiles - s.branch_tiles_run["specular"]
    np.testing.assert_array_equal(res.color, dn.denoise(frame, model, tile=16, skip=False))
    _close(res.color, _direct(model, frame))


def test_no_hit_tiles_are_passed_through(render, monkeypatch):
    frame = render("test:no_hit", 4, 1, resolution=(40, 36))
    assert frame["depth"].max() == 0
    model = _model("kpcn")

    def boom(*a, **k):
        raise AssertionError("the network must not run on a no-hit, converged frame")

    monkeypatch.setattr(model, "forward", boom)
    res = dn.denoise_result(frame, model, tile=16)
    np.testing.assert_array_equal(res.color, frame["color"])
    assert res.stats.tiles_passed_through == res.stats.tiles == 9 and res.stats.tiles_run == 0
    assert "diffuse" in res.stats.branches_skipped


def test_noisy_no_hit_tiles_are_denoised(render):
    # no geometry but a noisy colour: not converged, so the network runs
    frame = render("test:no_hit", 4, 1, resolution=(24, 24))
    rng = np.random.default_rng(0)
    noisy = _copy(frame)
    noisy.layers["specular"] = frame["specular"] * rng.uniform(0.5, 1.5, frame["specular"].shape).astype(np.float32)
    noisy.layers["color"] = noisy["specular"].copy()
    noisy.layers["colorVariance"] = np.full_like(frame["colorVariance"], 0.01)
    noisy.layers["specularVariance"] = np.full_like(frame["specularVariance"], 0.01)
    res = dn.denoise_result(noisy, _model("kpcn"), tile=16)
    assert res.stats.tiles_passed_through == 0 and res.stats.tiles_run == res.stats.tiles


# ----------------------------------------------------------------------------- files and weights


def _checkpoint(tmp_path, name="kpcn", cfg=SMALL, fname="model.safetensors"):
    """A weights file (``.safetensors``) or a training state (``.pt``) of a fresh model, and the model."""
    model = _model(name, **cfg)
    path = tmp_path / fname
    if path.suffix == ".safetensors":
        save_weights(path, model, step=7)
    else:
        save_train_state(path, model, None, 7, {"model": model.hparams()})
    return path, model


@pytest.mark.parametrize("fname", ["model.safetensors", "latest.pt"])
def test_load_model_from_checkpoint_and_cache(tmp_path, render, fname):
    path, model = _checkpoint(tmp_path, fname=fname)
    a = dn.load_model(path, device="cpu")
    assert a is dn.load_model(str(path), device="cpu")  # cached
    assert a.name == "kpcn" and a.hparams() == model.hparams()
    for k, v in model.state_dict().items():
        assert torch.equal(a.state_dict()[k], v)
    frame = render("test:glossy", 4, 1, resolution=(30, 20))
    np.testing.assert_array_equal(dn.denoise(frame, str(path), tile=16), dn.denoise(frame, model, tile=16))


def test_load_model_errors(tmp_path, monkeypatch):
    from kpcn.models import registry

    default = weights_entry(dn.DEFAULT_MODEL).path
    if not default.exists():
        with pytest.raises(dn.DefaultWeightsMissing, match="kpcn.train"):
            dn.load_model(None)
    else:
        assert dn.load_model(None, device="cpu").receptive_radius > 0
    if not weights_entry("dpcn").path.exists():
        with pytest.raises(dn.DefaultWeightsMissing, match=r"shipped weights dpcn:small are registered but .* is missing"):
            dn.load_model("dpcn")
    else:
        assert dn.load_model("dpcn", device="cpu").name == "dpcn"
    # a registered model without shipped weights (every built-in model ships some now: take mskpcn's away)
    registry._ensure_builtin_models()
    monkeypatch.setitem(registry._WEIGHTS, "mskpcn", {})
    monkeypatch.delitem(registry._DEFAULT_WEIGHTS, "mskpcn", raising=False)
    with pytest.raises(dn.DefaultWeightsMissing, match=r"no shipped weights mskpcn:<default>; shipped: .*kpcn\.train"):
        dn.load_model("mskpcn")
    with pytest.raises(FileNotFoundError, match=r"nope\.pt: neither a weights file nor a registered model name"):
        dn.load_model(str(tmp_path / "nope.pt"))
    bad = tmp_path / "bad.pt"
    torch.save({"weights": {}}, bad)
    with pytest.raises(CheckpointError, match=r"bad\.pt: not a kpcn checkpoint \(no 'model' weights; found \['weights'\]\)"):
        dn.load_model(bad)


class _Evil:
    """Unpickling this runs code: it writes ``marker`` (what a malicious checkpoint could do instead)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"open({self.marker!r}, 'w').write('pwned')",)


def _malicious_checkpoint(tmp_path, model, protocol):
    """A ``.pt`` checkpoint with valid weights plus an object whose unpickling writes a marker file."""
    marker = tmp_path / "PWNED"
    path = tmp_path / "evil.pt"
    ckpt = {"model": model.state_dict(), "model_name": model.name, "hparams": model.hparams(), "step": 1,
            "note": _Evil(marker)}
    torch.save(ckpt, path, pickle_protocol=protocol)
    assert not marker.exists()
    return path, marker


# torch.save's default protocol (2), and the protocol plain pickle writes (torch's weights-only loader fails earlier)
@pytest.mark.parametrize("protocol", [2, pickle.DEFAULT_PROTOCOL])
def test_malicious_pickle_checkpoint_is_refused(tmp_path, render, protocol):
    model = _model("kpcn")
    path, marker = _malicious_checkpoint(tmp_path, model, protocol)
    frame = render("test:glossy", 4, 1, resolution=(16, 16))
    src = tmp_path / "noisy.exr"
    write_exr(src, frame.layers, frame.meta)
    out = tmp_path / "out.exr"

    # the command line refuses it without running its code
    proc = subprocess.run([sys.executable, "-m", "kpcn.inference", str(src), "-o", str(out), "--model", str(path),
                           "--device", "cpu"], capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert not marker.exists(), "unpickling the checkpoint ran its code"
    assert not out.exists()
    assert f"cannot load the model: {path}: " in proc.stderr
    if protocol == 2:
        assert "--trust-checkpoint" in proc.stderr  # says how to load a file one trusts

    # so does the Python API (and denoise through it), naming the file
    with pytest.raises(CheckpointError, match=r"evil\.pt: holds Python objects" if protocol == 2 else r"evil\.pt: "):
        dn.load_model(path, device="cpu")
    with pytest.raises(CheckpointError, match=r"evil\.pt"):
        dn.denoise(frame, str(path), device="cpu")
    assert not marker.exists()

    # trust_pickle=True unpickles it (running its code) and loads the weights
    loaded = dn.load_model(path, device="cpu", trust_pickle=True)
    assert marker.exists() and marker.read_text() == "pwned"
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v)


def test_exr_in_exr_out(tmp_path, render):
    import OpenEXR

    frame = render("test:glossy", 4, 1, resolution=(30, 20))
    src = tmp_path / "noisy.exr"
    write_exr(src, frame.layers, frame.meta)
    model = _model("kpcn")
    out = tmp_path / "out" / "clean.exr"
    color = dn.denoise(src, model, out_path=out, tile=16)
    back = read_exr(out)
    assert set(back.layers) == {"color", "albedo", "normal", "depth"}
    np.testing.assert_array_equal(back["color"], color)
    np.testing.assert_array_equal(back["albedo"], frame["albedo"])
    with OpenEXR.File(str(out), separate_channels=True) as f:
        header = dict(f.header())
        assert set(f.channels()) >= {"R", "G", "B", "albedo.R", "normal.G", "depth.Y"}
        assert header["source"].endswith("noisy.exr") and header["denoiser"].startswith("kpcn")
        assert header["denoiseSeconds"] >= 0 and header["spp"] == 4


def test_missing_layers_are_refused(tmp_path, render):
    frame = render("test:glossy", 4, 1, resolution=(16, 16))
    layers = {k: v for k, v in frame.layers.items() if k not in ("specularVariance", "normal")}
    path = tmp_path / "partial.exr"
    write_exr(path, layers)
    with pytest.raises(MissingLayerError, match="normal, specularVariance; found: .*albedo"):
        dn.denoise(path, _model("kpcn"))


def test_in_memory_frame_is_sanitised_not_modified(render):
    frame = _copy(render("test:glossy", 4, 1, resolution=(16, 16)))
    frame.layers["diffuse"][3, 4, 0] = np.nan
    frame.layers["specular"][5, 5, 1] = np.inf
    with pytest.warns(RuntimeWarning, match="diffuse: 1, specular: 1"):
        res = dn.denoise_result(frame, _model("kpcn"))
    assert np.isnan(frame["diffuse"][3, 4, 0])  # the caller's arrays are untouched
    assert np.isfinite(res.color).all() and (res.color >= 0).all()
    assert res.stats.nonfinite == {"diffuse": 1, "specular": 1}


def test_cli_continues_after_a_bad_file(tmp_path, render, capsys):
    path, _ = _checkpoint(tmp_path)
    frame = render("test:glossy", 4, 1, resolution=(20, 16))
    good = tmp_path / "good.exr"
    write_exr(good, frame.layers, frame.meta)
    partial = tmp_path / "partial.exr"
    write_exr(partial, {"color": frame["color"]})
    garbage = tmp_path / "garbage.exr"
    garbage.write_bytes(b"not an exr at all")
    out_dir = tmp_path / "out"
    rc = cli_main([str(garbage), str(good), str(partial), "--out-dir", str(out_dir), "--model", str(path),
                  "--tile", "8", "--device", "cpu"])
    cap = capsys.readouterr()
    assert rc == 1
    assert (out_dir / "good_denoised.exr").exists()
    assert not (out_dir / "garbage_denoised.exr").exists()
    assert "good.exr ->" in cap.out and " s (" in cap.out
    assert "2 of 3 file(s) failed" in cap.err and "partial.exr" in cap.err and "missing layer" in cap.err
    assert "cannot read as OpenEXR" in cap.err
    with pytest.raises(SystemExit):
        cli_main([str(good), str(partial), "-o", str(tmp_path / "x.exr")])
    assert cli_main([str(good), "--model", str(tmp_path / "nope.pt")]) == 2
    assert cli_main([str(good), "-o", str(tmp_path / "one.exr"), "--model", str(path), "--device", "cpu"]) == 0
    assert read_exr(tmp_path / "one.exr")["color"].shape == (16, 20, 3)


def test_half_on_cpu_warns_and_runs_float32(render):
    frame = render("test:glossy", 4, 1, resolution=(16, 16))
    model = _model("kpcn")
    with pytest.warns(RuntimeWarning, match="only used on CUDA"):
        out = dn.denoise(frame, model, device="cpu", half=True)
    np.testing.assert_array_equal(out, dn.denoise(frame, model, device="cpu"))


def test_bench_denoise_skip_smoke(render, capsys):
    from kpcn.bench import SUBCOMMANDS

    rc = SUBCOMMANDS["denoise"](["--skip", "--sizes", "24", "--tile", "8", "--repeats", "1", "--scenes", "test:no_hit"])
    out = capsys.readouterr().out
    assert rc == 0 and "test:no_hit" in out and "tiles passed through" in out


_HEAP_SCRIPT = r"""
import time
import torch
from kpcn.inference import heap
from kpcn.inference.heap import heap_tuning_available, release_heap, reuse_heap

def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024

def touch_and_free(mb):
    t = torch.empty(mb << 18)  # float32: mb MB
    t.fill_(1.0)
    del t

print(heap_tuning_available())
base = rss_mb()
touch_and_free(48)
print(rss_mb() - base)          # no block: glibc maps and unmaps a block above 32 MiB
with reuse_heap():
    with reuse_heap():
        touch_and_free(48)
    print(rss_mb() - base)      # inner exit: still held for reuse
    for _ in range(4):          # reused (an aligned request may not fit the one freed block: at most two)
        touch_and_free(48)
    print(rss_mb() - base)
    held = rss_mb()
    touch_and_free((heap._DURING >> 20) + 32)  # above the threshold: mapped and unmapped as before
    print(rss_mb() - held)
kept = rss_mb() - base          # outer exit: kept for KPCN_HEAP_KEEP_S (0.5 s here) for the next call
print(kept)
with reuse_heap():              # a call within that time reuses it: nothing new faulted in
    touch_and_free(48)
print(rss_mb() - base - kept)
time.sleep(1.5)
print(rss_mb() - base)          # idle past the keep time: given back
with reuse_heap():
    touch_and_free(48)
release_heap()                  # or at once, on request
print(rss_mb() - base)
"""


def test_reuse_heap_keeps_freed_memory_during_a_call_and_gives_it_back_after():
    # a fresh interpreter: the heap settings are per process
    env = {**os.environ, "KPCN_HEAP_KEEP_S": "0.5"}
    out = subprocess.run([sys.executable, "-c", _HEAP_SCRIPT], capture_output=True, text=True, check=True,
                         env=env).stdout.split()
    assert out[0] == "True", "this test needs glibc (the heap tuning is a no-op elsewhere)"
    plain, inner, reused, big, kept, again, idle, released = map(float, out[1:])
    assert plain < 16, f"a freed 48 MB block stayed resident without the tuning: +{plain:.0f} MB"
    assert inner > 40, f"a freed block was not kept for reuse inside the block: +{inner:.0f} MB"
    assert reused < 2 * 48 + 16, f"freed blocks not reused: +{reused:.0f} MB after five 48 MB blocks"
    assert big < 16, f"a freed block above the threshold stayed resident: +{big:.0f} MB"
    assert kept > 40, f"memory not kept for the next call when the outermost block ended: +{kept:.0f} MB"
    assert again < 16, f"the next call did not reuse the kept memory: +{again:.0f} MB more"
    assert idle < 16, f"memory not given back after the keep time: +{idle:.0f} MB"
    assert released < 16, f"release_heap() did not give the memory back: +{released:.0f} MB"


_HEAP_FORK_SCRIPT = r"""
import os
import torch
from kpcn.inference import heap

def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024

base = rss_mb()
with heap.reuse_heap():
    t = torch.empty(48 << 18)
    t.fill_(1.0)
    del t
print(rss_mb() - base)  # kept for the next call
r, w = os.pipe()
if os.fork() == 0:  # the child has no timer thread: the kept memory must be given back at the fork
    os.write(w, f"{rss_mb() - base} {heap._raised}".encode())
    os._exit(0)
os.wait()
print(os.read(r, 100).decode())
"""


def test_a_forked_child_gives_the_kept_memory_back():
    env = {**os.environ, "KPCN_HEAP_KEEP_S": "30"}
    out = subprocess.run([sys.executable, "-c", _HEAP_FORK_SCRIPT], capture_output=True, text=True, check=True,
                         env=env).stdout.split()
    kept, child, raised = float(out[0]), float(out[1]), out[2]
    assert kept > 40, f"memory not kept after the call: +{kept:.0f} MB"
    assert child < 16 and raised == "False", f"the forked child kept +{child:.0f} MB (thresholds raised: {raised})"


def test_bench_train_and_denoise_compare_precisions(capsys):
    """``--precisions float32 bfloat16``: one row per config and dtype, in one run; a dtype the model lacks or
    an unknown name is refused."""
    from kpcn.bench import SUBCOMMANDS

    rc = SUBCOMMANDS["train"](["--configs", "configs/small_unet.yaml", "--precisions", "float32", "bfloat16",
                               "--batch", "2", "--patch", "16", "--steps", "1", "--warmup", "0"])
    out = capsys.readouterr().out
    assert rc == 0 and "configs/small_unet.yaml@float32" in out and "configs/small_unet.yaml@bfloat16" in out
    assert SUBCOMMANDS["train"](["--configs", "configs/small_unet.yaml", "--precisions", "half"]) == 2
    with pytest.raises(ValueError, match="cannot compute in 'bfloat16'"):
        SUBCOMMANDS["train"](["--configs", "configs/small.yaml", "--precisions", "bfloat16", "--steps", "1",
                              "--warmup", "0", "--batch", "1", "--patch", "16"])
    capsys.readouterr()
    assert SUBCOMMANDS["denoise"](["--precisions", "fp16", "--sizes", "24", "--no-oidn"]) == 2
    assert "precisions: expected auto, float32 or bfloat16" in capsys.readouterr().err


def test_bench_denoise_rounds_take_turns_and_pool_every_call(capsys, tmp_path):
    """``--rounds 2``: each configuration runs twice, in turn, and its row is the median of all its timed calls
    (the JSON keeps each round's median); ``--rounds 0`` is refused."""
    import json
    import statistics

    from kpcn.bench import SUBCOMMANDS

    out = tmp_path / "b.json"
    rc = SUBCOMMANDS["denoise"](["--sizes", "24", "--models", "small_unet", "--no-oidn", "--repeats", "2",
                                 "--rounds", "2", "--threads", "1", "--json", str(out)])
    text = capsys.readouterr()
    assert rc == 0 and "x 2 rounds" in text.out
    assert text.err.count("running small_unet") == 2
    (r,) = json.loads(out.read_text())["results"]
    assert r["status"] == "ok" and r["rounds"] == 2 and len(r["round_medians_s"]) == 2 and len(r["times_s"]) == 4
    assert r["median_s"] == statistics.median(r["times_s"])
    assert SUBCOMMANDS["denoise"](["--sizes", "24", "--no-oidn", "--rounds", "0"]) == 2
    assert "--rounds must be >= 1" in capsys.readouterr().err


def test_bench_denoise_times_the_native_kernels_against_the_pytorch_paths(capsys, tmp_path, monkeypatch):
    """``--kernels native pytorch``: the same model twice in one run, each in a process whose ``KPCN_NATIVE`` says
    which kernels it ran (the status each reports); an unknown name is refused."""
    import json

    from kpcn.bench import SUBCOMMANDS
    from kpcn.ops import native

    monkeypatch.setenv("KPCN_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "b.json"
    rc = SUBCOMMANDS["denoise"](["--sizes", "40", "--models", "small_unet", "--no-oidn", "--kernels", "native",
                                 "pytorch", "--threads", "1", "--json", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and "small_unet+native" in text and "small_unet+pytorch" in text
    by = {r["model"]: r for r in json.loads(out.read_text())["results"]}
    assert by["small_unet+pytorch"]["native"] == "off (KPCN_NATIVE=0)"
    want = "on: loaded " if native._compiler() is not None else "unavailable: "
    assert by["small_unet+native"]["native"].startswith(want), by["small_unet+native"]["native"]
    assert SUBCOMMANDS["denoise"](["--sizes", "24", "--no-oidn", "--kernels", "fast"]) == 2
    assert "kernels: expected native or pytorch" in capsys.readouterr().err


def test_bench_takes_a_bare_model_name_as_its_default_weights():
    """``--models unet_kpcn`` times the weights ``denoise`` would use (the registered default and its config);
    a name that is neither a config, a model nor a fallback is refused."""
    from kpcn.bench.models import _bench_model, _denoise_model_spec
    from kpcn.inference import load_model

    name, kw, origin = _denoise_model_spec("unet_kpcn")
    tag = weights_entry("unet_kpcn").tag
    assert (name, kw) == ("unet_kpcn", None) and f"unet_kpcn:{tag}" in origin
    assert _bench_model(name, kw) is load_model(None, "cpu")
    with pytest.raises(ValueError, match="unknown model config"):
        _denoise_model_spec("no_such_model")


def test_bench_finds_the_checkouts_configs_from_any_folder(tmp_path, monkeypatch):
    """A config name resolves to the checkout's ``configs/<name>.yaml`` when run from another folder too."""
    from pathlib import Path

    from kpcn.bench.models import _denoise_model_spec

    monkeypatch.chdir(tmp_path)
    name, kw, origin = _denoise_model_spec("unet_wide64h")
    want = Path(__file__).resolve().parents[1] / "configs" / "unet_wide64h.yaml"
    assert name == "unet_kpcn" and kw["widths"] == [64, 96, 128, 160] and Path(origin) == want


def test_a_frame_whose_spp_varies_is_denoised_region_by_region_and_keeps_its_count(tmp_path, render):
    """A real frame made of a 4-spp render in smooth regions and a 64-spp one elsewhere (what an adaptive sampler
    writes, with its sampleCount layer): the default leaves each region closer to the reference than its noisy
    pixels, and the output file keeps the count."""
    from kpcn.io import SAMPLE_COUNT
    from kpcn.metrics import relmse
    from kpcn.render import mix_frames
    from kpcn.sample_maps import region_mask

    res = (48, 48)
    lo, hi = render("test:glossy", spp=4, resolution=res), render("test:glossy", spp=64, seed=3, resolution=res)
    ref = render("test:glossy", spp=512, seed=2, role=1, resolution=res)["color"]
    low = region_mask(lo.shape, np.random.default_rng(0), cell=8, quantile=0.5)
    src = tmp_path / "mixed.exr"
    mixed = mix_frames(lo, hi, low)
    write_exr(src, mixed.layers, mixed.meta)
    out = tmp_path / "mixed_denoised.exr"
    res = dn.denoise_result(str(src), out_path=out)
    color = res.color
    assert res.stats.sample_count == (4.0, 64.0) and "4-64 spp per pixel" in res.stats.summary()
    for where in (low, ~low):
        assert relmse(color[where], ref[where]) < 0.7 * relmse(mixed["color"][where], ref[where])
    written = read_exr(out)
    np.testing.assert_array_equal(written[SAMPLE_COUNT], mixed[SAMPLE_COUNT])
    assert set(np.unique(written[SAMPLE_COUNT])) == {4.0, 64.0}
    holes = mixed.layers[SAMPLE_COUNT].copy()
    holes[:2, :3] = 0  # pixels an adaptive sampler gave no samples
    holes[5, :4] = 1  # and some only one
    with pytest.warns(UserWarning) as caught:
        dn.denoise(Frame({**mixed.layers, SAMPLE_COUNT: holes}, mixed.meta))
    said = " ".join(str(w.message) for w in caught)
    assert "6 pixel(s) have no samples" in said and "4 pixel(s) have one sample" in said


def test_bench_denoise_times_oidn_prefiltered_beside_oidn(capsys, tmp_path):
    """``--oidn-prefiltered``: OIDN with its guides prefiltered gets its own row, timed on the same rendered frame
    as OIDN's, in one run."""
    import json

    from kpcn.baselines import oidn_available
    from kpcn.bench import SUBCOMMANDS

    if not oidn_available():
        pytest.skip("pyoidn is not installed")
    out = tmp_path / "b.json"
    rc = SUBCOMMANDS["denoise"](["--sizes", "24", "--models", "small_unet", "--oidn-prefiltered", "--threads", "1",
                                 "--json", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    rows = {r["model"]: r for r in json.loads(out.read_text())["results"]}
    assert set(rows) == {"small_unet", "oidn", "oidn_prefiltered"}
    assert all(r["status"] == "ok" and r["median_s"] > 0 for r in rows.values())
    assert "oidn_prefiltered" in text
