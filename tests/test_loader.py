"""Tests of the Mitsuba XML scene loader (mpg.scene); no C++ core needed."""

from __future__ import annotations

import math
import os
import pathlib
import struct

import numpy as np
import pytest
from mpg.errors import SceneError
from mpg.scene import load_file, load_string
from mpg.scene.loader import rotate
from mpg.scene.spectra import spectrum_to_rgb

HEAD = '<scene version="3.0.0">\n'
TAIL = "</scene>\n"


def write(tmp_path: pathlib.Path, body: str, name: str = "scene.xml") -> pathlib.Path:
    p = tmp_path / name
    p.write_text(HEAD + body + TAIL)
    return p


def load(tmp_path, body, **kw):
    return load_file(write(tmp_path, body), **kw)


def line_of(text: str, marker: str) -> int:
    for i, l in enumerate((HEAD + text).splitlines(), 1):
        if marker in l:
            return i
    raise AssertionError(marker)


def expect_error(tmp_path, body, marker, match=None, **kw):
    """Loading must raise SceneError naming scene.xml and the line holding marker."""
    p = write(tmp_path, body)
    with pytest.raises(SceneError) as ei:
        load_file(p, **kw)
    msg = str(ei.value)
    assert "scene.xml" in msg, msg
    assert f":{line_of(body, marker)}:" in msg, msg
    if match:
        assert match in msg, msg
    return msg


def shape(t: str, extra: str = "", bsdf: str = "") -> str:
    return f'<shape type="{t}">{extra}{bsdf}</shape>\n'


# ---------------------------------------------------------------------------
# defaults, substitution, refs, includes

SPP_SCENE = """<default name="spp" value="8"/>
<sensor type="perspective">
  <float name="fov" value="40"/>
  <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
</sensor>
"""


def test_default_and_override(tmp_path):
    assert load(tmp_path, SPP_SCENE).camera.spp == 8
    assert load(tmp_path, SPP_SCENE, spp=16).camera.spp == 16
    assert load(tmp_path, SPP_SCENE, spp="3").camera.spp == 3


def test_unknown_variable(tmp_path):
    body = '<sensor type="perspective"><float name="fov" value="$nope"/>\n</sensor>\n'
    msg = expect_error(tmp_path, body, "$nope")
    assert "nope" in msg


def test_substitution_in_any_attribute(tmp_path):
    body = ('<default name="t" value="diffuse"/><default name="c" value="0.1, 0.2, 0.3"/>\n'
            '<shape type="rectangle"><bsdf type="$t"><rgb name="reflectance" value="$c"/></bsdf>'
            '</shape>\n')
    s = load(tmp_path, body)
    np.testing.assert_allclose(s.shapes[0].bsdf.params["reflectance"].value, [0.1, 0.2, 0.3])


def test_refs_share_objects(tmp_path):
    body = """<bsdf type="diffuse" id="mat"><rgb name="reflectance" value="0.2"/></bsdf>
<texture type="checkerboard" id="chk"/>
<shape type="rectangle"><ref id="mat"/></shape>
<shape type="disk"><ref name="bsdf" id="mat"/></shape>
<shape type="cube"><bsdf type="diffuse"><ref name="reflectance" id="chk"/></bsdf></shape>
"""
    s = load(tmp_path, body)
    assert s.shapes[0].bsdf is s.shapes[1].bsdf
    assert s.shapes[0].bsdf.id == "mat"
    t = s.shapes[2].bsdf.params["reflectance"]
    assert t.kind == "checkerboard"
    np.testing.assert_allclose(t.color0, 0.4)
    np.testing.assert_allclose(t.color1, 0.2)


def test_unknown_ref(tmp_path):
    expect_error(tmp_path, '<shape type="rectangle">\n<ref id="ghost"/></shape>\n', "ghost",
                 match="ghost")


def test_include(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "sub" / "part.xml").write_text(
        '<scene version="3.0.0"><shape type="obj"><string name="filename" value="tri.obj"/>'
        '</shape><default name="late" value="5"/></scene>')
    s = load(tmp_path, '<include filename="sub/part.xml"/>\n<shape type="rectangle"/>\n')
    assert len(s.shapes) == 2
    assert s.shapes[0].positions.shape == (3, 3)


