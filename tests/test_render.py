"""End-to-end renders against closed forms, determinism and the render loop.

Statistical checks use z-scores against the renderer's own per-pixel variance
estimate; each states its threshold. Pixels are independent (box filter).
"""

from __future__ import annotations

import numpy as np
import pytest

import mpg

CAMERA_DOWN = """
    <sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <transform name="to_world">
            <lookat origin="0, {h}, 0" target="0, 0, 0" up="0, 0, -1"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="{res}"/><integer name="height" value="{res}"/>
            <rfilter type="box"/>
        </film>
    </sensor>
"""


def scene_xml(body: str, integrator: str = '<integrator type="path"/>', fov=40, h=4.0, res=32):
    return (f'<scene version="3.0.0">{integrator}{CAMERA_DOWN.format(fov=fov, h=h, res=res)}'
            f"{body}</scene>")


def zscore_region(img: mpg.Image, expected: np.ndarray, sl=np.s_[:, :]) -> float:
    """z of the region mean of the image against the expected region mean."""
    a = img.rgb[sl].astype(np.float64)
    n = a[..., 0].size
    se = np.sqrt(img.variance[sl].astype(np.float64).sum(axis=(0, 1))) / n
    diff = a.mean(axis=(0, 1)) - expected[sl].mean(axis=(0, 1))
    return float(np.max(np.abs(diff) / np.maximum(se, 1e-12)))


def test_white_furnace_diffuse_and_glass():
    """A convex diffuse object of albedo rho in a uniform environment of radiance 1
    reflects exactly rho; a lossless glass sphere returns exactly 1 (the eta^2
    radiance scaling cancels on the way in and out). The glass sphere sees the
    diffuse one, so the two are rendered as separate scenes (the diffuse one may
    see the glass: it returns exactly 1, like the environment). |z| < 5 (p < 6e-7)."""
    body = """
      <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
      <shape type="sphere"><point name="center" x="-0.8" y="0" z="0"/><float name="radius" value="0.7"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf></shape>
      <shape type="sphere"><point name="center" x="0.8" y="0" z="0"/><float name="radius" value="0.7"/>
        <bsdf type="dielectric"><float name="int_ior" value="1.5"/></bsdf></shape>
    """
    xml = scene_xml(body, integrator='<integrator type="path"><integer name="max_depth" value="-1"/>'
                    '<integer name="rr_depth" value="100"/></integrator>', fov=60, h=3.0, res=64)
    sc = mpg.load_string(xml)
    img = mpg.render(sc, spp=64, progress=False)
    assert img.stats["rejected_samples"] == 0
    glass_only = mpg.load_string(xml.replace('value="0.7"/></bsdf>', 'value="0.7"/></bsdf>'
                                             '<transform name="to_world"><translate y="-50"/></transform>'))
    img_g = mpg.render(glass_only, spp=64, progress=False)
    # pixel centres of the camera looking down -y: left sphere covers x < 0 in world
    # (image x to the right maps to world +x with up = -z).
    q = sc.core.intersect
    rho = np.zeros((64, 64, 3))
    mask_d = np.zeros((64, 64), bool)
    mask_g = np.zeros((64, 64), bool)
    t = np.tan(np.radians(30))
    for j in range(64):
        for i in range(64):
            x = (2 * (i + 0.5) / 64 - 1) * t
            y = (2 * (j + 0.5) / 64 - 1) * t
            hit = q([0, 3, 0], [x, -1, y])
            # only pixels well inside a sphere (all of the pixel footprint covered)
            if hit["valid"] and hit["ng"][1] > 0.5:
                if hit["p"][0] < 0:
                    mask_d[j, i] = True
                else:
                    mask_g[j, i] = True
    rho[mask_d] = 0.7
    rho[mask_g] = 1.0
    rho[~(mask_d | mask_g)] = 1.0  # background sees the environment
    assert mask_d.sum() > 50 and mask_g.sum() > 50
    for m, im in ((mask_d, img), (mask_g, img_g)):
        a = im.rgb[m].astype(np.float64)
        se = np.sqrt(im.variance[m].astype(np.float64).sum(axis=0)) / len(a)
        z = np.abs(a.mean(axis=0) - rho[m].mean(axis=0)) / se
        assert np.all(z < 5), (a.mean(axis=0), rho[m].mean(axis=0), se)


