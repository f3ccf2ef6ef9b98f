"""Scene files as Mitsuba reads them: includes, $parameters, cameras, media, errors — tiny real renders."""
import os
import stat
import subprocess
import sys

import numpy as np
import pytest

from kpcn.io import read_exr
from kpcn.render import SceneError, load_scene, render_frame

MAIN = """<scene version="3.0.0">
  <default name="res" value="16"/>
  <default name="spp" value="4"/>
  <default name="albedo" value="0.5"/>
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  <include filename="parts/sensor.xml"/>
  <include filename="parts/objects.xml"/>
</scene>
"""
SENSOR = """<scene version="3.0.0">
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="stratified"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/>
      <rfilter type="gaussian"/></film>
  </sensor>
</scene>
"""
OBJECTS = """<scene version="3.0.0">
  <emitter type="constant"><rgb name="radiance" value="0.8"/></emitter>
  <shape type="sphere"><point name="center" x="-0.6" y="0" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf></shape>
  <shape type="sphere"><point name="center" x="0.6" y="0" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="$albedo"/></bsdf></shape>
  <shape type="obj"><string name="filename" value="meshes/quad.obj"/>
    <transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/><translate y="-0.5"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.4"/></bsdf></shape>
</scene>
"""
QUAD = "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3\nf 1 3 4\n"


def write_chain(folder):
    """main.xml including parts/sensor.xml and parts/objects.xml (which loads parts/meshes/quad.obj)."""
    (folder / "parts").mkdir(parents=True)
    (folder / "main.xml").write_text(MAIN)
    (folder / "parts" / "sensor.xml").write_text(SENSOR)
    (folder / "parts" / "objects.xml").write_text(OBJECTS)
    (folder / "meshes").mkdir()
    (folder / "meshes" / "quad.obj").write_text(QUAD)  # mesh paths resolve from the main file's folder
    return folder / "main.xml"


@pytest.fixture
def chain(tmp_path):
    return write_chain(tmp_path)


def test_include_chain_renders_split_with_overrides_logged(mi, chain, caplog):
    caplog.set_level("INFO", logger="kpcn.render")
    f = render_frame(chain, spp=4, seed=1)
    assert f["color"].shape == (16, 16, 3) and f.meta["scene"] == "main"
    assert f["diffuse"].sum() > 0 and f["specular"].sum() > 0
    np.testing.assert_allclose(f["diffuse"] + f["specular"], f["color"], rtol=0, atol=1e-5)
    expected = ["integrator path -> kpcn_split", "film rfilter gaussian -> box", "sampler stratified -> independent"]
    for note in expected:
        assert any(note in r.getMessage() for r in caplog.records), note
    _, name, notes = load_scene(chain, (24, 16))
    assert name == "main" and all(n in notes for n in expected) and "film size 16x16 -> 24x16" in notes
    assert render_frame(chain, spp=2, resolution=(24, 16))["color"].shape == (16, 24, 3)


def test_dollar_parameters_pass_through(mi, chain):
    assert render_frame(chain, spp=2, params={"res": 8})["color"].shape == (8, 8, 3)
    dark = render_frame(chain, spp=4, seed=2, params={"albedo": 0.1})
    bright = render_frame(chain, spp=4, seed=2, params={"albedo": "0.9"})
    # the diffuse sphere's albedo (first-hit feature) is the parameter; more light leaves it
    assert np.isclose(dark["albedo"], 0.1, atol=1e-4).any() and not np.isclose(dark["albedo"], 0.9, atol=1e-4).any()
    assert np.isclose(bright["albedo"], 0.9, atol=1e-4).any()
    assert bright["diffuse"].sum() > 1.2 * dark["diffuse"].sum()
    with pytest.raises(SceneError, match=r"unused parameters.*\$nosuch"):
        load_scene(chain, params={"nosuch": 1})