def test_include_cycle(tmp_path):
    (tmp_path / "a.xml").write_text('<scene version="3.0.0">\n<include filename="b.xml"/>\n</scene>')
    (tmp_path / "b.xml").write_text('<scene version="3.0.0">\n<include filename="a.xml"/>\n</scene>')
    with pytest.raises(SceneError) as ei:
        load_file(tmp_path / "a.xml")
    assert "cycle" in str(ei.value)


def test_missing_include(tmp_path):
    expect_error(tmp_path, '<include filename="nothere.xml"/>\n', "nothere", match="nothere")


def test_load_string_base_dir(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    xml = HEAD + '<shape type="obj"><string name="filename" value="tri.obj"/></shape>' + TAIL
    s = load_string(xml, base_dir=str(tmp_path))
    assert s.shapes[0].indices.tolist() == [[0, 1, 2]]
    with pytest.raises(SceneError) as ei:
        load_string(HEAD + "<shape type='nope'/>" + TAIL)
    assert "<string>" in str(ei.value)


# ---------------------------------------------------------------------------
# transforms

def sensor_with(ops: str) -> str:
    return (f'<sensor type="perspective"><float name="fov" value="30"/>'
            f'<transform name="to_world">{ops}</transform></sensor>\n')


def test_lookat_matrix(tmp_path):
    s = load(tmp_path, sensor_with('<lookat origin="0, 0, 5" target="0 0 0" up="0,1,0"/>'))
    expected = np.array([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 5], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(s.camera.to_world, expected, atol=1e-12)


def test_transform_order(tmp_path):
    # ops apply in document order: M = translate * rotate
    s = load(tmp_path, sensor_with('<rotate y="1" angle="90"/><translate x="1" y="2" z="3"/>'))
    r = np.array([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]], dtype=float)
    t = np.eye(4)
    t[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(s.camera.to_world, t @ r, atol=1e-12)
    np.testing.assert_allclose(rotate([0, 1, 0], 90)[:3, :3] @ [1, 0, 0], [0, 0, -1], atol=1e-12)


def test_transform_forms(tmp_path):
    s = load(tmp_path, sensor_with('<scale value="2"/><translate value="1 2 3"/>'
                                   '<scale x="3"/><matrix value="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/>'))
    m = s.camera.to_world
    np.testing.assert_allclose(m @ [1, 1, 1, 1], [3 * 3, 4, 5, 1])


def test_lookat_degenerate(tmp_path):
    expect_error(tmp_path, sensor_with('\n<lookat origin="1 1 1" target="1 1 1" up="0 1 0"/>'),
                 "lookat", match="degenerate")
    expect_error(tmp_path, sensor_with('\n<lookat origin="0 0 0" target="0 5 0" up="0 1 0"/>'),
                 "lookat", match="parallel")


# ---------------------------------------------------------------------------
# shapes

def tri_area(s):
    p = s.positions.astype(np.float64)[s.indices.astype(np.int64)]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()


def test_rectangle(tmp_path):
    s = load(tmp_path, shape("rectangle", '<transform name="to_world"><scale x="2" y="3"/>'
                             '<rotate x="1" angle="-90"/></transform>')).shapes[0]
    assert s.kind == "mesh"
    assert tri_area(s) == pytest.approx(4 * 6)
    np.testing.assert_allclose(s.normals, np.tile([0, 1, 0], (4, 1)), atol=1e-6)
    # uv (0,0) at local (-1,-1), (1,1) at (1,1)
    i0 = np.argmin(s.uvs.sum(axis=1))
    np.testing.assert_allclose(s.positions[i0], [-2, 0, 3], atol=1e-6)
    assert s.positions.dtype == np.float32 and s.indices.dtype == np.uint32


def test_disk(tmp_path):
    s = load(tmp_path, shape("disk", '<transform name="to_world"><scale value="2"/></transform>')
             ).shapes[0]
    assert tri_area(s) == pytest.approx(4 * math.pi, rel=1e-3)
    np.testing.assert_allclose(s.normals, np.tile([0, 0, 1], (len(s.normals), 1)), atol=1e-6)
    r = np.linalg.norm(s.positions[:, :2], axis=1)
    np.testing.assert_allclose(s.uvs[:, 0], r / 2, atol=1e-6)


def test_cube(tmp_path):
    s = load(tmp_path, shape("cube")).shapes[0]
    assert tri_area(s) == pytest.approx(24)
    assert len(s.positions) == 24
    # vertex normals equal the face normal of every triangle, outward
    p = s.positions[s.indices]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    for k in range(3):
        np.testing.assert_allclose(s.normals[s.indices[:, k]], fn, atol=1e-6)
    assert np.all(np.einsum("ij,ij->i", fn, p.mean(axis=1)) > 0)
    assert s.uvs.min() == 0 and s.uvs.max() == 1


def test_cylinder(tmp_path):
    s = load(tmp_path, shape("cylinder", '<point name="p0" value="1 0 0"/>'
                             '<point name="p1" x="1" y="2"/><float name="radius" value="0.5"/>')
             ).shapes[0]
    assert tri_area(s) == pytest.approx(2 * math.pi * 0.5 * 2, rel=1e-3)
    axis = np.array([0, 1, 0])
    np.testing.assert_allclose(s.normals @ axis, 0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1, atol=1e-6)
    radial = s.positions - [1, 0, 0]
    radial[:, 1] = 0
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), 0.5, atol=1e-6)
    np.testing.assert_allclose(s.normals, radial / 0.5, atol=1e-5)   # exact, outward
    np.testing.assert_allclose(s.uvs[:, 1], s.positions[:, 1] / 2, atol=1e-6)


