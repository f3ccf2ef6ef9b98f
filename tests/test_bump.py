"""Normal revisions 2 and 3: the ``normal`` layer holds the normal a bump- or normal-mapped BSDF shades with
(kpcn.bump)."""
import numpy as np
import pytest

from kpcn.integrator import NORMAL_REVISION
from kpcn.io import read_exr, write_exr
from kpcn.render import render_frame


def _heights(n=32, seed=0):
    return np.random.default_rng(seed).random((n, n, 1)).astype(np.float32)


def _bumpy(mi, scale=0.05, twosided=True, seed=0):
    bump = {"type": "bumpmap", "arbitrary": {"type": "bitmap", "bitmap": mi.Bitmap(_heights(seed=seed)), "raw": True},
            "scale": scale, "bsdf": {"type": "diffuse"}}
    return {"type": "twosided", "material": bump} if twosided else bump


def test_bumped_normal_is_the_one_the_bsdf_shades_with(mi):
    """For a diffuse BSDF under a bump map, f(wo) = R/pi * max(0, n·wo) with n the normal it shades with:
    the normal kpcn.bump computes predicts Mitsuba's own evaluation; the unmapped normal does not; hits on
    a BSDF without a bump map keep their normal exactly."""
    import drjit as dr

    from kpcn.bump import find_bump_maps, mapped_normal

    scene = mi.load_dict({"type": "scene", "plane": {"type": "rectangle", "bsdf": _bumpy(mi)},
                          "ball": {"type": "sphere", "center": [-3, 0, 0], "bsdf": {"type": "diffuse"}}})
    maps = find_bump_maps(scene)
    assert len(maps) == 1 and maps[0].scale == pytest.approx(0.05)
    rng = np.random.default_rng(1)
    n_rays = 2000
    ray = mi.Ray3f(mi.Point3f(rng.uniform(-4, 1, n_rays), rng.uniform(-1, 1, n_rays), np.full(n_rays, 5.0)),
                   mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=False)
    hit = si.is_valid()
    bsdf = si.bsdf(ray)
    flat = dr.select(hit, si.sh_frame.n, mi.Vector3f(0.0))
    bumped = mapped_normal(maps, si, bsdf, flat, hit)
    x, h = np.array(ray.o.x), np.array(hit)
    on_plane, on_ball = h & (np.abs(x) < 1), h & (x < -2)
    assert on_plane.sum() > 500 and on_ball.sum() > 300
    for wo in [(0.3, 0.2, 0.93), (-0.4, 0.1, 0.91), (0.1, -0.6, 0.8)]:
        wo_local = dr.normalize(mi.Vector3f(*wo))
        f = np.array(bsdf.eval(mi.BSDFContext(), si, wo_local, hit).x)
        wo_world = si.to_world(wo_local)
        for normal, err_max in ((bumped, 2e-3), (flat, None)):
            pred = np.array(0.5 / np.pi * dr.maximum(dr.dot(normal, wo_world), 0.0))
            err = np.abs(f - pred)
            if err_max is not None:
                assert err[on_plane].max() < err_max
                assert err[on_ball].max() < 1e-6
            else:  # the bump map matters on these rays: the unmapped normal mispredicts
                assert err[on_plane].max() > 20 * 2e-3
    b, u = np.array(bumped), np.array(flat)
    assert np.array_equal(b[:, on_ball], u[:, on_ball])
    assert np.abs(b[:, on_plane] - u[:, on_plane]).max() > 0.1