def test_cli_frame_with_params(mi, chain, tmp_path):
    out = tmp_path / "n.exr"
    r = subprocess.run([sys.executable, "-m", "kpcn.render", "frame", str(chain), "--spp", "4", "--out", str(out),
                        "--param", "res=12", "--param", "albedo=0.3"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    f = read_exr(out, require=("color", "diffuse", "specular"))
    assert f["color"].shape == (12, 12, 3) and f.meta["scene"] == "main"
    np.testing.assert_allclose(f["diffuse"] + f["specular"], f["color"], rtol=0, atol=1e-5)
    assert "rfilter gaussian -> box" in r.stderr and "integrator path -> kpcn_split" in r.stderr


def test_cli_scene_error_is_one_line(mi, tmp_path, capsys):
    from kpcn.render.cli import main

    missing = tmp_path / "nothere.xml"
    assert main(["frame", str(missing), "--out", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: scene file not found: {missing}"


@pytest.fixture
def read_only_chain(tmp_path):
    main = write_chain(tmp_path / "ro")
    folders = [p for p in (tmp_path / "ro").rglob("*") if p.is_dir()] + [tmp_path / "ro"]
    for p in folders:
        p.chmod(0o555)
    try:
        yield main
    finally:
        for p in folders:
            p.chmod(0o755)


def test_read_only_folder_renders_and_stays_untouched(mi, read_only_chain):
    folder = read_only_chain.parent
    assert not os.stat(folder).st_mode & stat.S_IWUSR

    def snapshot():  # (as root chmod does not stop writes: a file written and removed still changes mtimes)
        return sorted((str(p), p.stat().st_mtime_ns) for p in [folder, *folder.rglob("*")])

    before = snapshot()
    f = render_frame(read_only_chain, spp=2)
    assert f["color"].mean() > 0
    assert snapshot() == before


CAMERA = {
    "perspective": '<sensor type="perspective"><float name="fov" value="35"/>'
                   '<float name="principal_point_offset_x" value="0.1"/>',
    "thinlens": '<sensor type="thinlens"><float name="fov" value="35"/>'
                '<float name="aperture_radius" value="0.15"/><float name="focus_distance" value="3"/>',
    "orthographic": '<sensor type="orthographic">',
}


def camera_scene(kind, film="<rfilter type=\"box\"/>", extra=""):
    scale = '<scale x="1.5" y="1.5"/>' if kind == "orthographic" else ""
    return f"""<scene version="3.0.0">
  {CAMERA[kind]}
    <transform name="to_world">{scale}<lookat origin="0, 1, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"/>
    <film type="hdrfilm"><integer name="width" value="20"/><integer name="height" value="14"/>
      <string name="pixel_format" value="rgb"/><string name="component_format" value="float32"/>{film}</film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <shape type="sphere" id="ball"><point name="center" x="-0.6" y="0" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="roughconductor"/>{extra}</shape>
  <shape type="sphere"><point name="center" x="0.6" y="0" z="-1"/><float name="radius" value="0.5"/>
    <bsdf type="diffuse"/></shape>
</scene>
"""


@pytest.mark.parametrize("kind", ["perspective", "thinlens", "orthographic"])
def test_cameras_keep_their_view(mi, tmp_path, kind):
    xml = tmp_path / f"{kind}.xml"
    xml.write_text(camera_scene(kind))
    f = render_frame(xml, spp=4, resolution=(16, 12))
    assert f["color"].shape == (12, 16, 3) and f["color"].mean() > 0 and f["diffuse"].sum() > 0
    # the scene already has kpcn's film: the overridden sensor renders exactly what the original one does
    path = mi.load_dict({"type": "path", "max_depth": 6})
    scene, _, notes = load_scene(xml)
    assert notes == []
    ours = np.array(mi.render(scene, integrator=path, spp=8, seed=5))
    original = np.array(mi.render(mi.load_file(str(xml)), integrator=path, spp=8, seed=5))
    assert ours.shape == (14, 20, 3)
    np.testing.assert_array_equal(ours, original)


def test_crop_window_is_kept_without_resolution_and_dropped_with_one(mi, tmp_path):
    xml = tmp_path / "crop.xml"
    crop = '<integer name="crop_offset_x" value="4"/><integer name="crop_width" value="8"/><rfilter type="box"/>'
    xml.write_text(camera_scene("perspective", film=crop))
    scene, _, notes = load_scene(xml)
    assert tuple(scene.sensors()[0].film().crop_size()) == (8, 14) and notes == []
    scene, _, notes = load_scene(xml, (16, 16))
    assert tuple(scene.sensors()[0].film().crop_size()) == (16, 16)
    assert any("crop" in n for n in notes)


MEDIUM = '<medium type="homogeneous" id="fog"><float name="sigma_t" value="0.5"/></medium>'


@pytest.mark.parametrize("where", ["shape interior", "sensor", "nested exterior"])
def test_participating_media_are_refused(mi, tmp_path, where):
    xml = tmp_path / "fog.xml"
    if where == "shape interior":
        text = camera_scene("perspective", extra='<ref name="interior" id="fog"/>').replace(
            "<scene version=\"3.0.0\">", f"<scene version=\"3.0.0\">{MEDIUM}")
        owner = "shape 'ball' (sphere)"
    elif where == "sensor":
        text = camera_scene("perspective").replace("<sensor type=\"perspective\">",
                                                   f"{MEDIUM}<sensor type=\"perspective\"><ref id=\"fog\"/>")
        owner = "sensor (perspective)"
    else:
        text = camera_scene("perspective", extra=MEDIUM.replace("<medium ", '<medium name="exterior" '))
        owner = "shape 'ball' (sphere)"
    xml.write_text(text)
    with pytest.raises(SceneError) as err:
        load_scene(xml)
    msg = str(err.value)
    assert "medium 'fog' (homogeneous)" in msg and owner in msg and str(xml) in msg and "\n" not in msg


def test_dict_scene_with_medium_object_is_refused(mi):
    medium = mi.load_dict({"type": "homogeneous", "sigma_t": 0.5})
    scene = {"type": "scene", "kpcn_name": "foggy",
             "cam": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
             "ball": {"type": "sphere", "interior": medium}}
    with pytest.raises(SceneError, match=r"foggy: participating medium .*HomogeneousMedium.*shape 'ball'"):
        load_scene(scene)


def test_non_camera_sensors_and_sensorless_scenes_are_refused(mi, tmp_path):
    xml = tmp_path / "meter.xml"
    xml.write_text('<scene version="3.0.0"><sensor type="radiancemeter"/><shape type="sphere"/></scene>')
    with pytest.raises(SceneError, match=r"meter\.xml: cannot render sensor \(radiancemeter\)"):
        load_scene(xml)
    xml.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    with pytest.raises(SceneError, match="no sensor"):
        load_scene(xml)


@pytest.mark.parametrize("case", ["missing file", "broken xml", "missing mesh", "missing include"])
def test_broken_scenes_give_one_line_scene_error_naming_the_file(mi, tmp_path, case):
    xml = tmp_path / "user_scene.xml"
    if case == "broken xml":
        xml.write_text('<scene version="3.0.0">\n  <shape type="sphere">\n</scene>\n')
    elif case == "missing mesh":
        xml.write_text(camera_scene("perspective").replace(
            "</scene>", '<shape type="ply"><string name="filename" value="meshes/gone.ply"/></shape></scene>'))
    elif case == "missing include":
        xml.write_text('<scene version="3.0.0"><include filename="parts/gone.xml"/></scene>')
    with pytest.raises(SceneError) as err:
        load_scene(xml)
    msg = str(err.value)
    assert str(xml) in msg and "\n" not in msg
    assert {"missing file": "not found", "broken xml": "line 3", "missing mesh": "gone.ply",
            "missing include": "gone.xml"}[case] in msg
    assert sorted(p.name for p in tmp_path.iterdir()) == ([] if case == "missing file" else ["user_scene.xml"])