def test_cylinder_scaled_normals(tmp_path):
    # non-uniform scale: normals by the inverse transpose
    s = load(tmp_path, shape("cylinder", '<transform name="to_world"><scale x="2" y="1" z="1"/>'
                             '</transform>')).shapes[0]
    p = s.positions.astype(np.float64)
    expect = np.stack([p[:, 0] / 4, p[:, 1], np.zeros(len(p))], axis=1)
    expect /= np.linalg.norm(expect, axis=1, keepdims=True)
    np.testing.assert_allclose(s.normals, expect, atol=1e-5)


def test_sphere(tmp_path):
    s = load(tmp_path, shape("sphere", '<point name="center" value="1 0 0"/>'
                             '<float name="radius" value="2"/><transform name="to_world">'
                             '<scale value="3"/><translate y="1"/></transform>')).shapes[0]
    assert s.kind == "sphere"
    np.testing.assert_allclose(s.center, [3, 1, 0])
    assert s.radius == pytest.approx(6)
    expect_error(tmp_path, '<shape type="sphere">\n<transform name="to_world"><scale x="2"/>'
                 '</transform></shape>\n', "sphere", match="non-uniform")


def test_shape_flags(tmp_path):
    s = load(tmp_path, shape("rectangle", '<boolean name="flip_normals" value="true"/>'
                             '<boolean name="caustic_receiver" value="true"/>'
                             '<boolean name="caustic_caster_single" value="false"/>')).shapes[0]
    assert s.flip_normals
    assert s.hints == {"caustic_receiver"}
    assert s.bsdf.type == "diffuse"
    np.testing.assert_allclose(s.bsdf.params["reflectance"].value, 0.5)


OBJ = """# quad + triangle with negative indices
o first
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
f 1/1/1 2/2/1 3/3/1 4/4/1
o second
v 0 0 1
v 1 0 1
v 0 1 1
f -3//1 -2//1 -1//1
"""


def test_obj(tmp_path):
    (tmp_path / "m.obj").write_text(OBJ)
    s = load(tmp_path, shape("obj", '<string name="filename" value="m.obj"/>'
                             '<transform name="to_world"><translate z="2"/></transform>')).shapes[0]
    assert len(s.indices) == 3
    assert tri_area(s) == pytest.approx(1.5)
    np.testing.assert_allclose(s.normals, np.tile([0, 0, 1], (len(s.normals), 1)))
    assert s.positions[:, 2].min() == pytest.approx(2)
    # Mitsuba flips OBJ v: the vertex with vt (0,0) gets uv (0,1)
    i = int(np.where(np.all(s.positions == [0, 0, 2], axis=1))[0][0])
    np.testing.assert_allclose(s.uvs[i], [0, 1])
    s2 = load(tmp_path, shape("obj", '<string name="filename" value="m.obj"/>'
                              '<boolean name="face_normals" value="true"/>')).shapes[0]
    assert s2.normals is None


