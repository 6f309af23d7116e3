"""The stratified sampler: pixel positions from a per-pixel randomly shifted
Sobol (0,2)-sequence (cpp/core/rng.h shifted_sobol_2d, render.py `sampler`).

What must hold: every block of 2^m points is a (0,m,2)-net whatever the shift
(the stratification), each render stays unbiased (compared with the
independent sampler over many seeds), an edge pixel's variance falls, the
image does not depend on the thread count, and the scene's <sampler> picks it.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import mpg
from mpg import _core


@settings(max_examples=60, deadline=None)
@given(m=st.integers(0, 10), block=st.integers(0, 1 << 12),
       shift0=st.integers(0, 2**32 - 1), shift1=st.integers(0, 2**32 - 1))
def test_every_dyadic_block_is_a_net(m, block, shift0, shift1):
    """Points [b 2^m, (b+1) 2^m) put exactly one point in each of the 2^m
    elementary intervals 2^-j x 2^-(m-j), for every j (t = 0), and the shift
    keeps it."""
    n = 1 << m
    u = _core.sobol_2d(n, start=block * n, shift0=shift0, shift1=shift1).astype(np.float64)
    assert u.shape == (n, 2)
    assert np.all((u >= 0.0) & (u < 1.0))
    for j in range(m + 1):
        cx = np.floor(u[:, 0] * (1 << j)).astype(np.int64)
        cy = np.floor(u[:, 1] * (1 << (m - j))).astype(np.int64)
        cells = cx * (1 << (m - j)) + cy
        assert np.array_equal(np.sort(cells), np.arange(n)), (m, j)


def test_a_shifted_point_is_uniform():
    """Point i alone, over random shifts, is uniform on [0,1)^2: chi-square over
    an 8 x 8 grid from 64 000 shifts, 63 degrees of freedom, threshold 120
    (p ~ 2e-5)."""
    rng = np.random.default_rng(7)
    counts = np.zeros((8, 8))
    for s0, s1 in rng.integers(0, 2**32, size=(64_000, 2), dtype=np.uint64):
        u = _core.sobol_2d(1, start=5, shift0=int(s0), shift1=int(s1))[0]
        counts[int(u[0] * 8), int(u[1] * 8)] += 1
    chi2 = float(((counts - 1000.0) ** 2 / 1000.0).sum())
    assert chi2 < 120.0, chi2


def test_bad_arguments():
    with pytest.raises(ValueError):
        _core.sobol_2d(-1)
    with pytest.raises(ValueError):
        _core.sobol_2d(4, start=2**32 - 2)


# A camera looking straight down at an emitting half-plane whose edge crosses
# the 8 x 8 image at 20 degrees: an edge pixel's value is the covered fraction
# of its footprint, which only the pixel position decides.
EDGE = """<scene version="3.0.0">
  <integrator type="path"/>
  <sensor type="perspective">
    <float name="fov" value="30"/>
    <transform name="to_world"><lookat origin="0, 4, 0" target="0, 0, 0" up="0, 0, -1"/></transform>
    <sampler type="{sampler}"><integer name="sample_count" value="16"/></sampler>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world">
      <scale value="10"/><rotate x="1" angle="-90"/><translate x="10"/><rotate y="1" angle="20"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="1"/></emitter>
  </shape>
