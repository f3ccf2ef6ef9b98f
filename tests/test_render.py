"""The one-pass split renderer: properties of real Mitsuba renders."""
import json
import subprocess
import sys

import numpy as np
import pytest

from kpcn.io import read_exr
from kpcn.render import load_scene, render_dataset, render_frame


@pytest.mark.parametrize("scene", ["test:diffuse_box", "test:glossy", "test:glass", "test:envmap_open"])
def test_diffuse_plus_specular_is_color(render, scene):
    f = render(scene, spp=8)
    np.testing.assert_allclose(f["diffuse"] + f["specular"], f["color"], rtol=1e-6, atol=1e-5)
    assert (f["diffuse"] >= -1e-6).all(), "diffuse radiance must be non-negative"


def test_split_sends_glossy_and_glass_to_specular(render):
    f = render("test:glossy", spp=16)
    g = render("test:glass", spp=16)
    # non-diffuse materials are in view: a sizeable share of the light is specular
    for fr in (f, g):
        assert fr["specular"].sum() > 0.05 * fr["color"].sum()
        assert fr["diffuse"].sum() > 0.05 * fr["color"].sum()


def test_diffuse_scene_has_specular_only_on_emitters(render):
    f = render("test:diffuse_box", spp=16)
    spec = f["specular"].max(-1)
    # an all-diffuse scene: specular is only emitters seen directly (radiance of lights)
    lit = spec > 1e-6
    assert lit.mean() < 0.2
    assert (f["color"].max(-1)[lit] >= 0.5 * spec[lit]).all()
    assert np.allclose(f["specular"][~lit], 0.0)


def test_mean_matches_builtin_path_tracer(mi):
    loaded = load_scene("test:glossy", (32, 32))
    ours = render_frame("test:glossy", spp=512, seed=3, loaded=loaded)["color"]
    sensor_film = loaded[0].sensors()[0].film()
    assert tuple(sensor_film.size()) == (32, 32)
    ref = np.array(mi.render(loaded[0], integrator=mi.load_dict({"type": "path", "max_depth": 8}), spp=512, seed=11))
    assert ours.mean() == pytest.approx(ref[..., :3].mean(), rel=0.03)


@pytest.mark.parametrize("scene", ["test:glossy", "test:glass"])
def test_variance_matches_empirical_variance_over_seeds(render, scene):
    # 40 independent renders: glossy highlights are heavy-tailed, so fewer seeds give a noisy ratio
    frames = [render(scene, spp=8, seed=200 + i) for i in range(40)]
    for layer in ("color", "diffuse", "specular", "albedo", "normal", "depth"):
        vals = np.stack([f[layer] for f in frames])
        emp = vals.var(axis=0, ddof=1)
        pred = np.stack([f[f"{layer}Variance"] for f in frames]).mean(0)
        mask = pred > 1e-8
        if mask.sum() < 10:
            continue
        ratio = emp[mask].mean() / pred[mask].mean()
        assert 0.85 < ratio < 1.15, f"{layer}: empirical/predicted variance = {ratio:.3f}"


def test_same_seed_same_image_different_seed_different_noise(render):
    a = render("test:glossy", spp=4, seed=5)
    from kpcn.render import render_frame as rf

    b = rf("test:glossy", spp=4, seed=5, resolution=(32, 32))
    c = render("test:glossy", spp=4, seed=6)
    r = render("test:glossy", spp=4, seed=5, role=1)
    np.testing.assert_array_equal(a["color"], b["color"])
    assert not np.array_equal(a["color"], c["color"])
    assert not np.array_equal(a["color"], r["color"]), "reference role must not reuse input seeds"
    # the noise of two seeds is independent: correlation of residuals is small (on a scene
    # without heavy-tailed highlights, so the reference's own noise is negligible)
    # and over the pixels that do not see the light itself, whose few partly covered pixels
    # would dominate a correlation coefficient)
    reference = render("test:diffuse_box", spp=1024, seed=1, role=1)
    ref, lit = reference["color"], reference["specular"].max(-1) > 0
    a, c = render("test:diffuse_box", spp=4, seed=5), render("test:diffuse_box", spp=4, seed=6)
    ra, rc = (a["color"] - ref)[~lit].ravel(), (c["color"] - ref)[~lit].ravel()
    assert ra.size > 2000
    assert abs(np.corrcoef(ra, rc)[0, 1]) < 0.15
    # the same scene rendered twice with one seed gives identical residuals: the check can fail
    assert np.corrcoef(ra, (render("test:diffuse_box", spp=4, seed=5)["color"] - ref)[~lit].ravel())[0, 1] > 0.999