def test_obj_without_normals_gets_smooth_normals(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    s = load(tmp_path, shape("obj", '<string name="filename" value="m.obj"/>')).shapes[0]
    assert len(s.positions) == 4
    np.testing.assert_allclose(s.normals, np.tile([0, 0, 1], (4, 1)), atol=1e-6)


def test_obj_zero_normals_fall_back(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 0\nf 1//1 2//1 3//1\n")
    s = load(tmp_path, shape("obj", '<string name="filename" value="m.obj"/>'))
    assert s.shapes[0].normals is None
    assert any("face normals" in w for w in s.warnings)


def test_obj_errors(tmp_path):
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "idx.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n")
    msg = expect_error(tmp_path, shape("obj", '<string name="filename" value="nan.obj"/>'),
                       "nan.obj", match="NaN")
    msg = expect_error(tmp_path, shape("obj", '<string name="filename" value="idx.obj"/>'),
                       "idx.obj", match="idx.obj:5")
    assert "9" in msg
    expect_error(tmp_path, shape("obj", '<string name="filename" value="gone.obj"/>'),
                 "gone.obj", match="not found")


def test_missing_mesh_substituted(tmp_path):
    s = load(tmp_path, shape("obj", '<string name="filename" value="gone.obj"/>'),
             substitute_missing_textures=True)
    assert s.shapes[0].positions.shape[0] > 0
    assert any("gone.obj" in w for w in s.warnings)


def ply_binary(path, endian="<"):
    pos = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0]], dtype=np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (3, 1))
    uv = np.array([[0, 0], [1, 0], [0, 1]], dtype=np.float32)
    e = "little" if endian == "<" else "big"
    hdr = (f"ply\nformat binary_{e}_endian 1.0\nelement vertex 3\nproperty float x\n"
           "property float y\nproperty float z\nproperty float nx\nproperty float ny\n"
           "property float nz\nproperty float s\nproperty float t\nelement face 1\n"
           "property list uchar int vertex_indices\nend_header\n").encode()
    body = b"".join(struct.pack(endian + "8f", *pos[i], *nrm[i], *uv[i]) for i in range(3))
    body += struct.pack(endian + "B3i", 3, 0, 1, 2)
    path.write_bytes(hdr + body)


@pytest.mark.parametrize("endian", ["<", ">"])
def test_ply_binary(tmp_path, endian):
    ply_binary(tmp_path / "m.ply", endian)
    s = load(tmp_path, shape("ply", '<string name="filename" value="m.ply"/>')).shapes[0]
    assert tri_area(s) == pytest.approx(2)
    np.testing.assert_allclose(s.uvs, [[0, 0], [1, 0], [0, 1]])
    np.testing.assert_allclose(s.normals[:, 2], 1)


def test_ply_ascii_quad(tmp_path):
    (tmp_path / "m.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nproperty float u\nproperty float v\nelement face 1\n"
        "property list uchar int vertex_index\nend_header\n"
        "0 0 0 0 0\n1 0 0 1 0\n1 1 0 1 1\n0 1 0 0 1\n4 0 1 2 3\n")
    s = load(tmp_path, shape("ply", '<string name="filename" value="m.ply"/>')).shapes[0]
    assert len(s.indices) == 2
    assert tri_area(s) == pytest.approx(1)


def test_serialized(tmp_path):
    import zlib
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    payload = struct.pack("<I", 0x1000) + b"tri\0" + struct.pack("<QQ", 3, 1) + pos.tobytes() \
        + np.array([0, 1, 2], dtype=np.uint32).tobytes()
    data = struct.pack("<HH", 0x041C, 4) + zlib.compress(payload)
    data += struct.pack("<QI", 0, 1)
    (tmp_path / "m.serialized").write_bytes(data)
    s = load(tmp_path, shape("serialized", '<string name="filename" value="m.serialized"/>'))
    assert tri_area(s.shapes[0]) == pytest.approx(0.5)