</scene>"""


def _renders(sampler: str, spp: int, seeds: range) -> np.ndarray:
    sc = mpg.load_string(EDGE.format(sampler="independent"))
    return np.stack([mpg.render(sc, spp=spp, seed=s, progress=False, sampler=sampler).rgb[..., 0]
                     for s in seeds]).astype(np.float64)


def test_stratified_is_unbiased_and_lowers_an_edge_pixels_variance():
    """96 seeds of each sampler. Unbiased: per pixel, the mean over seeds of the
    stratified renders agrees with the independent ones' within |z| < 4.5
    (64 pixels, p < 5e-4 for the image), at 12 spp, which the passes 1, 1, 2, 4,
    4 cut off mid-block. Stratified: at 16 spp the summed variance over seeds of
    the edge pixels is below half the independent sampler's (an edge's is
    expected near 16^-1/2 of it, ~0.25; the 96-seed estimate of the ratio has a
    relative error near 0.2)."""
    seeds = range(96)
    for spp in (12, 16):
        ind = _renders("independent", spp, seeds)
        strat = _renders("stratified", spp, seeds)
        se = np.sqrt(ind.var(axis=0, ddof=1) / len(seeds) + strat.var(axis=0, ddof=1) / len(seeds))
        diff = np.abs(strat.mean(axis=0) - ind.mean(axis=0))
        edge = (ind.mean(axis=0) > 0.05) & (ind.mean(axis=0) < 0.95)
        assert edge.sum() >= 6, "the edge should cross several pixels"
        assert np.all(diff[edge] < 4.5 * se[edge]), (spp, (diff / np.maximum(se, 1e-12))[edge])
        if spp == 16:
            ratio = strat[:, edge].var(axis=0, ddof=1).sum() / ind[:, edge].var(axis=0, ddof=1).sum()
            assert ratio < 0.5, ratio


def test_stratified_image_does_not_depend_on_threads_and_continues_across_passes():
    # 48 x 48 pixels: 9 tiles, so two threads really share the image.
    xml = EDGE.format(sampler="independent").replace('value="8"/>', 'value="48"/>')
    sc = mpg.load_string(xml)
    a = mpg.render(sc, spp=9, seed=3, threads=1, progress=False, sampler="stratified")
    b = mpg.render(sc, spp=9, seed=3, threads=2, progress=False, sampler="stratified")
    assert np.array_equal(a.rgb, b.rgb)
    assert a.stats["sampler"] == "stratified" and a.stats["passes"] == 5   # 1, 1, 2, 4, 1 spp
    # The passes continue one sequence per pixel: the same 9 points as one
    # pass of 9 samples (a pixel's value here is decided by its positions
    # alone -- the light or nothing -- so the images are equal).
    integ = _core.make_integrator(sc.core, "path", dict(sc.desc.integrator.params))
    job = _core.RenderJob(sc.core, integ, 9, 3, 0, 1, stratify=True, sample_offset=0)
    while not job.wait(1.0):
        pass
    one = np.asarray(job.result()["sum"]).reshape(a.rgb.shape) / 9.0
    assert np.allclose(one, a.rgb, rtol=0, atol=1e-6)
    # Restarting the sequence in each pass would repeat points 0..: not these.
    job = _core.RenderJob(sc.core, integ, 9, 3, 0, 1, stratify=True, sample_offset=1)
    while not job.wait(1.0):
        pass
    shifted = np.asarray(job.result()["sum"]).reshape(a.rgb.shape) / 9.0
    assert not np.allclose(shifted, a.rgb, rtol=0, atol=1e-6)
    # Another seed shifts the sequences: a different image.
    c = mpg.render(sc, spp=9, seed=4, threads=1, progress=False, sampler="stratified")
    assert not np.array_equal(a.rgb, c.rgb)


@pytest.mark.parametrize("kind", ["stratified", "multijitter", "ldsampler", "orthogonal",
                                  "low_discrepancy"])
def test_scene_sampler_picks_it(kind):
    sc = mpg.load_string(EDGE.format(sampler=kind))
    assert sc.desc.camera.sampler == "stratified"
    assert not any("sampler" in w for w in sc.desc.warnings)
    img = mpg.render(sc, spp=2, progress=False)
    assert img.stats["sampler"] == "stratified"
    img = mpg.render(sc, spp=2, progress=False, sampler="independent")
    assert img.stats["sampler"] == "independent"


def test_unknown_sampler_is_an_error():
    sc = mpg.load_string(EDGE.format(sampler="independent"))
    with pytest.raises(mpg.RenderError, match="sampler"):
        mpg.render(sc, spp=1, progress=False, sampler="sobol")
    with pytest.raises(mpg.SceneError, match="unsupported sampler 'halton'"):
        mpg.load_string(EDGE.format(sampler="halton"))