def test_features_of_first_hit(render):
    f = render("test:envmap_open", spp=8)
    n = np.linalg.norm(f["normal"], axis=-1)
    hit = f["depth"][..., 0] > 0
    assert hit.any() and (~hit).any()
    # unit normals inside objects (pixels on silhouettes average hits with misses, whose normal is 0)
    inner = hit.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= np.roll(np.roll(hit, dy, 0), dx, 1)
    assert inner.sum() > 20
    # (edges between faces average normals too: most, not all, inner pixels are unit length)
    assert np.mean(np.abs(n[inner] - 1) < 0.05) > 0.8 and n.max() < 1 + 1e-5
    assert np.all(f["albedo"][~hit] == 0) and np.all(n[~hit] == 0)


def test_no_hit_scene(render):
    f = render("test:no_hit", spp=4)
    assert np.all(f["depth"] == 0) and np.all(f["albedo"] == 0)
    assert f["color"].mean() > 0  # the environment is seen
    assert np.allclose(f["diffuse"], 0)


def test_xml_scene_is_overridden_and_rendered(mi, tmp_path):
    xml = tmp_path / "scene.xml"
    xml.write_text("""<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="stratified"><integer name="sample_count" value="64"/></sampler>
    <film type="hdrfilm"><integer name="width" value="640"/><integer name="height" value="480"/>
      <rfilter type="gaussian"/></film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
  <shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
</scene>""")
    scene, name, notes = load_scene(xml, (24, 16))
    assert name == "scene"
    assert any("rfilter" in n for n in notes) and any("integrator direct" in n for n in notes)
    f = render_frame(xml, spp=4, resolution=(24, 16))
    assert f["color"].shape == (16, 24, 3)
    # a diffuse sphere under a white sky: albedo 0.5 where hit, 0 elsewhere
    hit = f["depth"][..., 0] > 0
    assert np.allclose(np.median(f["albedo"][hit]), 0.5, atol=1e-6)
    assert f["albedo"].max() <= 0.5 + 1e-6 and np.all(f["albedo"][~hit] == 0)
    assert not any(p.name.startswith(".scene") for p in tmp_path.iterdir()), "temporary XML left behind"


def _sphere_scene(mi, bsdf: dict) -> dict:
    """One sphere filling most of a 24x24 view under a white sky."""
    return {"type": "scene",
            "sensor": {"type": "perspective", "fov": 30,
                       "to_world": mi.ScalarTransform4f().look_at([0, 0, 4.5], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 24, "height": 24}},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "ball": {"type": "sphere", "bsdf": bsdf}}


def test_albedo_of_metal_and_glass_is_their_directional_albedo(mi):
    """Revision 2: a rough metal's albedo is its Fresnel colour, clear glass's 1, both within [0, 1]
    (Mitsuba's eval_diffuse_reflectance, revision 1, gave a metal seen head-on its glossy peak: up to 37)."""
    from kpcn.integrator import ALBEDO_REVISION

    metal = render_frame(_sphere_scene(mi, {"type": "roughconductor", "material": "Al", "alpha": 0.15}), spp=16, seed=1)
    glass = render_frame(_sphere_scene(mi, {"type": "dielectric", "int_ior": 1.5}), spp=16, seed=1)
    diffuse = render_frame(_sphere_scene(mi, {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.3}}), spp=4)
    assert metal.meta["albedoRevision"] == ALBEDO_REVISION
    # (a rough metal loses some energy to masking near grazing angles: 0.6, not 0.9, at its rim)
    for f, low, high in ((metal, 0.6, 1.0), (glass, 0.97, 1.0), (diffuse, 0.3 - 1e-6, 0.3 + 1e-6)):
        inner = f["depth"][..., 0] > 0
        for axis in (0, 1):  # pixels whose four neighbours hit too (silhouettes average hits with the sky)
            inner &= np.roll(inner, 1, axis) & np.roll(inner, -1, axis)
        a = f["albedo"][inner]
        assert inner.sum() > 100 and low <= a.min() and a.max() <= high, (a.min(), a.max())
    # seen head-on, aluminium's Fresnel reflectance: about 0.9
    centre = metal["albedo"][10:14, 10:14]
    assert np.all((centre > 0.85) & (centre < 0.95)), centre


