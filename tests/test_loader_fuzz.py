"""Mutation fuzzing of the scene loader: a mutated scene must load or raise
SceneError, never another exception, and never hang."""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mpg.errors import SceneError
from mpg.scene import load_string

BASE = """<scene version="2.0.0">
  <default name="spp" value="4"/>
  <default name="r" value="0.5"/>
  <integrator type="path_sms_ss">
    <integer name="max_depth" value="6"/>
    <float name="solver_threshold" value="1e-5"/>
    <boolean name="biased" value="false"/>
  </integrator>
  <sensor type="perspective">
    <string name="fov_axis" value="smaller"/>
    <float name="fov" value="40"/>
    <transform name="to_world">
      <lookat origin="0, 5, 10" target="0, 0, 0" up="0, 1, 0"/>
      <translate x="1"/>
    </transform>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm" id="film">
      <integer name="width" value="32"/><integer name="height" value="24"/>
      <integer name="crop_offset_x" value="2"/><integer name="crop_width" value="16"/>
      <rfilter type="gaussian"><float name="stddev" value="0.4"/></rfilter>
    </film>
  </sensor>
  <bsdf type="roughconductor" id="metal">
    <string name="material" value="Au"/><float name="alpha" value="0.2"/>
    <string name="distribution" value="ggx"/>
  </bsdf>
  <texture type="checkerboard" id="chk">
    <rgb name="color0" value="0.1, 0.2, 0.3"/>
    <transform name="to_uv"><scale x="4" y="4"/></transform>
  </texture>
  <emitter type="envmap">
    <string name="filename" value="env.exr"/><float name="scale" value="0.5"/>
    <transform name="to_world"><rotate y="1" angle="170"/></transform>
  </emitter>
  <emitter type="spot">
    <spectrum name="intensity" value="400:1, 500:2, 700:1"/>
    <float name="cutoff_angle" value="30"/>
    <transform name="to_world"><lookat origin="0 4 0" target="0 0 0" up="1 0 0"/></transform>
  </emitter>
  <shape type="rectangle">
    <boolean name="caustic_receiver" value="true"/>
    <bsdf type="diffuse"><ref name="reflectance" id="chk"/></bsdf>
    <transform name="to_world"><scale value="10"/><rotate x="1" angle="-90"/></transform>
  </shape>
  <shape type="obj">
    <string name="filename" value="m.obj"/>
    <boolean name="caustic_caster_single" value="true"/>
    <bsdf type="normalmap">
      <bsdf type="dielectric"><float name="int_ior" value="1.33"/></bsdf>
      <string name="filename" value="n.png"/><float name="tiles" value="2"/>
    </bsdf>
  </shape>
  <shape type="ply"><string name="filename" value="m.ply"/><ref id="metal"/></shape>
  <shape type="sphere">
    <point name="center" value="0, 1, 0"/><float name="radius" value="$r"/>
    <bsdf type="twosided"><bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.3"/>
    </bsdf></bsdf>
  </shape>
  <shape type="cylinder">
    <point name="p0" value="0 0 0"/><point name="p1" value="0 2 0"/>
    <float name="radius" value="0.1"/>
    <emitter type="area"><rgb name="radiance" value="1, 2, 3"/>
      <boolean name="caustic_emitter_single" value="true"/></emitter>
  </shape>
  <shape type="disk"><bsdf type="diffuse"><texture name="reflectance" type="bitmap">
    <string name="filename" value="c.png"/><string name="wrap_mode" value="clamp"/>
  </texture></bsdf></shape>
  <shape type="cube"><bsdf type="thindielectric"/></shape>
</scene>
"""

OBJ = """v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
f 1/1/1 2/2/1 3/3/1 4/4/1
f -4/-4/1 -2/-2/1 -1/-1/1
"""

PLY = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
       "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
       "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    import OpenEXR
    from PIL import Image
    d = tmp_path_factory.mktemp("fuzz")
    (d / "m.obj").write_text(OBJ)
    (d / "m.ply").write_text(PLY)
    Image.fromarray(np.full((4, 4, 3), [128, 128, 255], np.uint8)).save(d / "n.png")
    Image.fromarray(np.full((4, 4, 3), 90, np.uint8)).save(d / "c.png")
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"RGB": np.full((4, 8, 3), 0.3, np.float32)}).write(str(d / "env.exr"))
    return d