def _pixel_dirs(res, fov, sub=8):
    """World directions of a camera at (0, h, 0) looking down with up = -z,
    sub x sub points per pixel (for the pixel-footprint average)."""
    t = np.tan(np.radians(fov) / 2)
    off = (np.arange(sub) + 0.5) / sub
    px = (np.arange(res)[:, None] + off[None, :]).ravel()
    sx = (2 * px / res - 1) * t   # image x -> world +x
    X, Y = np.meshgrid(sx, sx)    # image y -> world +z
    return X, Y


def test_point_light_over_diffuse_plane_closed_form():
    """Irradiance from a point light: E = I cos(theta) / d^2, radiance rho E / pi.
    The per-pixel expectation is the average over the pixel footprint
    (8x8 quadrature). Region z-scores |z| < 5 (p < 6e-7 each, 17 regions)."""
    I, rho, hl, res, fov, hc = 10.0, 0.6, 1.5, 32, 40, 4.0
    body = f"""
      <emitter type="point"><point name="position" x="0.3" y="{hl}" z="0.2"/>
        <rgb name="intensity" value="{I}"/></emitter>
      <shape type="rectangle"><transform name="to_world"><scale value="10"/>
        <rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="{rho}"/></bsdf></shape>
    """
    img = mpg.render(mpg.load_string(scene_xml(body, fov=fov, h=hc, res=res)), spp=64,
                     progress=False)
    X, Y = _pixel_dirs(res, fov)
    px, pz = X * hc, Y * hc   # ray (x, -1, y) from height hc hits y = 0 at (x*hc, y*hc)
    d2 = (px - 0.3) ** 2 + hl**2 + (pz - 0.2) ** 2
    L = rho / np.pi * I * (hl / np.sqrt(d2)) / d2
    exp = L.reshape(res, 8, res, 8).mean(axis=(1, 3))
    expected = np.repeat(exp[:, :, None], 3, axis=2)
    assert zscore_region(img, expected) < 5
    for i in range(4):
        for j in range(4):
            sl = np.s_[i * 8:(i + 1) * 8, j * 8:(j + 1) * 8]
            assert zscore_region(img, expected, sl) < 5
    # The point light makes the direct term deterministic per position: the
    # pixel error is only the footprint quadrature, so check it tightly too.
    assert np.max(np.abs(img.rgb[..., 0] - exp) / exp) < 0.02


def test_disk_light_on_axis_irradiance():
    """On the axis of a parallel disk light of radius r at height h:
    E = pi L r^2 / (r^2 + h^2). Checked on the central 4x4 pixels (footprint
    small, variation < 0.1%), |z| < 5 with MIS of NEE and BSDF sampling."""
    Le, r, h, rho = 5.0, 0.5, 1.0, 0.5
    body = f"""
      <shape type="disk"><transform name="to_world"><scale value="{r}"/>
        <rotate x="1" angle="90"/><translate y="{h}"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="{Le}"/></emitter></shape>
      <shape type="rectangle"><transform name="to_world"><scale value="10"/>
        <rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="{rho}"/></bsdf></shape>
    """
    # camera below the light looking down would be blocked by the disk: look from
    # the side through a narrow fov at the point under the disk centre.
    xml = f"""<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="2"/></integrator>
      <sensor type="perspective"><float name="fov" value="0.5"/>
        <transform name="to_world"><lookat origin="0, 0.3, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
        <rfilter type="box"/></film></sensor>{body}</scene>"""
    img = mpg.render(mpg.load_string(xml), spp=4096, progress=False)
    E = np.pi * Le * r**2 / (r**2 + h**2)
    # the disk is tessellated (256 segments): its area is low by (1 - sinc) ~ 1e-4
    expected = np.full((16, 16, 3), rho / np.pi * E)
    assert zscore_region(img, expected, np.s_[6:10, 6:10]) < 5