@pytest.mark.parametrize("scene", ["test:glossy", "test:glass"])
def test_albedo_only_render_writes_what_a_full_render_writes(mi, scene):
    """The same seed and role: the albedo pass gives the full render's albedo, normal, depth and denoising guides
    bit for bit (in test:glass, behind the glass's delta bounces too)."""
    full = render_frame(scene, spp=8, seed=4, role=7, resolution=(24, 24))
    alone = render_frame(scene, spp=8, seed=4, role=7, resolution=(24, 24), albedo_only=True)
    for name in ("albedo", "albedoVariance", "normal", "normalVariance", "depth", "denoisingAlbedo",
                 "denoisingNormal"):
        assert np.array_equal(full[name], alone[name]), name
    assert full["albedo"].max() <= 1 and alone["color"].max() == 0 and full["color"].max() > 0
    other = render_frame(scene, spp=8, seed=4, role=8, resolution=(24, 24), albedo_only=True)
    assert not np.array_equal(other["albedo"], alone["albedo"])  # another role, other samples


def _pane_scene(mi, pane: dict) -> dict:
    """A red wall seen head-on (normal +z), its left half behind a pane tilted 45 degrees about y."""
    T = mi.ScalarTransform4f
    return {"type": "scene",
            "sensor": {"type": "perspective", "fov": 40, "to_world": T().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 32, "height": 32}},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.5}},
            "wall": {"type": "rectangle", "to_world": T().scale(5.0),
                     "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.2, 0.1]}}},
            "pane": {"type": "rectangle", "to_world": T().translate([-0.7, 0, 2]).rotate([0, 1, 0], 45).scale(
                [1, 3, 1]), "bsdf": pane}}


@pytest.mark.parametrize("pane", [{"type": "thindielectric"}, {"type": "dielectric"}])
def test_denoising_guides_behind_glass_are_what_it_shows(mi, pane):
    """Behind a delta surface the denoising albedo and normal are those of the surface the delta bounces reach,
    times their weights, 0 where they escape; ``albedo`` and ``normal`` stay the pane's own (its directional
    albedo, about 1, and its tilted normal), and elsewhere the two pairs are the same."""
    f = render_frame(_pane_scene(mi, pane), spp=32, seed=3)
    wall = np.array([0.8, 0.2, 0.1], np.float32)
    behind, bare = f["denoisingAlbedo"][4:28, 2:10], f["denoisingAlbedo"][4:28, 24:30]
    np.testing.assert_allclose(bare, np.broadcast_to(wall, bare.shape), rtol=1e-6)
    for name in ("albedo", "normal"):
        np.testing.assert_array_equal(f[name][4:28, 24:30], f["denoising" + name.title()][4:28, 24:30])
    # each sample sees the wall through the pane (weight 1) or the sky by reflection (0): the wall's colour, scaled
    share = behind / wall
    np.testing.assert_allclose(share, share[..., :1].repeat(3, -1), rtol=1e-4)
    assert 0.75 < share.mean() < 0.98 and share.min() > 0.4, (share.mean(), share.min())
    n = f["denoisingNormal"][4:28, 2:10]
    # the wall's normal (0, 0, 1), not the pane's (±0.71, 0, 0.71), in the same share
    assert np.abs(n[..., :2]).max() < 1e-5, np.abs(n[..., :2]).max()
    np.testing.assert_allclose(n[..., 2], share[..., 0], atol=1e-5)
    # the first-hit guides: the pane's
    assert f["albedo"][4:28, 2:10].min() > 0.97 and np.abs(f["normal"][4:28, 2:10, 0]).min() > 0.65
    # OIDN is given the denoising guides
    from kpcn.baselines import oidn_guides

    albedo, normal = oidn_guides(f)
    assert albedo is f["denoisingAlbedo"] and normal is f["denoisingNormal"]