def test_base_scene_loads(scene_dir):
    s = load_string(BASE, base_dir=str(scene_dir))
    assert len(s.shapes) == 7 and len(s.emitters) == 2


ROOT = ET.fromstring(BASE)
ALL_ELEMENTS = [e for e in ROOT.iter()]
TAGS = sorted({e.tag for e in ALL_ELEMENTS} | {"bogus", "include", "ref", "default"})
ATTRS = sorted({k for e in ALL_ELEMENTS for k in e.attrib} | {"id", "filename"})

values = st.one_of(
    st.text(max_size=12),
    st.integers(min_value=-10**12, max_value=10**12).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["nan", "inf", "-1", "0", "1e308", "1e-320", "true", "false", "$spp", "$zz",
                     "1, 2", "1 2 3 4", ",,", "360:1, 830:1", "m.obj", "../nothere", "bitmap",
                     "diffuse", "rectangle", "ggx", "film", "metal", "chk", "x", "9999999999"]),
    st.lists(st.floats(min_value=-1e3, max_value=1e3), min_size=1, max_size=4)
    .map(lambda v: ", ".join(map(str, v))),
)

mutation = st.tuples(
    st.sampled_from(["delete", "duplicate", "set_attr", "del_attr", "retag", "move"]),
    st.integers(min_value=0, max_value=10**6),
    st.integers(min_value=0, max_value=10**6),
    st.sampled_from(ATTRS),
    values,
    st.sampled_from(TAGS),
)


def mutate(muts) -> ET.Element:
    root = copy.deepcopy(ROOT)
    for kind, i, j, attr, val, tag in muts:
        parents = [(p, c) for p in root.iter() for c in list(p)]
        if not parents:
            break
        parent, elem = parents[i % len(parents)]
        if kind == "delete":
            parent.remove(elem)
        elif kind == "duplicate":
            parent.insert(j % (len(parent) + 1), copy.deepcopy(elem))
        elif kind == "set_attr":
            elem.set(attr, val)
        elif kind == "del_attr":
            if elem.attrib:
                keys = sorted(elem.attrib)
                del elem.attrib[keys[j % len(keys)]]
        elif kind == "retag":
            elem.tag = tag
        elif kind == "move":
            parent.remove(elem)
            targets = list(root.iter())
            targets[j % len(targets)].append(elem)
    return root


def check(xml: str, base: str) -> None:
    try:
        load_string(xml, base_dir=base, substitute_missing_textures=False)
    except SceneError:
        pass


@settings(max_examples=250, deadline=2000, suppress_health_check=[HealthCheck.too_slow,
          HealthCheck.function_scoped_fixture], derandomize=True)
@given(muts=st.lists(mutation, min_size=1, max_size=4))
def test_mutated_scenes(scene_dir, muts):
    xml = ET.tostring(mutate(muts), encoding="unicode")
    check(xml, str(scene_dir))


@settings(max_examples=80, deadline=2000, suppress_health_check=[HealthCheck.too_slow,
          HealthCheck.function_scoped_fixture], derandomize=True)
@given(cut=st.integers(min_value=0, max_value=len(BASE)), junk=st.text(max_size=8))
def test_truncated_scenes(scene_dir, cut, junk):
    check(BASE[:cut] + junk, str(scene_dir))


@settings(max_examples=60, deadline=2000, suppress_health_check=[HealthCheck.too_slow,
          HealthCheck.function_scoped_fixture], derandomize=True)
@given(data=st.binary(max_size=200), which=st.sampled_from(["m.obj", "m.ply"]))
def test_garbage_meshes(tmp_path_factory, data, which):
    d = tmp_path_factory.mktemp("garbage", numbered=True)
    base = OBJ.encode() if which == "m.obj" else PLY.encode()
    (d / which).write_bytes(base[: len(data) % (len(base) + 1)] + data)
    kind = which.split(".")[1]
    xml = (f'<scene version="3.0.0"><shape type="{kind}"><string name="filename" '
           f'value="{which}"/></shape></scene>')
    check(xml, str(d))