def test_normal_mapped_normal_is_the_one_the_bsdf_shades_with(mi):
    """For a diffuse BSDF under a normal map, f(wo) = R/pi * n·wo: three evaluations give the normal the BSDF
    shades with, and kpcn.bump's agrees with it to a fraction of a degree on every hit (the unmapped normal
    is tens of degrees off); the map's texture is an sRGB bitmap, so its own colour handling must be used."""
    from kpcn.bump import find_bump_maps, mapped_normal

    rng = np.random.default_rng(4)
    texels = np.clip(0.5 + 0.3 * rng.standard_normal((16, 16, 3)), 0, 1).astype(np.float32)
    texels[..., 2] = 0.9
    bsdf = {"type": "twosided", "material": {"type": "normalmap", "bsdf": {"type": "diffuse"},
                                             "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(texels),
                                                           "raw": False}}}
    scene = mi.load_dict({"type": "scene", "plane": {"type": "rectangle", "bsdf": bsdf}})
    maps = find_bump_maps(scene)
    assert len(maps) == 1 and maps[0].kind == "normal"
    n_rays = 500
    ray = mi.Ray3f(mi.Point3f(rng.uniform(-0.9, 0.9, n_rays), rng.uniform(-0.9, 0.9, n_rays), np.full(n_rays, 5.0)),
                   mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=False)
    hit = si.is_valid()
    assert np.array(hit).all()
    ptr = si.bsdf(ray)
    flat = mi.Vector3f(si.sh_frame.n)
    mapped = np.array(mapped_normal(maps, si, ptr, flat, hit))
    wos = np.array([[0.2, 0.1, 0.97], [-0.15, 0.2, 0.97], [0.05, -0.25, 0.97]])
    wos /= np.linalg.norm(wos, axis=1, keepdims=True)
    f = np.stack([np.array(ptr.eval(mi.BSDFContext(), si, mi.Vector3f(*map(float, w)), hit).x) for w in wos])
    shaded = np.linalg.solve(wos, f * np.pi / 0.5)  # local = world here: the plane's frame is the identity
    shaded /= np.linalg.norm(shaded, axis=0)
    angle = np.degrees(np.arccos(np.clip((shaded * mapped).sum(0), -1, 1)))
    assert angle.max() < 0.5
    unmapped = np.degrees(np.arccos(np.clip(shaded[2], -1, 1)))
    assert np.median(unmapped) > 10


def _plane_scene(mi, bsdf):
    return {"type": "scene",
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}}},
            "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([3, 3, 1]), "bsdf": bsdf},
            "light": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}}


def test_a_rendered_normal_layer_shows_the_bump_map(mi):
    """A real render of a plane: under a bump map its normal layer varies with the heights (and stays a unit
    vector toward the camera's side); without one it is the plane's normal everywhere."""
    flat = render_frame(_plane_scene(mi, {"type": "diffuse"}), 4, 0, (24, 24))
    bumpy = render_frame(_plane_scene(mi, _bumpy(mi, scale=0.02)), 4, 0, (24, 24))
    assert flat.meta["normalRevision"] == bumpy.meta["normalRevision"] == NORMAL_REVISION
    np.testing.assert_allclose(flat["normal"], np.broadcast_to([0, 0, 1], flat["normal"].shape), atol=1e-6)
    n = bumpy["normal"]
    assert np.abs(n[..., :2]).mean() > 0.01 and (n[..., 2] > 0).all()
    assert bumpy["normalVariance"][..., :2].mean() > 100 * flat["normalVariance"][..., :2].mean() + 1e-6


def test_a_frame_of_normal_revision_1_gets_its_normal_only(mi, tmp_path):
    """A frame written before normal revision 2 (the unmapped normal, no header key): its normal layers are
    rendered again as a fresh render writes them; every other layer is kept bit for bit."""
    from kpcn.render.albedo import outdated_first_hit, update_first_hit

    scene = _plane_scene(mi, _bumpy(mi, scale=0.02, seed=3))
    fresh = render_frame(scene, 4, 5, (24, 24), role=2)
    path = tmp_path / "old.exr"
    old_meta = {k: v for k, v in fresh.meta.items() if k != "normalRevision"}
    write_exr(path, {**fresh.layers, "normal": np.broadcast_to([0, 0, 1], fresh["normal"].shape).astype(np.float32),
                     "normalVariance": np.zeros_like(fresh["normalVariance"])}, old_meta)
    old = read_exr(path)
    assert outdated_first_hit(old) == ["normal"]
    update_first_hit(path, scene, 4, 5, role=2, which=outdated_first_hit(old), resolution=(24, 24))
    new = read_exr(path)
    assert outdated_first_hit(new) == [] and new.meta["normalRevision"] == NORMAL_REVISION
    for name in ("normal", "normalVariance"):
        np.testing.assert_array_equal(new[name], fresh[name])
    for name in ("color", "colorVariance", "albedo", "albedoVariance", "depth", "specular"):
        np.testing.assert_array_equal(new[name], old[name])