@pytest.mark.parametrize("integ", ["path", "sms_star"])
def test_small_area_light_far_off_axis_is_not_self_shadowed(integ):
    """A small light (0.2 x 0.2, facing down at height 1) lighting floor points
    2-3 units away, coordinates above 1: the shadow ray starts 1e-4 * |p| off
    the floor, and along the direction from the unshifted point it met the
    light's plane short of the sampled point by more than the shadow margin,
    so the light shadowed itself there (black pixels until 2026-12-04, where
    Mitsuba 3 lights them). Pixel values against rho/pi * Le * int dA / r^4
    (cos_l = cos_p = 1/r), midpoint rule over 16 x 16 nodes, |z| < 5."""
    Le, rho = 20.0, 0.5
    xml = f"""<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="2"/></integrator>
      <sensor type="perspective"><float name="fov" value="30"/>
        <transform name="to_world"><lookat origin="-1.4, 4, 0" target="-1.4, 0, 0" up="0, 0, -1"/></transform>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/>
        <rfilter type="box"/></film></sensor>
      <shape type="rectangle"><transform name="to_world"><scale value="10"/><rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="{rho}"/></bsdf></shape>
      <shape type="rectangle"><transform name="to_world"><scale value="0.1"/><rotate x="1" angle="90"/>
        <translate x="0.8" y="1" z="1"/></transform><bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="{Le}"/></emitter></shape></scene>"""
    img = mpg.render(mpg.load_string(xml), integrator=integ, spp=256, seed=2, progress=False)
    # the floor point of each sub-pixel (camera at height 4 over x = -1.4, up = -z)
    t = np.tan(np.radians(15))
    sub = 8
    s = ((np.arange(8)[:, None] + (np.arange(sub) + 0.5)[None, :] / sub).ravel() * 2 / 8 - 1) * t * 4
    X, Z = np.meshgrid(s - 1.4, s)
    q = (np.arange(16) + 0.5) / 16 * 0.2 - 0.1
    E = np.zeros_like(X)
    for qx in q:
        for qz in q:
            E += Le * (0.2 / 16) ** 2 / ((X - 0.8 - qx) ** 2 + 1 + (Z - 1 - qz) ** 2) ** 2
    exp = (rho / np.pi * E).reshape(8, sub, 8, sub).mean(axis=(1, 3))
    a = img.rgb[..., 0].astype(np.float64)
    z = (a - exp) / np.sqrt(img.variance[..., 0].astype(np.float64))
    assert np.abs(z).max() < 5, np.abs(z).max()
    assert a.min() > 0.5 * exp.min()   # (the self-shadowed pixels were 0)


def test_bit_identical_across_thread_counts():
    sc = mpg.load_file(mpg.default_scene_path(), res_x="48", res_y="32")
    a = mpg.render(sc, spp=8, threads=1, seed=3, progress=False)
    b = mpg.render(sc, spp=8, threads=2, seed=3, progress=False)
    c = mpg.render(sc, spp=8, threads=5, seed=3, progress=False)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.rgb, c.rgb)
    assert np.array_equal(a.variance, c.variance)
    d = mpg.render(sc, spp=8, threads=2, seed=4, progress=False)
    assert not np.array_equal(a.rgb, d.rgb)


def test_a_pass_result_outlives_its_job_and_can_be_read_twice():
    """RenderJob.result()'s arrays are views of the job's buffers (no copy):
    they keep the job alive, so they stay valid after the job is dropped, and
    a second result() gives the same arrays (the sub-path buffer is moved
    out by the first); a pass still running has no result."""
    import gc
    import weakref

    from mpg import _core
    sc = mpg.load_file(mpg.default_scene_path(), res_x="24", res_y="16")
    integ = _core.make_integrator(sc.core, "path", dict(sc.desc.integrator.params))
    job = _core.RenderJob(sc.core, integ, 4, 1, 0, 1)
    while not job.wait(1.0):
        pass
    r1, r2 = job.result(), job.result()
    assert r1["sum"].shape == (16, 24, 3) and r1["sum_sq"].shape == (16, 24, 3)
    assert not r1["sum"].flags.owndata   # (a view, not a copy)
    assert np.array_equal(r1["sum"], r2["sum"]) and np.array_equal(r1["sum_sq"], r2["sum_sq"])
    expected = np.array(r1["sum"])
    assert expected.sum() > 0
    alive = weakref.ref(job)
    del job, r2
    gc.collect()
    _ = [np.ones(16 * 24 * 3) for _ in range(100)]   # (freed memory would be reused)
    assert np.array_equal(r1["sum"], expected) and alive() is not None
    del r1
    gc.collect()
    assert alive() is None   # (the last view gone, the job goes too)
    # A running pass's buffers are still being written: no result yet.
    running = _core.RenderJob(sc.core, integ, 100_000, 1, 0, 1)
    try:
        with pytest.raises(RuntimeError, match="still running"):
            running.result()
    finally:
        running.cancel()
        running.wait(60.0)


