"""The evaluation scenes (scenes/eval/) and their generator (scenes/generate.py).

The generator is deterministic and the committed files are what it produces; every
scene loads in mpg, has a valid JSON sidecar, and renders a tiny image without NaN.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
import subprocess
import sys

import numpy as np
import pytest

import mpg

from conftest import ROOT, SCENES

# The content hash of everything scenes/generate.py writes. Update this constant
# (and say so in the commit) whenever the generator is changed on purpose.
EXPECTED_HASH = "e988a8dbddab24b7e8cfded24b6e8672f11cf766436e73820d299346a535d54f"

EVAL = SCENES / "eval"
XMLS = sorted(EVAL.glob("*.xml"))
SERIES = {"chain_length", "visibility", "emitter_size"}


def _generator():
    spec = importlib.util.spec_from_file_location("scenes_generate", SCENES / "generate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def gen():
    return _generator()


def test_generator_is_deterministic(gen):
    h1 = gen.content_hash()
    h2 = _generator().content_hash()
    assert h1 == h2
    assert h1 == EXPECTED_HASH, "generator output changed: if intended, update EXPECTED_HASH"


def test_committed_files_are_up_to_date():
    r = subprocess.run([sys.executable, str(SCENES / "generate.py"), "--check"], capture_output=True,
                       text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr


def test_every_scene_is_generated(gen):
    names = {p.stem for p in XMLS}
    assert names == set(gen.scenes())
    expected = {"sphere", "sphere_point", "slab", "double_slabs", "ring", "pool", "plane", "diffuse_room",
                "chain_length_1", "chain_length_4", "visibility_0", "visibility_8"}
    assert expected <= names
    assert sum(n.startswith("emitter_size_") for n in names) >= 4


def test_sizes():
    sizes = {p: p.stat().st_size for p in EVAL.rglob("*") if p.is_file()}
    assert all(s < 2_000_000 for s in sizes.values()), {str(p): s for p, s in sizes.items() if s >= 2_000_000}
    assert sum(sizes.values()) < 10_000_000


@pytest.mark.parametrize("path", XMLS, ids=[p.stem for p in XMLS])
def test_scene_file(path):
    text = path.read_text()
    assert '<scene version="3.0.0">' in text
    for d in ('<default name="res" value="256"/>', '<default name="spp" value="16"/>'):
        assert d in text
    assert re.search(r'<default name="max_depth" value="\d+"/>', text)
    assert '<integrator type="path">' in text and '<rfilter type="box"/>' in text

    scene = mpg.load_file(path)
    desc = scene.desc
    assert desc.warnings == []
    assert desc.camera.crop[2] == 256 and desc.camera.crop[3] == 256 and desc.camera.spp == 16
    assert desc.integrator.type == "path"

    side = json.loads(path.with_suffix(".json").read_text())
    assert set(side) == {"name", "description", "chains", "series", "caustic_box", "reference"} | (
        {"reference_fill"} if path.stem == "sphere_point" else set())
    assert side["name"] == path.stem
    assert isinstance(side["description"], str) and side["description"]
    assert isinstance(side["reference"], str) and side["reference"]
    assert side["reference"].split(":")[0] in ("mitsuba path", "mitsuba ptracer", "mitsuba ptracer+path",
                                               "mpg long run")
    assert all(re.fullmatch(r"[RT]+", c) for c in side["chains"])
    if side["series"] is not None:
        assert set(side["series"]) == {"name", "value"} and side["series"]["name"] in SERIES
        assert path.stem.startswith(side["series"]["name"] + "_")
    box = side["caustic_box"]
    if not side["chains"]:
        assert box is None
    else:
        assert len(box) == 4 and all(0.0 <= v <= 1.0 for v in box)
        assert box[0] < box[2] and box[1] < box[3]
        # hints: a caster and an emitter are marked
        assert any("caustic_caster_multi" in s.hints for s in desc.shapes)
        emitter_hints = [e.hints for e in desc.emitters] + [s.emitter.hints for s in desc.shapes if s.emitter]
        assert any("caustic_emitter_multi" in h for h in emitter_hints)


@pytest.mark.parametrize("path", XMLS, ids=[p.stem for p in XMLS])
def test_scene_renders(path):
    img = mpg.render(mpg.load_file(path, res="32"), spp=2, progress=False)
    assert img.rgb.shape == (32, 32, 3)
    assert np.isfinite(img.rgb).all()
    assert img.rgb.mean() > 0


def test_emitter_size_series_keeps_power(gen):
    powers = []
    for p in sorted(EVAL.glob("emitter_size_*.xml")):
        d = mpg.load_file(p).desc
        (light,) = [s for s in d.shapes if s.emitter is not None]
        radiance = float(np.mean(light.emitter.params["radiance"]))
        radius = json.loads(p.with_suffix(".json").read_text())["series"]["value"]
        powers.append(radiance * math.pi * radius ** 2)
    radii = [json.loads(p.with_suffix(".json").read_text())["series"]["value"]
             for p in EVAL.glob("emitter_size_*.xml")]
    assert max(radii) / min(radii) >= 99
    assert np.allclose(powers, powers[0], rtol=1e-4)


@pytest.mark.parametrize("path", XMLS, ids=[p.stem for p in XMLS])
def test_scene_loads_in_mitsuba(gen, path):
    pytest.importorskip("mitsuba")
    scene = gen.load_mitsuba(str(path), res="32")
    assert len(scene.shapes()) >= 2 and len(scene.emitters()) >= 1
