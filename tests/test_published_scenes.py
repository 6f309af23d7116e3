"""Every scene file published with the SMS and MPG papers loads (missing
textures substituted) and renders a few spp without error, NaN or Inf.

The papers' own integrators (path_sms_ss, manifold_path_guiding, ...) are not
available yet; the render uses `path` with the scene's max_depth (the loader
and renderer say so in a warning). The whole view is rendered at a reduced
film size (64 pixels on the longer side) to keep the test fast.
"""

from __future__ import annotations

import numpy as np
import pytest

import mpg

from conftest import shared_dir

PUBLISHED = shared_dir() / "published-scenes"
FILES = sorted(PUBLISHED.rglob("*.xml")) if PUBLISHED.is_dir() else []
EXTRA = {"Figure_17_Roughness": {"alpha": "0.1"}}


def _params(path):
    for key, val in EXTRA.items():
        if key in str(path):
            return val
    return {}


@pytest.mark.skipif(not FILES, reason="shared/published-scenes not present")
@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(PUBLISHED)) for p in FILES])
def test_published_scene_renders(path):
    sc = mpg.load_file(path, substitute_missing_textures=True, **_params(path))
    cam = sc.desc.camera
    s = 64 / max(cam.width, cam.height)
    cam.width, cam.height = max(1, round(cam.width * s)), max(1, round(cam.height * s))
    cam.crop = (0, 0, cam.width, cam.height)
    img = mpg.render(sc, integrator="path", spp=4, progress=False)
    assert img.rgb.shape == (cam.crop[3], cam.crop[2], 3)
    assert np.isfinite(img.rgb).all()
    assert img.stats["rejected_samples"] <= img.stats["samples"] * 1e-3
    assert img.rgb.max() > 0.0, "a published scene rendered black"
