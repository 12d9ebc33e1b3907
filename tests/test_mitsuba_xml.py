"""Mitsuba 3 scenes in and out (clscatter.scene.mitsuba_in and mitsuba_out, docs/mitsuba.md):
hand-written XML for every supported element (defaults and $name, include, ref, each
transform step, rgb and number spectra), the notes and errors, Mitsuba-style dict input,
TOML -> XML -> TOML round trips of the built-in scenes, ``clscatter convert`` both ways
through the command line, and, where the optional ``mitsuba`` package is installed,
Mitsuba's own reading of the XML written here."""
from __future__ import annotations

import copy
import logging
import math
from pathlib import Path

import numpy as np
import pytest

import clscatter
from clscatter.cli import main
from clscatter.errors import SceneError
from clscatter.scene import BUILTIN, load_scene, mitsuba_out, scene_from_dict
from clscatter.scene.mitsuba_in import (
    DISK_MESH,
    Transform,
    from_mitsuba,
    parse_xml,
    read_xml,
)

SENSOR = """
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 1, 5" target="0, 1, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film>
    <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
  </sensor>"""
POINT = """
  <emitter type="point"><point name="position" value="0, 3, 0"/><float name="intensity" value="5"/></emitter>"""
# a tetrahedron, outward-facing
TETRA = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def _xml(body: str, sensor: str = SENSOR, light: str = POINT, version: str = "3.0.0") -> str:
    return f'<scene version="{version}">{sensor}{light}{body}\n</scene>\n'


def _read(body: str, **kw) -> tuple[dict, list[str]]:
    return from_mitsuba(parse_xml(_xml(body, **kw)))


def _load(tmp_path: Path, body: str, **kw) -> tuple[object, list[str]]:
    """Write the scene file, read it and validate it (as ``clscatter render`` does)."""
    path = tmp_path / "scene.xml"
    path.write_text(_xml(body, **kw))
    data, notes = read_xml(path)
    return scene_from_dict(data, tmp_path, str(path)), notes


def _run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


# ---- the file: defaults, parameters, include, ref, transforms, spectra ---------------------

def test_defaults_and_parameters():
    body = """
  <default name="w" value="64"/>
  <default name="albedo" value="0.25"/>
  <shape type="rectangle"><bsdf type="diffuse"><float name="reflectance" value="$albedo"/></bsdf></shape>"""
    sensor = SENSOR.replace('name="width" value="32"', 'name="width" value="$w"')
    data, _ = from_mitsuba(parse_xml(_xml(body, sensor=sensor)))
    assert data["camera"]["resolution"] == [64, 24]
    assert data["objects"][0]["material"] == {"type": "diffuse", "albedo": 0.25}
    # a caller's value wins over the default
    data, _ = from_mitsuba(parse_xml(_xml(body, sensor=sensor), params={"w": 100}))
    assert data["camera"]["resolution"] == [100, 24]
    with pytest.raises(SceneError, match=r"\$nothere has no value"):
        parse_xml(_xml('<shape type="sphere"><float name="radius" value="$nothere"/></shape>'))


def test_include_and_ref(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "materials.xml").write_text("""<scene version="3.0.0">
  <default name="grey" value="0.3"/>
  <bsdf type="twosided" id="matte"><bsdf type="diffuse"><float name="reflectance" value="$grey"/></bsdf></bsdf>
  <shape type="obj"><string name="filename" value="tetra.obj"/><ref id="matte"/></shape>
</scene>""")
    (tmp_path / "parts" / "tetra.obj").write_text(TETRA)
    scene, notes = _load(tmp_path, """
  <include filename="parts/materials.xml"/>
  <shape type="sphere"><float name="radius" value="0.5"/><ref id="matte" name="bsdf"/></shape>""")
    assert notes == []
    assert [o.material.name for o in scene.objects] == ["matte", "matte"]
    np.testing.assert_allclose(scene.materials["matte"].albedo, 0.3)
    # the mesh named in the included file is found beside that file
    assert scene.objects[0].shape == "mesh" and len(scene.objects[0].faces) == 4
    with pytest.raises(SceneError, match="reference to id 'nothing'"):
        _read('<shape type="sphere"><ref id="nothing"/></shape>')