# ---------------------------------------------------------------------------
# spectra, BSDFs, textures

def test_spectrum_flat_is_grey():
    np.testing.assert_allclose(spectrum_to_rgb([360, 830], [0.7, 0.7]), 0.7, rtol=1e-9)
    rgb = spectrum_to_rgb(np.arange(360, 831, 10), np.full(48, 2.0))
    np.testing.assert_allclose(rgb, 2.0, rtol=1e-3)
    red = spectrum_to_rgb([360, 599, 600, 830], [0, 0, 1, 1])
    assert red[0] > red[1] and red[0] > red[2]


def test_spectrum_properties(tmp_path):
    s = load(tmp_path, """<shape type="rectangle"><emitter type="area">
<spectrum name="radiance" value="360:3, 830:3"/></emitter></shape>
<shape type="rectangle"><emitter type="area"><spectrum name="radiance" value="5"/></emitter>
</shape><shape type="rectangle"><emitter type="area"><rgb name="radiance" value="0.25"/></emitter>
</shape>""")
    np.testing.assert_allclose(s.shapes[0].emitter.params["radiance"], 3, rtol=1e-6)
    np.testing.assert_allclose(s.shapes[1].emitter.params["radiance"], 5)
    np.testing.assert_allclose(s.shapes[2].emitter.params["radiance"], 0.25)


def test_bsdf_defaults(tmp_path):
    body = "".join(shape("rectangle", bsdf=b) for b in [
        '<bsdf type="dielectric"/>',
        ('<bsdf type="dielectric"><string name="int_ior" value="water"/>'
        '<string name="ext_ior" value="vacuum"/></bsdf>'),
        '<bsdf type="plastic"/>',
        '<bsdf type="conductor"/>',
        ('<bsdf type="roughconductor"><string name="material" value="Au"/>'
        '<float name="alpha_u" value="0.1"/><float name="alpha_v" value="0.2"/></bsdf>'),
        '<bsdf type="twosided"><bsdf type="diffuse"/></bsdf>',
        ('<bsdf type="roughdielectric"><float name="alpha" value="0.3"/>'
        '<string name="distribution" value="ggx"/></bsdf>'),
        ('<bsdf type="conductor"><rgb name="eta" value="0.2, 0.3, 0.4"/>'
        '<spectrum name="k" value="3"/></bsdf>'),
    ])
    b = [x.bsdf for x in load(tmp_path, body).shapes]
    assert b[0].params["int_ior"] == pytest.approx(1.5046)
    assert b[0].params["ext_ior"] == pytest.approx(1.000277)
    assert b[1].params["int_ior"] == pytest.approx(1.333)
    assert b[1].params["ext_ior"] == 1.0
    assert b[2].params["int_ior"] == pytest.approx(1.49)
    assert b[2].params["nonlinear"] is False
    np.testing.assert_allclose(b[2].params["diffuse_reflectance"].value, 0.5)
    np.testing.assert_allclose(b[3].params["eta"], 0)     # perfect mirror
    np.testing.assert_allclose(b[3].params["k"], 1)
    assert b[4].params["distribution"] == "beckmann"
    assert (b[4].params["alpha_u"], b[4].params["alpha_v"]) == (0.1, 0.2)
    assert b[4].params["eta"][2] > 1 and b[4].params["k"][0] > 3
    assert b[5].params["front"] is b[5].params["back"]
    assert b[6].params["alpha"] == 0.3 and b[6].params["distribution"] == "ggx"
    np.testing.assert_allclose(b[7].params["k"], 3)


def test_bsdf_errors(tmp_path):
    expect_error(tmp_path, shape("rectangle", bsdf='<bsdf type="mask">\n</bsdf>'), "mask",
                 match="unsupported BSDF")
    expect_error(tmp_path, shape("rectangle", bsdf='<bsdf type="dielectric">\n'
                                 '<string name="int_ior" value="unobtainium"/></bsdf>'),
                 "unobtainium")
    expect_error(tmp_path, shape("rectangle", bsdf='<bsdf type="conductor">\n'
                                 '<string name="material" value="Zz"/></bsdf>'), '"Zz"')