def test_time_budget_stops_and_keeps_passes():
    sc = mpg.load_file(mpg.default_scene_path(), res_x="64", res_y="48")
    img = mpg.render(sc, time=1.0, progress=False)
    assert img.spp >= 1
    assert img.stats["seconds"] < 2.5
    assert np.isfinite(img.rgb).all()
    # the work of a pass the limit cut is reported (and can only be part of the budget)
    assert 0.0 <= img.stats["seconds_dropped"] <= img.stats["seconds"]
    # the passes' own wall time, the dropped one's too; the loop's is the rest
    assert img.stats["seconds_dropped"] <= img.stats["seconds_passes"] <= img.stats["seconds"]
    assert img.stats["seconds_passes"] > 0.5


def test_time_limited_pass_sizes():
    """Half of what is left, at most an eighth of the budget, at least 1 spp,
    never above the schedule's k; without an estimate the schedule's k."""
    from mpg.render import time_limited_pass_spp
    assert time_limited_pass_spp(32, 1.6, 2.0, None) == 32
    assert time_limited_pass_spp(32, 1.6, 2.0, 0.02) == 12    # 2 / 8 = 0.25 s at 20 ms
    assert time_limited_pass_spp(32, 0.1, 2.0, 0.02) == 2     # 0.05 s left to use
    assert time_limited_pass_spp(32, 0.01, 2.0, 0.02) == 1
    assert time_limited_pass_spp(4, 1.6, 2.0, 0.001) == 4


def test_a_seconds_per_spp_estimate_sizes_the_first_timed_pass():
    """With a time budget the estimate sizes the first pass (an estimate of
    1 us per spp: the schedule's cap, 32 spp, which always finishes); with an
    spp budget it is ignored and the image is the one without it; mpg passes
    one from its training."""
    sc = mpg.load_file(mpg.default_scene_path(), res_x="16", res_y="12")
    img = mpg.render(sc, integrator="path", time=0.5, seconds_per_spp=1e-6, progress=False)
    assert img.spp >= 32 and img.stats["seconds_per_spp_hint"] == 1e-6
    plain = mpg.render(sc, integrator="path", time=0.2, progress=False)
    assert plain.stats["seconds_per_spp_hint"] == 0.0
    a = mpg.render(sc, integrator="path", spp=5, seconds_per_spp=1e-6, progress=False)
    b = mpg.render(sc, integrator="path", spp=5, progress=False)
    assert a.stats["passes"] == b.stats["passes"] == 4 and np.array_equal(a.rgb, b.rgb)
    assert a.stats["seconds_per_spp_hint"] == 0.0
    # mpg hands its render twice its training's seconds per spp
    m = mpg.render(sc, integrator="mpg", time=1.0, progress=False)
    assert m.stats["spp_training"] > 0 and m.stats["seconds_per_spp_hint"] > 0.0


def test_variance_estimate_is_calibrated():
    """The per-pixel variance of the mean predicts the spread between two
    independent renders: mean of (a-b)^2 / (va+vb) is 1 (chi-square/n, n = 3072
    pixel-channels; accept 0.85..1.15, > 5 sigma of its sampling spread for
    light-tailed pixels)."""
    sc = mpg.load_string(scene_xml("""
      <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
      <shape type="rectangle"><transform name="to_world"><scale value="10"/><rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>""", res=32))
    a = mpg.render(sc, spp=64, seed=1, progress=False)
    b = mpg.render(sc, spp=64, seed=2, progress=False)
    r = ((a.rgb - b.rgb) ** 2 / (a.variance + b.variance)).mean()
    assert 0.85 < r < 1.15


def test_unknown_integrator_is_a_clear_error():
    sc = mpg.load_file(mpg.default_scene_path(), res_x="8", res_y="8")
    with pytest.raises(mpg.RenderError, match="unknown integrator 'bdpt'"):
        mpg.render(sc, integrator="bdpt", spp=1, progress=False)