@pytest.mark.parametrize("steps, expected", [
    ('<translate x="1" y="2" z="3"/>', np.array([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])),
    ('<translate value="1 2 3"/>', np.array([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])),
    ('<scale value="2"/>', np.diag([2.0, 2.0, 2.0, 1.0])),
    ('<scale x="2" z="3"/>', np.diag([2.0, 1.0, 3.0, 1.0])),
    ('<rotate y="1" angle="90"/>', np.array([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]])),
    ('<rotate value="0, 0, 1" angle="90"/>', np.array([[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
    ('<matrix value="1 0 0 4  0 2 0 5  0 0 3 6  0 0 0 1"/>',
     np.array([[1, 0, 0, 4], [0, 2, 0, 5], [0, 0, 3, 6], [0, 0, 0, 1]])),
    ('<matrix value="0 -1 0  1 0 0  0 0 1"/>', np.array([[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
    # first written, first applied: scale by 2, then move by 1 along x
    ('<scale value="2"/><translate x="1"/>', np.array([[2, 0, 0, 1], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]])),
    # Mitsuba's look_at: columns left = up x dir, up, dir, origin
    ('<lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/>',
     np.array([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 5], [0, 0, 0, 1]])),
])
def test_transform_steps(steps, expected):
    tree = parse_xml(_xml(f'<shape type="cube" id="c"><transform name="to_world">{steps}</transform></shape>'))
    np.testing.assert_allclose(tree["c"]["to_world"].matrix, expected, atol=1e-12)


def test_spectra_rgb_and_numbers():
    """rgb (three values or one) and plain numbers carry over unchanged (linear); a
    wavelength-sampled spectrum is approximated by its mean, a texture by the default,
    each with one note."""
    data, notes = _read("""
  <shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="0.1, 0.2, 0.3"/></bsdf></shape>
  <shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="0.4"/></bsdf></shape>
  <shape type="sphere"><bsdf type="diffuse"><float name="reflectance" value="0.7"/></bsdf></shape>
  <shape type="sphere"><bsdf type="diffuse"><spectrum name="reflectance" value="0.6"/></bsdf></shape>
  <shape type="sphere" id="sampled"><bsdf type="diffuse"><spectrum name="reflectance" value="400:0.2, 500:0.4, 600:0.9"/></bsdf></shape>
  <shape type="sphere" id="textured"><bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="wood.png"/></texture></bsdf></shape>""")
    albedos = [o["material"]["albedo"] for o in data["objects"]]
    assert albedos[:4] == [[0.1, 0.2, 0.3], 0.4, 0.7, 0.6]
    assert albedos[4] == pytest.approx(0.5, abs=1e-12) and albedos[5] == 0.5
    assert len(notes) == 2
    assert "sampled.bsdf" in notes[0] and "approximated by its mean 0.5" in notes[0]
    assert "textured.bsdf" in notes[1] and '"bitmap"' in notes[1] and "0.5 used" in notes[1]


# ---- elements ------------------------------------------------------------------------------

def test_sensor():
    data, notes = _read("")
    cam = data["camera"]
    assert cam["origin"] == [0.0, 1.0, 5.0] and cam["target"] == [0.0, 1.0, 0.0]
    assert cam["up"] == [0.0, 1.0, 0.0] and cam["fov"] == 40.0 and cam["fov_axis"] == "x"
    assert cam["resolution"] == [32, 24] and cam["spp"] == 4
    assert data["render"] == {"seed": 0} and notes == []

    def fov(params: str, w=32, h=24) -> tuple[float, str]:
        s = (f'<sensor type="perspective">{params}<film type="hdrfilm"><integer name="width" '
             f'value="{w}"/><integer name="height" value="{h}"/></film>'
             '<sampler type="stratified"><integer name="sample_count" value="16"/>'
             '<integer name="seed" value="7"/></sampler></sensor>')
        d, _ = _read("", sensor=s)
        assert d["camera"]["spp"] == 16 and d["render"]["seed"] == 7
        return d["camera"]["fov"], d["camera"]["fov_axis"]

    assert fov('<float name="fov" value="30"/><string name="fov_axis" value="y"/>') == (30.0, "y")
    assert fov('<float name="fov" value="30"/><string name="fov_axis" value="smaller"/>') == (30.0, "y")
    assert fov('<float name="fov" value="30"/><string name="fov_axis" value="larger"/>') == (30.0, "x")
    # the diagonal fov across x: tan(fx / 2) = tan(fd / 2) * w / sqrt(w^2 + h^2)
    fx, axis = fov('<float name="fov" value="50"/><string name="fov_axis" value="diagonal"/>')
    assert axis == "x" and math.tan(math.radians(fx) / 2) == pytest.approx(
        math.tan(math.radians(25)) * 32 / 40, rel=1e-12)
    # no fov: Mitsuba's 50 mm lens on a 36 x 24 mm film: x_fov 38.1848 degrees at 768 x 576
    fx, axis = fov("", 768, 576)
    assert axis == "x" and fx == pytest.approx(38.1848, abs=1e-4)

    near = SENSOR.replace('<float name="fov" value="40"/>',
                          '<float name="fov" value="40"/><float name="near_clip" value="0.5"/>')
    _, notes = _read("", sensor=near)
    assert len(notes) == 1 and "near_clip 0.5 dropped" in notes[0]


def test_shapes(tmp_path):
    (tmp_path / "tetra.obj").write_text(TETRA)
    scene, notes = _load(tmp_path, """
  <shape type="obj"><string name="filename" value="tetra.obj"/><boolean name="face_normals" value="true"/>
    <transform name="to_world"><scale value="2"/><rotate y="1" angle="30"/><translate x="1"/></transform></shape>
  <shape type="obj"><string name="filename" value="tetra.obj"/></shape>
  <shape type="sphere"><point name="center" value="0, 1, 0"/><float name="radius" value="0.5"/>
    <transform name="to_world"><scale value="2"/><translate z="1"/></transform></shape>
  <shape type="cube"><transform name="to_world"><scale x="0.5" y="1" z="2"/><translate y="3"/></transform></shape>
  <shape type="cube"><transform name="to_world"><rotate x="1" angle="45"/></transform></shape>
  <shape type="rectangle"><transform name="to_world"><scale x="3" y="2"/><rotate x="1" angle="-90"/></transform></shape>
  <shape type="disk"><transform name="to_world"><scale value="0.5"/><translate y="2"/></transform></shape>""")
    assert notes == []
    tetra, smooth, sphere, box, tilted, quad, disk = scene.objects
    # obj: M = T R S, the scene format's transform; face_normals -> flat, else smooth
    from clscatter.scene.shapes import rotation_matrix
    expected = 2.0 * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) @ rotation_matrix(
        np.array([0.0, 1.0, 0.0]), 30.0).T + [1.0, 0.0, 0.0]
    np.testing.assert_allclose(np.unique(tetra.vertices, axis=0), np.unique(expected, axis=0),
                               atol=1e-12)
    assert tetra.normals is None and smooth.normals is not None
    # sphere: world centre M(center), radius scaled
    np.testing.assert_allclose(sphere.vertices.mean(axis=0), [0.0, 2.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(sphere.vertices - [0.0, 2.0, 1.0], axis=1), 1.0,
                               rtol=1e-12)
    # cube: the box from -1 to 1 under to_world
    np.testing.assert_allclose(box.vertices.min(axis=0), [-0.5, 2.0, -2.0])
    np.testing.assert_allclose(box.vertices.max(axis=0), [0.5, 4.0, 2.0])
    np.testing.assert_allclose(tilted.vertices.max(axis=0), [1.0, math.sqrt(2), math.sqrt(2)],
                               rtol=1e-12)
    # rectangle: [-1, 1]^2 at z = 0, scaled then turned to face +y
    np.testing.assert_allclose(quad.vertices.min(axis=0), [-3.0, 0.0, -2.0], atol=1e-12)
    np.testing.assert_allclose(quad.vertices.max(axis=0), [3.0, 0.0, 2.0], atol=1e-12)
    # disk: the packaged 128-gon of radius 1, scaled to 0.5 at y = 2
    t = disk.vertices[disk.faces]
    area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
    assert area == pytest.approx(math.pi * 0.25, rel=5e-4)
    np.testing.assert_array_equal(disk.vertices[:, 2], 0.0)       # its plane z = 0
    rim = np.linalg.norm(disk.vertices[:, :2] - [0.0, 2.0], axis=1)
    assert rim.min() == 0.0 and rim.max() == pytest.approx(0.5, rel=1e-12)
    data, _ = _read('<shape type="disk"><transform name="to_world"><translate y="2"/></transform></shape>')
    assert data["objects"][0]["file"] == str(DISK_MESH)
    assert data["objects"][0]["transform"] == {"translate": [0.0, 2.0, 0.0]}
    data, _ = _read('<shape type="ply"><string name="filename" value="bunny.ply"/></shape>')
    assert data["objects"][0] == {"shape": "mesh", "file": "bunny.ply", "smooth": True,
                                  "material": {"type": "diffuse", "albedo": 0.5}}


def test_bsdfs():
    data, notes = _read("""
  <shape type="sphere" id="a"><bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.3, 0.4"/></bsdf></bsdf></shape>
  <shape type="sphere" id="b"><bsdf type="diffuse"><float name="reflectance" value="0"/></bsdf></shape>
  <shape type="sphere" id="c"><bsdf type="dielectric"/></shape>
  <shape type="sphere" id="d"><bsdf type="dielectric"><float name="int_ior" value="1.8"/><float name="ext_ior" value="1.2"/></bsdf></shape>
  <shape type="sphere" id="e"><bsdf type="dielectric"><string name="int_ior" value="water"/><string name="ext_ior" value="vacuum"/></bsdf></shape>
  <shape type="sphere" id="f"><bsdf type="conductor"><rgb name="specular_reflectance" value="0.9, 0.8, 0.7"/></bsdf></shape>
  <shape type="sphere" id="g"><bsdf type="roughconductor"><float name="alpha" value="0"/></bsdf></shape>
  <shape type="sphere" id="h"><bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.1, 0.5, 0.2"/></bsdf></shape>""")
    m = [o["material"] for o in data["objects"]]
    assert m[0] == {"type": "diffuse", "albedo": [0.2, 0.3, 0.4]}
    assert m[1] == {"type": "black"}
    assert m[2]["type"] == "dielectric" and m[2]["ior"] == pytest.approx(1.5046 / 1.000277, rel=1e-12)
    assert m[3]["ior"] == pytest.approx(1.5, rel=1e-12) and m[4]["ior"] == pytest.approx(1.333)
    assert m[5] == {"type": "mirror", "reflectance": [0.9, 0.8, 0.7]}
    assert m[6] == {"type": "mirror", "reflectance": 1.0}
    assert m[7] == {"type": "diffuse", "albedo": [0.1, 0.5, 0.2]}
    assert len(notes) == 1 and notes[0].startswith('bsdf "plastic" (h.bsdf)')
    for bad, what in (('<bsdf type="roughdielectric"/>', "roughdielectric"),
                      ('<bsdf type="thindielectric"/>', "thindielectric"),
                      ('<bsdf type="roughconductor"/>', "rough conductor")):
        with pytest.raises(SceneError, match=what):
            _read(f'<shape type="sphere">{bad}</shape>')


def test_media(tmp_path):
    """sigma_s = albedo sigma_t scale, sigma_a = (1 - albedo) sigma_t scale; the medium the
    sensor sits in is unbounded unless an axis-aligned null cube holds it; other null shapes
    hold volumes; a dielectric's interior medium is its material's interior keys."""
    fog = """<medium type="homogeneous" id="fog">
    <rgb name="sigma_t" value="0.5, 0.25, 1"/><float name="albedo" value="0.8"/><float name="scale" value="2"/>
    <phase type="hg"><float name="g" value="-0.3"/></phase></medium>"""
    sensor_in_fog = SENSOR.replace("</sensor>", '<ref id="fog"/></sensor>')
    data, notes = _read(fog + '<shape type="sphere"/>', sensor=sensor_in_fog)
    med = data["medium"]
    np.testing.assert_allclose(med["sigma_s"], [0.8, 0.4, 1.6], rtol=1e-12)
    np.testing.assert_allclose(med["sigma_a"], [0.2, 0.1, 0.4], rtol=1e-12)
    assert med["g"] == -0.3 and "bounds" not in med and notes == []

    cube = """<shape type="cube"><bsdf type="null"/><ref name="interior" id="fog"/>
    <transform name="to_world"><scale x="3" y="2" z="3"/><translate y="2"/></transform></shape>"""
    data, _ = _read(fog + cube)                      # the camera is outside: bounded
    assert data["medium"]["bounds"] == {"min": [-3.0, 0.0, -3.0], "max": [3.0, 4.0, 3.0]}
    assert data["objects"] == []

    glass = """<shape type="sphere"><float name="radius" value="0.5"/><bsdf type="dielectric">
      <float name="int_ior" value="1.5"/><float name="ext_ior" value="1"/></bsdf>
      <medium type="homogeneous" name="interior"><rgb name="sigma_t" value="0.1, 0.2, 0.4"/>
        <float name="albedo" value="0.5"/><phase type="isotropic"/></medium></shape>
    <shape type="sphere"><point name="center" value="2, 0, 0"/><bsdf type="null"/>
      <medium type="homogeneous" name="interior"><float name="sigma_t" value="3"/>
        <phase type="hg"><float name="g" value="-0.3"/></phase></medium></shape>"""
    data, notes = _read(fog + cube + glass)
    interior = data["objects"][0]["material"]
    assert interior["interior_sigma_s"] == [0.05, 0.1, 0.2]
    assert interior["interior_sigma_a"] == [0.05, 0.1, 0.2]
    assert interior["interior_g"] == 0.0            # isotropic, unlike the scene's -0.3
    vol = data["volumes"][0]
    assert vol == {"shape": "sphere", "center": [2.0, 0.0, 0.0], "radius": 1.0, "ior": 1.0,
                   "sigma_s": 2.25, "sigma_a": 0.75}       # albedo 0.75 by default
    assert notes == []                              # its g is the scene medium's
    scene = scene_from_dict(data)
    assert scene.objects[0].material.interior_g == 0.0 and scene.volumes[0].ior == 1.0

    # hg's default g is 0.8; a volume's own phase gives a note
    data, notes = _read('<shape type="sphere"><bsdf type="null"/><medium type="homogeneous" '
                        'name="interior"><phase type="hg"/></medium></shape>')
    assert data["volumes"][0]["sigma_s"] == 0.75 and "medium" not in data
    assert len(notes) == 1 and "phase g = 0.8" in notes[0]


def test_heterogeneous_medium_is_a_density_volume(tmp_path):
    """A gridvolume sigma_t: the file is the density (passed on), sigma_s and sigma_a per
    unit density are albedo scale and (1 - albedo) scale, the bounds its unit cube under
    its to_world; the scene format reads the .vol file written by mitsuba_out."""
    density = np.random.default_rng(1).random((4, 3, 2)).astype(np.float32)
    (tmp_path / "smoke.vol").write_bytes(mitsuba_out.vol_bytes(density, np.zeros(3), np.ones(3)))
    body = """<shape type="cube"><bsdf type="null"/>
    <transform name="to_world"><translate value="1, 1, 1"/></transform>
    <medium type="heterogeneous" name="interior">
      <volume type="gridvolume" name="sigma_t"><string name="filename" value="smoke.vol"/>
        <transform name="to_world"><scale value="2"/></transform></volume>
      <rgb name="albedo" value="0.9, 0.8, 0.5"/><float name="scale" value="4"/>
    </medium></shape>"""
    scene, notes = _load(tmp_path, body)
    assert notes == []
    path = tmp_path / "scene.xml"
    vol = read_xml(path)[0]["volumes"][0]
    assert vol["density"] == "smoke.vol"
    assert vol["bounds"] == {"min": [0.0, 0.0, 0.0], "max": [2.0, 2.0, 2.0]}
    np.testing.assert_allclose(vol["sigma_s"], [3.6, 3.2, 2.0], rtol=1e-12)
    np.testing.assert_allclose(vol["sigma_a"], [0.4, 0.8, 2.0], rtol=1e-12)
    v = scene.volumes[0]
    np.testing.assert_array_equal(v.density, density)
    np.testing.assert_allclose(v.grid_bounds, [[0.0] * 3, [2.0] * 3])
    # a shape other than the grid's box: the grid's box is used, with a note
    _, notes = _read(body.replace('<translate value="1, 1, 1"/>', '<scale value="3"/>'))
    assert len(notes) == 1 and "density grid's box" in notes[0]


def test_emitters():
    data, notes = _read("""
  <emitter type="point"><transform name="to_world"><translate value="1, 2, 3"/></transform>
    <rgb name="intensity" value="1, 2, 3"/></emitter>
  <emitter type="spot" id="hard"><transform name="to_world"><lookat origin="0, 3, 0" target="0, 0, 1" up="1, 0, 0"/></transform>
    <float name="intensity" value="20"/><float name="cutoff_angle" value="25"/><float name="beam_width" value="25"/></emitter>
  <emitter type="spot" id="soft"><transform name="to_world"><rotate x="1" angle="90"/><translate y="4"/></transform></emitter>
  <emitter type="directional"><vector name="direction" value="0, -1, 0"/><float name="irradiance" value="2"/></emitter>
  <emitter type="directional"><transform name="to_world"><lookat origin="0, 0, 0" target="1, -1, 0" up="0, 1, 0"/></transform></emitter>""",
                        light="")
    point, hard, soft, sun, sun2 = data["lights"]
    assert point == {"type": "point", "position": [1.0, 2.0, 3.0], "intensity": [1.0, 2.0, 3.0]}
    assert hard == {"type": "spot", "position": [0.0, 3.0, 0.0], "target": [0.0, 0.0, 1.0],
                    "intensity": 20.0, "cutoff_angle": 25.0}
    # +z turned about x by 90 degrees is -y, from (0, 4, 0); defaults 20 degrees, intensity 1
    np.testing.assert_allclose(soft["position"], [0.0, 4.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(soft["target"], [0.0, 3.0, 0.0], atol=1e-12)
    assert soft["cutoff_angle"] == 20.0 and soft["intensity"] == 1.0
    assert sun == {"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0}
    np.testing.assert_allclose(sun2["direction"], np.array([1.0, -1.0, 0.0]) / math.sqrt(2))
    assert len(notes) == 1 and notes[0].startswith('emitter "spot" (soft)')
    assert "beam_width 15 and cutoff_angle 20" in notes[0] and "hard cone" in notes[0]


@pytest.mark.parametrize("depth, max_depth, note", [
    (2, 0, None), (5, 3, "max_depth 5 also allows multiple scattering"),
    (-1, None, "max_depth -1 also allows multiple scattering")])
def test_integrator_depth(depth, max_depth, note):
    """render.max_depth = Mitsuba's max_depth - 2; more than single scattering is noted."""
    data, notes = _read(f'<integrator type="volpath"><integer name="max_depth" value="{depth}"/>'
                        '</integrator>')
    assert data["render"].get("max_depth") == max_depth
    if note is None:
        assert notes == []
    else:
        assert len(notes) == 1 and notes[0].startswith('integrator "volpath"') and note in notes[0]


def test_integrator_without_scattering_is_refused():
    with pytest.raises(SceneError, match=r'integrator "volpath".*max_depth 1 leaves no path'):
        _read('<integrator type="volpath"><integer name="max_depth" value="1"/></integrator>')


# ---- notes and errors --------------------------------------------------------------------------

def test_an_unsupported_element_gives_one_note():
    data, notes = _read("""
  <shape type="cylinder" id="pillar"><float name="radius" value="0.3"/><bsdf type="diffuse"/></shape>
  <shape type="sphere" id="ball"><bsdf type="diffuse"><float name="shininess" value="3"/></bsdf></shape>""")
    assert notes == ['shape "cylinder" (pillar): not a shape clscatter reads; dropped',
                     'bsdf "diffuse" (ball.bsdf): parameter shininess is not supported; ignored']
    assert len(data["objects"]) == 1


def test_an_area_light_beside_another_light_is_dropped_with_a_note():
    data, notes = _read('<shape type="sphere" id="bulb"><emitter type="area">'
                        '<rgb name="radiance" value="5, 5, 5"/></emitter></shape>')
    assert len(data["lights"]) == 1 and data["lights"][0]["type"] == "point"
    assert notes == [('emitter "area" (bulb.emitter): clscatter has point, spot and directional '
                      'lights only; dropped')]


@pytest.mark.parametrize("body, sensor, light, match", [
    ('<shape type="sphere" id="bulb"><emitter type="area"/></shape>', SENSOR, "",
     (r'^emitter "area" \(bulb.emitter\): clscatter has point, spot and directional lights only, '
      'and the scene has no other light$')),
    ('<shape type="sphere"/>', SENSOR, "", "^scene: no light"),
    ('<shape type="sphere" id="s"><bsdf type="roughdielectric"/></shape>', SENSOR, POINT,
     r'^bsdf "roughdielectric" \(s.bsdf\)'),
    ("", '<sensor type="orthographic"/>', POINT, '^sensor "orthographic"'),
    ('<shape type="cube"><transform name="to_world"><matrix value="1 1 0 0 1 0 0 0 1"/></transform></shape>',
     SENSOR, POINT, "shears the shape"),
])
def test_scenes_beyond_a_note_are_refused(body, sensor, light, match):
    with pytest.raises(SceneError, match=match) as err:
        _read(body, sensor=sensor, light=light)
    assert "\n" not in str(err.value)


def test_only_mitsuba_3_scenes():
    with pytest.raises(SceneError, match=r"scene version '0.6.0': only Mitsuba 3"):
        parse_xml(_xml("", version="0.6.0"))
    with pytest.raises(SceneError, match="invalid XML"):
        parse_xml("<scene version='3.0.0'><shape></scene>")


# ---- dict input and the Python API ------------------------------------------------------------

def _mitsuba_dict(to_world) -> dict:
    return {
        "type": "scene",
        "fog": {"type": "homogeneous", "sigma_t": {"type": "rgb", "value": [0.2, 0.3, 0.4]},
                "albedo": 0.5, "scale": 2.0, "phase": {"type": "hg", "g": 0.4}},
        "sensor": {"type": "perspective", "fov": 30.0, "fov_axis": "y",
                   "to_world": to_world,
                   "film": {"type": "hdrfilm", "width": 40, "height": 30},
                   "sampler": {"type": "independent", "sample_count": 9},
                   "medium": {"type": "ref", "id": "fog"}},
        "lamp": {"type": "point", "position": [0.0, 3.0, 0.0],
                 "intensity": {"type": "spectrum", "value": 5.0}},
        "wall": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.3},
                 "glow": {"type": "area"}},
    }


def test_mitsuba_dict_through_the_api(caplog):
    m = np.eye(4)
    m[:3, 3] = [0.0, 1.0, 5.0]
    m[:3, 2] = [0.0, 0.0, -1.0]          # looking down -z (x mirrored to keep it proper)
    m[:3, 0] = [-1.0, 0.0, 0.0]
    with caplog.at_level(logging.WARNING, logger="clscatter"):
        spec = clscatter.load(_mitsuba_dict(m))
    assert spec.source == "<mitsuba dict>"
    np.testing.assert_allclose(spec.camera.origin, [0.0, 1.0, 5.0])
    np.testing.assert_allclose(spec.camera.target, [0.0, 1.0, 4.0])
    assert spec.camera.fov_axis == "y" and spec.camera.spp == 9
    np.testing.assert_allclose(spec.medium.sigma_s, [0.2, 0.3, 0.4], rtol=1e-12)
    np.testing.assert_allclose(spec.medium.sigma_a, [0.2, 0.3, 0.4], rtol=1e-12)
    assert spec.medium.g == 0.4 and spec.medium.bounds is None
    np.testing.assert_allclose(spec.lights[0].power, 5.0)
    assert spec.objects[0].shape == "quad"
    assert [r.getMessage() for r in caplog.records] == [
        ('emitter "area" (wall.glow): clscatter has point, spot and directional lights only; '
         "dropped")]


def test_mitsuba_dict_with_mitsuba_objects():
    mi = pytest.importorskip("mitsuba", reason="the optional mitsuba package is not installed")
    mi.set_variant("scalar_rgb")
    to_world = mi.ScalarTransform4f().look_at(origin=[1.0, 2.0, 3.0], target=[0.0, 0.0, 0.0],
                                              up=[0.0, 1.0, 0.0])
    d = _mitsuba_dict(to_world)
    d["lamp"]["position"] = mi.ScalarPoint3f(0.0, 3.0, 0.0)
    d["fog"]["sigma_t"]["value"] = mi.ScalarColor3f(0.2, 0.3, 0.4)
    spec = clscatter.load(d)
    np.testing.assert_allclose(spec.camera.origin, [1.0, 2.0, 3.0], atol=1e-6)
    np.testing.assert_allclose(spec.camera.target - spec.camera.origin,
                               -np.array([1.0, 2.0, 3.0]) / math.sqrt(14), atol=1e-6)
    np.testing.assert_allclose(spec.lights[0].position, [0.0, 3.0, 0.0])
    np.testing.assert_allclose(spec.medium.sigma_s, [0.2, 0.3, 0.4], rtol=1e-6)


def test_xml_path_through_the_api_and_the_cli(tmp_path, caplog, capsys):
    path = tmp_path / "scene.xml"
    path.write_text(_xml('<shape type="sphere" id="ball"><bsdf type="plastic"/></shape>'))
    with caplog.at_level(logging.WARNING, logger="clscatter"):
        spec = clscatter.load(path)
    assert spec.source == str(path) and spec.objects[0].material.type == "diffuse"
    assert len(caplog.records) == 1 and 'bsdf "plastic" (ball.bsdf)' in caplog.records[0].getMessage()
    code, out, err = _run(["check", str(path)], capsys)
    assert code == 0 and f"{path}: valid" in out
    assert err.splitlines()[0].startswith('clscatter: note: bsdf "plastic" (ball.bsdf): approximated')


# ---- writing, round trips, convert --------------------------------------------------------------

def _graded(name: str) -> bool:
    return any(v.get("ior", 1.0) != 1.0 or "grid" in v for v in BUILTIN[name]().get("volumes", []))


def _same_scene(a, b) -> None:
    """The numbers of two loaded scenes agree: camera, medium, lights, materials, the
    objects' triangles, volumes, seed (and max_depth where mirrors or glass use it)."""
    ca, cb = a.camera, b.camera
    for k in ("origin", "target", "up"):
        np.testing.assert_allclose(getattr(cb, k), getattr(ca, k), rtol=1e-12, atol=1e-12)
    assert (cb.fov, cb.fov_axis, cb.width, cb.height, cb.spp) == (ca.fov, ca.fov_axis, ca.width,
                                                                 ca.height, ca.spp)
    assert a.has_medium() == b.has_medium()
    if a.has_medium():
        floor = mitsuba_out.MIN_SIGMA_T * float(a.medium.kappa.max())
        np.testing.assert_allclose(b.medium.sigma_s, a.medium.sigma_s, rtol=1e-13, atol=floor)
        np.testing.assert_allclose(b.medium.sigma_a, a.medium.sigma_a, rtol=1e-13, atol=floor)
        assert b.medium.g == a.medium.g
        assert (a.medium.bounds is None) == (b.medium.bounds is None)
        if a.medium.bounds is not None:
            np.testing.assert_allclose(b.medium.bounds, a.medium.bounds, rtol=1e-13, atol=1e-13)
    assert len(a.lights) == len(b.lights)
    for la, lb in zip(a.lights, b.lights):
        assert (la.type, la.cutoff_angle) == (lb.type, lb.cutoff_angle)
        np.testing.assert_allclose(lb.power, la.power, rtol=1e-15)
        for k in ("position", "direction"):
            if getattr(la, k) is not None:
                np.testing.assert_allclose(getattr(lb, k), getattr(la, k), rtol=1e-12, atol=1e-12)
    assert len(a.objects) == len(b.objects)
    for oa, ob in zip(a.objects, b.objects):
        ma, mb = oa.material, ob.material
        assert ma.type == mb.type
        np.testing.assert_allclose(mb.color, ma.color, rtol=1e-15)
        if ma.type == "dielectric":
            assert mb.ior == pytest.approx(ma.ior, rel=1e-14)
            floor = mitsuba_out.MIN_SIGMA_T * float(np.max(ma.interior_sigma_s + ma.interior_sigma_a))
            np.testing.assert_allclose(mb.interior_sigma_s, ma.interior_sigma_s, atol=floor)
            np.testing.assert_allclose(mb.interior_sigma_a, ma.interior_sigma_a, atol=floor)
            g = a.medium.g if a.medium is not None else 0.0
            assert (mb.interior_g if mb.interior_g is not None else g) == \
                (ma.interior_g if ma.interior_g is not None else g)
        # the same triangles in the same order, as written to full precision, and the same shading
        np.testing.assert_array_equal(ob.vertices[ob.faces], oa.vertices[oa.faces])
        assert (oa.normals is None) == (ob.normals is None)
    assert len(a.volumes) == len(b.volumes)
    for va, vb in zip(a.volumes, b.volumes):
        np.testing.assert_array_equal(vb.density, va.density)
        np.testing.assert_allclose(vb.grid_bounds, va.grid_bounds, rtol=1e-13)
        # coefficients that differ between r, g and b travel as a three-channel float32
        # grid (density x colour): the colour comes back to float32's precision
        tol = 1e-13 if np.ptp(va.sigma_s + va.sigma_a) == 0 else 1e-7
        np.testing.assert_allclose(vb.sigma_s, va.sigma_s, rtol=tol)
        np.testing.assert_allclose(vb.sigma_a, va.sigma_a, rtol=tol)
    assert a.render.seed == b.render.seed
    if any(o.material.type in ("mirror", "dielectric") for o in a.objects):
        assert a.render.max_depth == b.render.max_depth


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_builtin_scenes_round_trip(name, tmp_path, monkeypatch):
    if _graded(name):
        with pytest.raises(SceneError, match=r"volumes\[0\]: a graded index of refraction"):
            mitsuba_out.convert(BUILTIN[name]())
        pytest.skip("a graded index of refraction has no Mitsuba 3 equivalent")
    monkeypatch.chdir(tmp_path)
    mitsuba_out.write_xml(BUILTIN[name](), tmp_path / "scene.xml")
    _same_scene(load_scene(f"builtin:{name}"), load_scene(tmp_path / "scene.xml"))


def test_a_grey_density_volume_round_trips(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    d = BUILTIN["smoke_plume"]()
    d["volumes"][0].update(sigma_s=2.5, sigma_a=0.5)
    mitsuba_out.write_xml(d, tmp_path / "smoke.xml")
    assert (tmp_path / "smoke_files" / "volume_0.vol").is_file()
    _same_scene(scene_from_dict(copy.deepcopy(d)), load_scene(tmp_path / "smoke.xml"))


def test_writer_numbers():
    """The medium as sigma_t within [0, 1] times scale (a zero channel floored), glass's
    interior medium, the sampler and the depth of single scattering."""
    d = BUILTIN["glass"]()
    conv = mitsuba_out.convert(d)
    med = conv.tree["medium"]
    assert med["sigma_t"]["value"] == [1.0, 1.0, 1.0] and med["scale"] == pytest.approx(0.045)
    assert med["albedo"]["value"] == pytest.approx([0.04 / 0.045] * 3, rel=1e-15)
    interior = conv.tree["glass_interior"]
    assert interior["sigma_t"]["value"] == [mitsuba_out.MIN_SIGMA_T, 0.5, 1.0]
    assert interior["scale"] == 0.1 and interior["albedo"]["value"] == [0.0, 0.0, 0.0]
    assert conv.tree["object_1"]["interior"] == {"type": "ref", "id": "glass_interior"}
    assert conv.tree["object_1"]["exterior"] == {"type": "ref", "id": "medium"}
    assert conv.tree["integrator"] == {"type": "volpath", "max_depth": 18}
    assert len(conv.notes) == 1 and "mirrors or glass" in conv.notes[0]
    assert conv.tree["sensor"]["sampler"] == {"type": "stratified", "sample_count": 4, "seed": 0}
    d["camera"]["spp"] = 9
    assert mitsuba_out.convert(d).tree["sensor"]["sampler"]["type"] == "independent"
    shafts = mitsuba_out.convert(BUILTIN["shafts"]())
    assert shafts.tree["integrator"]["max_depth"] == mitsuba_out.SINGLE_SCATTERING_DEPTH == 2
    assert isinstance(shafts.tree["sensor"]["to_world"], Transform)


def test_convert_both_ways_through_the_cli(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    code, out, err = _run(["convert", "builtin:spotlight", "-o", "spot.xml"], capsys)
    assert code == 0 and out.strip() == "builtin:spotlight -> spot.xml"
    assert err.count("clscatter: note:") == 1 and "objects[0]" in err   # the floor crosses the bounds
    assert sorted(p.name for p in (tmp_path / "spot_files").iterdir()) == ["object_0.obj",
                                                                           "object_1.obj"]
    code, out, err = _run(["convert", "spot.xml", "-o", "out/spot.toml"], capsys)
    assert code == 0 and err == ""
    text = (tmp_path / "out" / "spot.toml").read_text()
    assert 'file = "../spot_files/object_0.obj"' in text          # relative to the TOML
    _same_scene(load_scene("builtin:spotlight"), load_scene(tmp_path / "out" / "spot.toml"))
    code, _, _ = _run(["convert", "out/spot.toml", "-o", "again.xml"], capsys)
    assert code == 0
    _same_scene(load_scene("builtin:spotlight"), load_scene(tmp_path / "again.xml"))


@pytest.mark.parametrize("src, output, key", [
    ("area.xml", "out.toml", 'emitter "area"'),
    ("builtin:volume_lens", "out.xml", "volumes[0]"),
    ("builtin:shafts", "out.obj", "unsupported -o format"),
])
def test_convert_errors_write_nothing(src, output, key, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "area.xml").write_text(_xml('<shape type="sphere"><emitter type="area"/></shape>',
                                            light=""))
    before = set(tmp_path.iterdir())
    code, out, err = _run(["convert", src, "-o", output], capsys)
    assert code == 2 and out == ""
    assert len(err.splitlines()) == 1 and err.startswith("clscatter: error:") and key in err
    assert set(tmp_path.iterdir()) == before


def test_mitsuba_reads_what_is_written(tmp_path):
    """Mitsuba's own loader takes the XML (glass with an interior medium, a mirror, the
    sensor in an unbounded medium; a density volume in a bounded one) and renders it
    without NaN; its sensor, film and emitters are the scene's."""
    mi = pytest.importorskip("mitsuba", reason="the optional mitsuba package is not installed")
    mi.set_variant("scalar_rgb")
    smoke = BUILTIN["smoke_plume"]()
    smoke["medium"] = {"sigma_s": 0.05, "sigma_a": 0.01, "g": 0.3,
                       "bounds": {"min": [-2.5, 0.0, -2.5], "max": [2.5, 3.0, 2.5]}}
    for name, d in (("glass", BUILTIN["glass"]()), ("smoke", smoke)):
        d["camera"].update(resolution=[24, 18], fov_axis="y")
        mitsuba_out.write_xml(d, tmp_path / f"{name}.xml")
        scene = mi.load_file(str(tmp_path / f"{name}.xml"))
        sensor = scene.sensors()[0]
        assert list(sensor.film().size()) == [24, 18]
        fov_y = 2 * math.degrees(math.atan(math.tan(math.radians(mi.traverse(sensor)["x_fov"]) / 2)
                                           * 18 / 24))
        assert fov_y == pytest.approx(d["camera"]["fov"], rel=1e-5)
        assert len(scene.emitters()) == len(d["lights"])
        image = np.array(mi.render(scene, spp=4))
        assert image.shape == (18, 24, 3) and np.isfinite(image).all() and image.mean() > 0.0