def png(path, arr, mode=None):
    from PIL import Image
    Image.fromarray(arr, mode).save(path)


def test_bitmap_texture(tmp_path):
    img = np.zeros((2, 3, 3), np.uint8)
    img[0, 0] = [255, 128, 0]
    png(tmp_path / "t.png", img)
    png(tmp_path / "g.png", np.full((2, 2), 128, np.uint8))
    body = """<shape type="rectangle"><bsdf type="diffuse">
<texture name="reflectance" type="bitmap"><string name="filename" value="t.png"/>
<string name="filter_type" value="nearest"/><transform name="to_uv"><scale x="2" y="3"/>
<translate x="0.5"/></transform></texture></bsdf></shape>
<shape type="rectangle"><bsdf type="diffuse"><texture name="reflectance" type="bitmap">
<string name="filename" value="t.png"/><boolean name="raw" value="true"/></texture></bsdf></shape>
<shape type="rectangle"><bsdf type="diffuse"><spectrum name="reflectance" type="bitmap">
<string name="filename" value="g.png"/></spectrum></bsdf></shape>
"""
    s = load(tmp_path, body)
    t = s.shapes[0].bsdf.params["reflectance"]
    assert t.kind == "bitmap" and t.filter == "nearest" and t.wrap == "repeat"
    assert t.image.shape == (2, 3, 3) and t.image.dtype == np.float32
    np.testing.assert_allclose(t.image[0, 0], [1.0, 0.21586, 0.0], atol=1e-4)   # sRGB decoded
    np.testing.assert_allclose(t.to_uv, [[2, 0, 0.5], [0, 3, 0], [0, 0, 1]])
    t2 = s.shapes[1].bsdf.params["reflectance"]
    np.testing.assert_allclose(t2.image[0, 0], [1.0, 128 / 255, 0.0], atol=1e-6)
    t3 = s.shapes[2].bsdf.params["reflectance"]
    assert t3.image.shape == (2, 2, 3)


def test_exr_texture(tmp_path):
    import OpenEXR
    rgb = np.random.default_rng(1).random((4, 5, 3)).astype(np.float32)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"RGB": rgb}).write(str(tmp_path / "e.exr"))
    s = load(tmp_path, '<emitter type="envmap"><string name="filename" value="e.exr"/>'
             '<float name="scale" value="2"/></emitter>\n')
    e = s.emitters[0]
    np.testing.assert_allclose(e.params["image"], rgb)
    assert e.params["scale"] == 2


def test_missing_texture(tmp_path):
    body = ('<shape type="rectangle"><bsdf type="diffuse"><texture name="reflectance" '
            'type="bitmap">\n<string name="filename" value="nope.jpg"/></texture></bsdf></shape>\n')
    expect_error(tmp_path, body, "nope.jpg", match="nope.jpg")
    s = load(tmp_path, body, substitute_missing_textures=True)
    t = s.shapes[0].bsdf.params["reflectance"]
    assert t.kind == "constant"
    np.testing.assert_allclose(t.value, 0.5)
    assert s.warnings


def test_normalmap_forms(tmp_path):
    png(tmp_path / "n.png", np.full((2, 2, 3), [128, 128, 255], np.uint8))
    body = """<shape type="rectangle"><bsdf type="normalmap"><bsdf type="dielectric"/>
<string name="filename" value="n.png"/><float name="tiles" value="4"/>
<boolean name="use_slopes" value="true"/></bsdf></shape>
<shape type="rectangle"><bsdf type="normalmap">
<texture name="normalmap" type="bitmap"><boolean name="raw" value="true"/>
<string name="filename" value="n.png"/></texture><bsdf type="diffuse"/></bsdf></shape>
<shape type="rectangle"><bsdf type="normalmap"><bsdf type="diffuse"/>
<string name="filename" value="missing.png"/></bsdf></shape>
"""
    s = load(tmp_path, body, substitute_missing_textures=True)
    a, b, c = (x.bsdf for x in s.shapes)
    assert a.params["nested"].type == "dielectric"
    np.testing.assert_allclose(a.params["normalmap"].to_uv, np.diag([4, 4, 1]))
    np.testing.assert_allclose(a.params["normalmap"].image[0, 0], [128 / 255, 128 / 255, 1])  # raw
    assert a.params["use_slopes"] is True
    np.testing.assert_allclose(b.params["normalmap"].image[0, 0], [128 / 255, 128 / 255, 1])
    np.testing.assert_allclose(c.params["normalmap"].image.reshape(-1), [0.5, 0.5, 1])