@pytest.mark.parametrize("kw", [{"spp": 0}, {"time": -1.0}, {"threads": 0}])
def test_bad_render_arguments(kw):
    sc = mpg.load_file(mpg.default_scene_path(), res_x="8", res_y="8")
    with pytest.raises(mpg.RenderError):
        mpg.render(sc, progress=False, **kw)


def test_a_budget_shorter_than_one_pass_still_gives_an_image():
    """A time limit below one pass's time finishes that first pass (1 spp)
    instead of returning an empty image; a later pass cut by the limit is
    dropped whole and stops within a sample, not a tile."""
    sc = mpg.load_file(mpg.default_scene_path(), res_x="64", res_y="48")
    img = mpg.render(sc, integrator="sms_star", time=1e-3, progress=False)
    assert img.spp >= 1 and img.stats["time_limited"]
    assert np.isfinite(img.rgb).all() and img.rgb.max() > 0


def test_ctrl_c_between_passes_keeps_the_image(scenes_dir, monkeypatch):
    """Ctrl-C that lands between two passes (here: while the third pass's job
    is created) used to escape the loop as a KeyboardInterrupt and lose the
    image (a CI run of the Ctrl-C CLI test hit it). Now the interrupt sets a
    flag the loop checks: the render returns the finished passes, marked
    interrupted, and the signal handler is restored afterwards."""
    import os
    import signal

    from mpg import _core

    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="8")
    real = _core.RenderJob
    made = []

    def job(*a, **kw):
        made.append(1)
        if len(made) == 3:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):   # bytecodes: the Python-level handler runs here
                pass
        return real(*a, **kw)

    monkeypatch.setattr(_core, "RenderJob", job)
    # (the handler before the render: Python's default_int_handler, or SIG_IGN
    # when the test process was started in the background by a shell without
    # job control, which then leaves SIGINT ignored)
    before = signal.getsignal(signal.SIGINT)
    img = mpg.render(sc, integrator="path", spp=1000, seed=1, progress=False)
    assert img.stats["interrupted"] is True
    # passes of 1, 1, 2 spp: the third, started as the flag was set, is kept
    # when it finished before the loop looked (a finished pass is never lost)
    assert (img.stats["passes"], img.spp) in ((2, 2), (3, 4)) and np.isfinite(img.rgb).all()
    assert signal.getsignal(signal.SIGINT) is before


# --- camera_delta: the light seen from the camera through delta scattering only


@pytest.mark.parametrize("integ", ["path", "sms_star"])
def test_camera_delta_splits_the_image_path_by_path(scenes_dir, integ):
    """exclude + only = all, sample by sample (same seed, same random numbers):
    every path is in exactly one of the two. On the eval sphere the camera sees
    the light refracted and reflected in the glass, so `only` is not empty, and
    it ends its paths at the first diffuse vertex."""
    sc = mpg.load_file(scenes_dir / "eval" / "sphere.xml", res=64)
    spp = 64 if integ == "path" else 32
    ims = {m: mpg.render(sc, {"type": integ, "camera_delta": m}, spp=spp, seed=3, progress=False)
           for m in ("all", "exclude", "only")}
    a, e, o = (ims[m].rgb.astype(np.float64) for m in ("all", "exclude", "only"))
    assert np.abs(a - e - o).max() <= 1e-5 * max(1.0, np.abs(a).max())
    lit = o.sum(axis=2) > 0
    assert 0 < lit.sum() < 0.01 * lit.size        # a few pixels: the light's images in the glass
    assert (np.abs(a - e).sum(axis=2) > 0).sum() == lit.sum()
    assert ims["only"].stats["shadow_rays"] == 0 and ims["only"].stats.get("chain_estimates", 0) == 0
    assert ims["only"].stats["path_vertices"] < ims["all"].stats["path_vertices"]


def test_camera_delta_bad_value_is_a_clear_error(scenes_dir):
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res=8)
    with pytest.raises(Exception, match="camera_delta must be all, exclude or only"):
        mpg.render(sc, {"type": "path", "camera_delta": "some"}, spp=1, progress=False)