def test_cli_writes_contract_exr(mi, tmp_path):
    out = tmp_path / "n.exr"
    r = subprocess.run([sys.executable, "-m", "kpcn.render", "frame", "test:glass", "--spp", "4", "--out", str(out),
                        "--resolution", "16", "16", "--ref-spp", "16"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    f = read_exr(out, require=("color", "diffuse", "specular", "albedo", "normal", "depth", "colorVariance"))
    assert f.meta["spp"] == 4 and f.meta["scene"] == "test:glass" and f.meta["renderTimeSeconds"] > 0
    assert read_exr(tmp_path / "n_ref.exr").meta["spp"] == 16


def test_dataset_manifest_and_resume(tiny_dataset):
    manifest = json.loads((tiny_dataset / "manifest.json").read_text())
    assert len(manifest["scenes"]) == 3 and manifest["ref_spp"] == 128
    first = manifest["scenes"][0]
    paths = [tiny_dataset / p for p in first["inputs"].values()] + [tiny_dataset / first["reference"]]
    assert all(p.exists() for p in paths)
    mtimes = [p.stat().st_mtime_ns for p in paths]
    render_dataset(tiny_dataset, n_scenes=3, spp_list=(4, 8), ref_spp=128, resolution=(48, 48), first_seed=100, progress=False)
    assert [p.stat().st_mtime_ns for p in paths] == mtimes, "existing frames must not be rendered again"
    inp, ref = read_exr(paths[0]), read_exr(paths[-1])
    assert inp.meta["spp"] == 4 and ref.meta["spp"] == 128
    assert not np.array_equal(inp["color"], ref["color"])


def test_clear_error_without_llvm(monkeypatch):
    import drjit as dr

    from kpcn import render as R

    monkeypatch.setattr(dr.detail, "llvm_version", lambda: (16, 0, 6))
    with pytest.raises(R.RendererUnavailable, match="libllvm19"):
        R.ensure_variant()


def test_variant_choice_is_checked(monkeypatch):
    from kpcn.render.scene import RendererUnavailable, chosen_variant

    monkeypatch.delenv("KPCN_MITSUBA_VARIANT", raising=False)
    assert chosen_variant() == "llvm_ad_rgb"
    monkeypatch.setenv("KPCN_MITSUBA_VARIANT", "cuda_ad_rgb")
    assert chosen_variant() == "cuda_ad_rgb"
    monkeypatch.setenv("KPCN_MITSUBA_VARIANT", "scalar_spectral")
    with pytest.raises(RendererUnavailable, match="KPCN_MITSUBA_VARIANT.*llvm_ad_rgb, cuda_ad_rgb"):
        chosen_variant()


def test_extended_frame_is_the_longer_render(mi):
    """A frame given more samples by :func:`extend_frame` (its passes kept, the following ones added) is the frame
    rendered with that many samples directly, variances included."""
    from kpcn.render import extend_frame

    kw = dict(resolution=(16, 16), role=1, pass_spp=2)
    short = render_frame("test:glossy", 4, 3, **kw)
    direct = render_frame("test:glossy", 8, 3, **kw)
    longer = extend_frame(short, "test:glossy", 8, 3, **kw)
    assert longer.spp == 8 and sorted(longer.layers) == sorted(direct.layers)
    for name in direct.layers:
        np.testing.assert_allclose(longer[name], direct[name], rtol=1e-4, atol=1e-6, err_msg=name)
    assert not np.allclose(short["color"], direct["color"])  # the added passes are new samples
    with pytest.raises(ValueError, match="not at least 2 above"):
        extend_frame(short, "test:glossy", 5, 3, **kw)
    # a frame rendered before the denoising guides is extended without them, as its header says
    from kpcn.io import Frame

    old = Frame({k: v for k, v in short.layers.items() if not k.startswith("denoising")},
                {k: v for k, v in short.meta.items() if k != "denoisingRevision"})
    older = extend_frame(old, "test:glossy", 8, 3, **kw)
    assert sorted(older.layers) == sorted(old.layers) and "denoisingRevision" not in older.meta
    np.testing.assert_allclose(older["color"], direct["color"], rtol=1e-4, atol=1e-6)


def test_merged_frames_are_the_union_of_their_samples():
    """Pure maths: two frames' means and variances of the mean merge into those of all their samples."""
    from kpcn.io import Frame
    from kpcn.render import merge_frames

    rng = np.random.default_rng(0)
    samples = rng.lognormal(0.0, 1.5, size=(12, 4, 5, 3))  # 12 samples per pixel, heavy-tailed

    def frame(s):
        n = len(s)
        return Frame({"color": s.mean(0).astype(np.float32), "colorVariance": (s.var(0, ddof=1) / n).astype(np.float32),
                      "depth": np.full((4, 5, 1), float(n), np.float32)}, {"spp": n, "renderTimeSeconds": 1.0})

    merged, whole = merge_frames(frame(samples[:7]), frame(samples[7:])), frame(samples)
    assert merged.spp == 12 and merged.meta["renderTimeSeconds"] == 2.0
    np.testing.assert_allclose(merged["color"], whole["color"], rtol=1e-5)
    np.testing.assert_allclose(merged["colorVariance"], whole["colorVariance"], rtol=1e-4)
    np.testing.assert_allclose(merged["depth"], (7 * 7 + 5 * 5) / 12)  # a layer without variance: the weighted mean
    with pytest.raises(ValueError, match="different layers"):
        merge_frames(frame(samples[:7]), Frame({"color": samples[0].astype(np.float32)}, {"spp": 1}))


def test_frames_whose_spp_varies_per_pixel_merge_pixel_by_pixel():
    """Pure maths: frames of samples whose count varies per pixel (a sample-count layer, as an adaptive sampler
    writes, here made by mix_frames) merge into the mean and variance of all each pixel's samples."""
    from kpcn.io import SAMPLE_COUNT, Frame
    from kpcn.render import merge_frames, mix_frames

    rng = np.random.default_rng(1)
    samples = rng.lognormal(0.0, 1.5, size=(40, 4, 5, 3))
    mask = rng.random((4, 5)) < 0.5

    def frame(s):
        n = len(s)
        return Frame({"color": s.mean(0).astype(np.float32),
                      "colorVariance": (s.var(0, ddof=1) / n).astype(np.float32)}, {"spp": n, "renderTimeSeconds": 1.0})

    # first 4 samples where mask, 16 elsewhere; then 6 more where mask, 20 more elsewhere
    first = mix_frames(frame(samples[:4]), frame(samples[:16]), mask)
    assert np.array_equal(first.sample_count(), np.where(mask, 4.0, 16.0)) and SAMPLE_COUNT in first
    assert first.spp == round(float(np.where(mask, 4, 16).mean())) and "renderTimeSeconds" not in first.meta
    more = mix_frames(frame(samples[4:10]), frame(samples[16:36]), mask)
    both = merge_frames(first, more)
    assert np.array_equal(both.sample_count(), np.where(mask, 10.0, 36.0))
    for whole, where in ((frame(samples[:10]), mask), (frame(samples[:36]), ~mask)):
        for name in ("color", "colorVariance"):
            np.testing.assert_allclose(both[name][where], whole[name][where], rtol=1e-4, err_msg=name)
    # a uniform frame merges with a varying one: its spp is every pixel's count
    plus = merge_frames(first, frame(samples[36:]))
    assert np.array_equal(plus.sample_count(), np.where(mask, 8.0, 20.0))
    with pytest.raises(ValueError, match="mask is"):
        mix_frames(frame(samples[:4]), frame(samples[:16]), mask[:3])
    with pytest.raises(ValueError, match="neither a sampleCount layer nor an spp"):
        merge_frames(Frame(dict(frame(samples[:4]).layers)), frame(samples[:4]))


def test_a_sample_map_renders_each_pixel_with_its_own_samples(mi):
    """render_sample_map (an adaptive sampler's request): each pixel of a map of 4, 8 and 12 samples is that pixel of
    the uniform render with the same passes, mean and variances, and the frame says its counts."""
    from kpcn.io import SAMPLE_COUNT
    from kpcn.render import render_sample_map

    res = (16, 12)
    counts = np.full((12, 16), 4)
    counts[:, 8:] = 8
    counts[:3] = 12
    mapped = render_sample_map("test:glossy", counts, 3, resolution=res, pass_spp=4)
    assert np.array_equal(mapped[SAMPLE_COUNT][..., 0], counts) and mapped.spp == round(counts.mean())
    for c in (4, 8, 12):
        whole = render_frame("test:glossy", c, 3, resolution=res, pass_spp=4)
        at = counts == c
        assert sorted(set(mapped.layers) - {SAMPLE_COUNT}) == sorted(whole.layers)
        for name in whole.layers:
            np.testing.assert_allclose(mapped[name][at], whole[name][at], rtol=1e-5, atol=1e-7, err_msg=f"{c} {name}")
    assert not np.allclose(mapped["color"][counts == 4], render_frame("test:glossy", 4, 4, resolution=res)["color"]
                           [counts == 4])  # another seed: other samples
    with pytest.raises(ValueError, match="integers >= 2"):
        render_sample_map("test:glossy", np.ones((12, 16)), 3, resolution=res)
    with pytest.raises(ValueError, match="the film 12x16"):
        render_sample_map("test:glossy", np.full((16, 12), 4), 3, resolution=res)