# ---------------------------------------------------------------------------
# emitters, sensor, film, integrator

def test_emitters(tmp_path):
    s = load(tmp_path, """<emitter type="point"><point name="position" value="1 2 3"/>
<rgb name="intensity" value="5"/><boolean name="caustic_emitter_single" value="true"/></emitter>
<emitter type="spot"><transform name="to_world"><lookat origin="0 1 0" target="0 0 0" up="1 0 0"/>
</transform></emitter>
<emitter type="directional"><vector name="direction" value="0 -2 0"/></emitter>
<emitter type="constant"/>
""")
    pt, sp, di, co = s.emitters
    np.testing.assert_allclose(pt.params["position"], [1, 2, 3])
    assert pt.hints == {"caustic_emitter_single"}
    assert sp.params["cutoff_angle"] == 20 and sp.params["beam_width"] == 15
    np.testing.assert_allclose(sp.params["to_world"][:3, 2], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(di.params["direction"], [0, -1, 0])
    np.testing.assert_allclose(co.params["radiance"], 1)


def test_camera_film_sampler(tmp_path):
    s = load(tmp_path, """<sensor type="perspective"><float name="fov" value="35"/>
<string name="fov_axis" value="smaller"/><float name="near_clip" value="0.1"/>
<film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="32"/>
<integer name="crop_offset_x" value="8"/><integer name="crop_width" value="16"/>
<string name="pixel_format" value="rgb"/><rfilter type="gaussian"/></film>
<sampler type="stratified"><integer name="sample_count" value="9"/></sampler></sensor>
<integrator type="path"><integer name="max_depth" value="7"/></integrator>
""")
    c = s.camera
    assert (c.fov, c.fov_axis, c.near_clip, c.far_clip) == (35, "smaller", 0.1, 1e4)
    assert (c.width, c.height, c.crop) == (64, 32, (8, 0, 16, 32))
    assert c.rfilter.type == "gaussian" and c.rfilter.stddev == 0.5
    assert c.spp == 9 and c.sampler == "stratified"
    assert not any("stratified" in w for w in s.warnings)
    assert s.integrator.type == "path"
    assert s.integrator.params == {"max_depth": 7, "rr_depth": 5, "hide_emitters": False}


def test_defaults_without_sensor_and_integrator(tmp_path):
    s = load(tmp_path, shape("rectangle"))
    assert s.integrator.type == "path" and s.integrator.params["max_depth"] == -1
    c = s.camera
    assert c.fov == 45 and c.spp == 4 and c.rfilter.type == "box"
    np.testing.assert_allclose(c.to_world[:3, 2], [0, 0, -1], atol=1e-12)
    assert c.to_world[2, 3] > 1


def test_paper_integrator_keeps_params(tmp_path):
    s = load(tmp_path, """<integrator type="path_sms_ss"><integer name="max_depth" value="6"/>
<float name="solver_threshold" value="1e-5"/><boolean name="biased" value="false"/>
<integer name="samples_per_pass" value="4294967295"/></integrator>
""")
    p = s.integrator.params
    assert s.integrator.type == "path_sms_ss"
    assert p["max_depth"] == 6 and p["solver_threshold"] == 1e-5 and p["biased"] is False
    assert p["samples_per_pass"] == 4294967295 and p["rr_depth"] == 5


# ---------------------------------------------------------------------------
# error cases: SceneError with file and line

def test_malformed_xml(tmp_path):
    p = tmp_path / "scene.xml"
    p.write_text('<scene version="3.0.0">\n<shape type="cube">\n</scene>\n')
    with pytest.raises(SceneError) as ei:
        load_file(p)
    assert "scene.xml:3:" in str(ei.value) and "malformed" in str(ei.value)


def test_old_version_rejected(tmp_path):
    p = tmp_path / "scene.xml"
    p.write_text('<scene version="0.6.0">\n</scene>\n')
    with pytest.raises(SceneError, match="0.6.0"):
        load_file(p)


@pytest.mark.parametrize("body,marker,match", [
    ('<shape type="torus">\n</shape>\n', "torus", "unsupported shape"),
    ('<emitter type="laser"/>\n', "laser", "unsupported emitter"),
    ('<integrator type="bdpt"/>\n', "bdpt", "unsupported integrator"),
    ('<sensor type="thinlens"/>\n', "thinlens", "perspective"),
    ('<shape type="rectangle">\n<float name="radius" value="1"/></shape>\n', "radius",
     "unknown parameter 'radius'"),
    ('<integrator type="path">\n<integer name="max_depth" value="1.5"/></integrator>\n',
     "1.5", "integer"),
    ('<integrator type="path">\n<float name="max_depth" value="1"/></integrator>\n',
     "max_depth", "must be an <integer>"),
    ('<shape type="rectangle">\n<boolean name="flip_normals" value="yes"/></shape>\n',
     "yes", "true"),
    (('<shape type="rectangle"><bsdf type="diffuse">\n<rgb name="reflectance" value="1, 2"/>'
     '</bsdf></shape>\n'), "1, 2", "rgb"),
    ('<sensor type="perspective">\n<float name="fov" value="0"/></sensor>\n', "fov", "fov"),
    ('<sensor type="perspective">\n<float name="fov" value="180"/></sensor>\n', "fov", "fov"),
    (('<shape type="rectangle">\n<emitter type="area"><rgb name="radiance" value="1, -1, 1"/>'
     '</emitter></shape>\n'), "radiance", "non-negative"),
    (('<shape type="rectangle">\n<transform name="to_world"><scale x="0"/></transform>'
     '<emitter type="area"/></shape>\n'), "rectangle", "zero area"),
    ('<emitter type="area">\n</emitter>\n', "area", "nested inside a <shape>"),
    ('<bogus/>\n', "bogus", "unknown element"),
    ('<shape type="rectangle">\n<float value="1"/></shape>\n', "float value", "name"),
    (('<shape type="rectangle"><bsdf type="diffuse">\n<rgb name="reflectance" value="nan"/>'
     '</bsdf></shape>\n'), "nan", "NaN"),
])
def test_errors(tmp_path, body, marker, match):
    expect_error(tmp_path, body, marker, match=match)


def test_mesh_out_of_range_index_ply(tmp_path):
    (tmp_path / "m.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    expect_error(tmp_path, shape("ply", '\n<string name="filename" value="m.ply"/>'), "m.ply",
                 match="out of range")


# ---------------------------------------------------------------------------
# the published scenes

def _shared() -> pathlib.Path:
    env = os.environ.get("MPG_SHARED")
    if env:
        return pathlib.Path(env)
    return pathlib.Path(__file__).resolve().parents[2] / "shared"


PUBLISHED = sorted((_shared() / "published-scenes").rglob("*.xml")) \
    if (_shared() / "published-scenes").is_dir() else []
# scenes that use a $name without a <default> (their paper's scripts pass it with -D)
PUBLISHED_PARAMS = {"Figure_17_Roughness": {"alpha": "0.1"}}


@pytest.mark.skipif(not PUBLISHED, reason="shared/published-scenes not found")
@pytest.mark.parametrize("path", PUBLISHED, ids=lambda p: p.parent.name + "/" + p.name)
def test_published_scene_loads(path):
    params = PUBLISHED_PARAMS.get(path.parent.name, {})
    s = load_file(path, substitute_missing_textures=True, **params)
    assert s.shapes
    for sh in s.shapes:
        if sh.kind == "mesh":
            assert sh.positions.ndim == 2 and sh.indices.max() < len(sh.positions)
            if sh.normals is not None:
                np.testing.assert_allclose(np.linalg.norm(sh.normals, axis=1), 1, atol=1e-4)
    assert 0 < s.camera.fov < 180


@pytest.mark.skipif(not PUBLISHED, reason="shared/published-scenes not found")
def test_published_scene_missing_textures_need_flag():
    p = next(x for x in PUBLISHED if x.name == "sphere_sms.xml")
    with pytest.raises(SceneError, match="not found"):
        load_file(p)
