"""Light tracing of the point and spot lights' caustics at the camera's first
hit (integrators/light_trace.h, `light_trace` photons per camera sample):
closed forms (a mirror, a spot's falloff, refraction through a slab), the
partition with the chain estimator (paths seen through glass stay the
estimator's, bit for bit), determinism, the cases it declines, bad values.
z-tests at |z| < 5 (p < 6e-7 per comparison)."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

import mpg
from mpg import _core
from test_chains import (SLAB_POINT, _fresnel, mirror_expected, mirror_floor_points, mirror_scene,
                         spot_mirror_expected, spot_mirror_scene, swept_solid_angle)
from test_manifold import _slab_path


@pytest.mark.parametrize("which", ["point", "spot"])
@pytest.mark.parametrize("integ", [{"type": "sms", "tau": "R"}, {"type": "sms_star"}])
def test_light_traced_mirror_caustic_matches_the_closed_form(which, integ):
    """The floor lit by a point (spot) light and its mirror image, seen
    directly: with light tracing the mirror's light comes from photons only
    (the estimator skips every chain to the light, contributes nothing), and
    every pixel and the image mean match the closed form of test_chains."""
    sc = mpg.load_string(mirror_scene() if which == "point" else spot_mirror_scene())
    exp = mirror_expected() if which == "point" else spot_mirror_expected()
    img = mpg.render(sc, integrator=dict(integ, light_trace=16), spp=64, seed=3, progress=False)
    st = img.stats
    assert st["lt_photons"] == 16 * 64 * 24 * 24
    assert st["lt_splats"] > 20 * 24 * 24 and st["chain_lt_skipped"] > 0
    assert st["chain_contributions"] == 0 and st["rejected_samples"] == 0 and st["lt_rejected"] == 0
    a = img.rgb[..., 0].astype(np.float64)
    var = img.variance[..., 0].astype(np.float64)
    lit = exp > 1e-6
    z = (a[lit] - exp[lit]) / np.sqrt(var[lit])
    assert np.abs(z).max() < 5, np.abs(z).max()
    assert abs(a.mean() - exp.mean()) / (np.sqrt(var.sum()) / a.size) < 5
    # (the spot: its falloff edge runs through the image, test_chains)
    assert np.all(a[~lit] < 1e-3)


def pixel_means(radiance, o, target, up, res=8, sub=4, fov=30.0):
    """Each pixel's mean of radiance(d) over sub x sub sub-pixel rays d (unit)
    of a camera at o looking at target (Mitsuba's lookat frame and film: x
    right, y down)."""
    fwd = (target - o) / np.linalg.norm(target - o)
    left = np.cross(up, fwd)
    left /= np.linalg.norm(left)
    upv = np.cross(fwd, left)
    t = np.tan(np.radians(fov / 2))
    out = np.zeros((res, res))
    for j in range(res):
        for i in range(res):
            acc = 0.0
            for sj in range(sub):
                for si in range(sub):
                    fx, fy = i + (si + 0.5) / sub, j + (sj + 0.5) / sub
                    d = fwd - left * (2 * fx / res - 1) * t - upv * (2 * fy / res - 1) * t
                    acc += radiance(d / np.linalg.norm(d))
            out[j, i] = acc / sub**2
    return out


def floor_below_refraction(o, d, eta, y_top, y_bottom):
    """Where the ray o + t d, refracted into a medium of index eta between
    y_top and y_bottom (flat faces), meets the floor y = 0 (air below
    y_bottom when y_bottom > 0), and cos(theta) in the air above."""
    c = -d[1]
    s = np.sqrt(1 - c * c)
    sw = s / eta
    h = np.array([d[0], 0, d[2]]) / max(s, 1e-12)
    horiz = s / c * ((o[1] - y_top) + y_bottom) + sw / np.sqrt(1 - sw * sw) * (y_top - y_bottom)
    return np.array([o[0], 0.0, o[2]]) + h * horiz, c


# The slab of test_chains seen from below it: the camera sees the floor
# directly, the point light's light reaches it through the slab (TT).
SLAB_BELOW = SLAB_POINT.replace('<integer name="max_depth" value="6"/>', '<integer name="max_depth" value="4"/>').replace(
    '<lookat origin="0.6, 5, 0.2" target="0.6, 0, 0.2" up="0, 0, -1"/>',
    '<lookat origin="0.9, 0.5, 1.4" target="0.6, 0, 0.2" up="0, 1, 0"/>').replace(
    '<float name="fov" value="6"/>', '<float name="fov" value="30"/>')


def _slab_below_expected(res=8, sub=4, fov=30.0):
    """rho/pi I (1 - F)^2 |d omega_L / dA_D| at the floor point of each
    sub-pixel ray (parallel faces: omega_L = -omega_D; max_depth 4 leaves only
    TT; the slab shadows the light's direct light), averaged per pixel."""
    eta, y0, y1, I, rho = 1.5, 0.75, 1.25, 10.0, 0.5
    xL, o = np.array([0.0, 2.5, 0.0]), np.array([0.9, 0.5, 1.4])

    def radiance(d):
        p = o + d * (-o[1] / d[1])
        w = _slab_path(p, xL, y0, y1, eta)
        G = swept_solid_angle(lambda q: _slab_path(q, xL, y0, y1, eta), p)
        return rho / np.pi * I * (1 - _fresnel(w[1], eta)) ** 2 * G

    return pixel_means(radiance, o, np.array([0.6, 0.0, 0.2]), np.array([0.0, 1.0, 0.0]), res, sub, fov)


def _sms_against(xml, tau, lt, seed, exp):
    """sms with letters tau and light_trace lt (128 spp without photons, 512
    with) against the closed form exp: every pixel and the mean within 5
    standard errors, the mean within 2 % (3 % with photons: 2.3 % above at
    128 spp in one run of the slab seen from below, z = 3.3; 0.4 %, z = 1.1,
    at 2048 spp: their tails are wider than the estimator's there)."""
    img = mpg.render(mpg.load_string(xml), integrator={"type": "sms", "tau": tau, "light_trace": lt},
                     spp=128 if lt == 0 else 512, seed=seed, progress=False)
    got = img.rgb[..., 0].astype(np.float64)
    var = img.variance[..., 0].astype(np.float64)
    assert (img.stats["lt_splats"] > 0) == (lt > 0)
    assert np.all(np.abs(got - exp) < 5 * np.sqrt(var)), (got, exp)
    assert abs(got.mean() - exp.mean()) / (np.sqrt(var.sum()) / got.size) < 5
    assert abs(got.mean() / exp.mean() - 1) < (0.02 if lt == 0 else 0.03)
    return img


@pytest.mark.parametrize("lt", [0, 64])
def test_slab_seen_from_below_matches_the_closed_form(lt):
    """Refraction twice (the eta^2 of the radiance-mode weights undone on the
    photon's side), against the independent 1D solution of the path: with the
    estimator alone (lt = 0) and with the light tracer (lt = 64: the slab's
    bound holds the light, so photons leave in all directions and few land in
    the view), per pixel and for the mean."""
    img = _sms_against(SLAB_BELOW, "TT", lt, 2, _slab_below_expected())
    assert (img.stats["chain_contributions"] > 0) == (lt == 0)


# The same, the light inside the slab (y = 1.0 between its faces 0.75 and
# 1.25): one refraction, light and floor in different media.
SLAB_INSIDE = SLAB_BELOW.replace('x="0" y="2.5" z="0"', 'x="0" y="1.0" z="0"')


def _slab_inside_expected(res=8, sub=4, fov=30.0):
    """rho/pi I (1 - F) |d omega_L / dA_D| with omega_L the direction in the
    glass at the light (flux through the interface is conserved: no eta^2),
    from the 1D solution of the path with the slab's top put at the light."""
    eta, y0, yl, I, rho = 1.5, 0.75, 1.0, 10.0, 0.5
    xL, o = np.array([0.0, yl, 0.0]), np.array([0.9, 0.5, 1.4])

    def glass_dir(p):   # the direction in the glass, toward the light
        w = _slab_path(p, xL, y0, yl, eta)
        h = np.array([w[0], 0.0, w[2]]) / eta
        return h + np.array([0.0, np.sqrt(1 - h @ h), 0.0])

    def radiance(d):
        p = o + d * (-o[1] / d[1])
        w = _slab_path(p, xL, y0, yl, eta)
        return rho / np.pi * I * (1 - _fresnel(w[1], eta)) * swept_solid_angle(glass_dir, p)

    return pixel_means(radiance, o, np.array([0.6, 0.0, 0.2]), np.array([0.0, 1.0, 0.0]), res, sub, fov)


@pytest.mark.parametrize("lt", [0, 64])
def test_light_inside_the_slab_matches_the_closed_form(lt):
    """A point light inside the glass, the floor outside it, one refraction
    (sms with tau = T: the light tracer takes that type only, the TR paths off
    the slab's top face stay out on both sides). Photons carry flux; the
    estimator's lobe weights drop the radiance's 1/eta^2 for a point light
    (ChainEstimator::kappa): both match E = I (1 - F) |d omega_L / dA_D|, which
    the radiance-mode weights would put eta^2 = 2.25 too low."""
    _sms_against(SLAB_INSIDE, "T", lt, 4, _slab_inside_expected())


# test_chains' slab seen from above, with a wider view and a slab of 8 x 8
# (so that sms_star's uniform seeds on it converge; the paths of the view
# stay inside it): the camera sees the floor through the slab only.
SLAB_ABOVE = SLAB_POINT.replace('<float name="fov" value="6"/>', '<float name="fov" value="40"/>').replace(
    '<scale x="30" y="0.25" z="30"/>', '<scale x="4" y="0.25" z="4"/>')


def _slab_above_expected(res=8, sub=4, fov=40.0):
    """T_cam rho/pi I (1 - F)^2 |d omega_L / dA_D| (test_chains' closed form)
    at the floor point of each sub-pixel ray, refracted twice on its way down,
    averaged per pixel."""
    eta, y0, y1, I, rho = 1.5, 0.75, 1.25, 10.0, 0.5
    xL, o = np.array([0.0, 2.5, 0.0]), np.array([0.6, 5.0, 0.2])

    def radiance(d):
        p, c = floor_below_refraction(o, d, eta, y1, y0)
        w = _slab_path(p, xL, y0, y1, eta)
        G = swept_solid_angle(lambda q: _slab_path(q, xL, y0, y1, eta), p)
        return (1 - _fresnel(c, eta)) ** 2 * rho / np.pi * I * (1 - _fresnel(w[1], eta)) ** 2 * G

    return pixel_means(radiance, o, np.array([0.6, 0.0, 0.2]), np.array([0.0, 0.0, -1.0]), res, sub, fov)


def _render_through(xml, integ, spp, seed, exp):
    """Render; with light_trace_through the photons' camera-side chains bring
    the light (more than 10 splats a pixel) and no estimate contributes,
    without it the estimator does. Returns the red channel, its variance and exp."""
    img = mpg.render(mpg.load_string(xml), integrator=integ, spp=spp, seed=seed, progress=False)
    got = img.rgb[..., 0].astype(np.float64)
    through = integ.get("light_trace_through", False)
    assert (img.stats["lt_chain_splats"] > 10 * got.size) == through
    assert (img.stats["chain_contributions"] == 0) == through
    return got, img.variance[..., 0].astype(np.float64), exp


@pytest.mark.parametrize("integ,spp", [({"type": "sms", "tau": "TT"}, 64),
                                       ({"type": "sms_star", "light_trace": 64, "light_trace_through": True}, 256)])
def test_slab_seen_from_above_matches_the_closed_form(integ, spp):
    """The caustic seen through glass: the estimator at the camera path's
    separator behind the slab (sms), or photons connected to the camera by a
    camera-side chain (light_trace_through: ChainEstimator::connect_point,
    kappa G K / P(m) with G = |d omega_c / dA_D|), which then takes those
    separators' point-light chains whole (no estimate contributes)."""
    got, var, exp = _render_through(SLAB_ABOVE, integ, spp, 1, _slab_above_expected())
    assert np.all(np.abs(got - exp) < 5 * np.sqrt(var)), (got, exp)
    assert abs(got.mean() - exp.mean()) / (np.sqrt(var.sum()) / got.size) < 5
    assert abs(got.mean() / exp.mean() - 1) < 0.03


# A floor under water (y = 0, the water from -0.5 to 1.0), seen from the air
# above through its surface; the point light in the air: the camera-side
# chain (m = 1) crosses from water to air, so the radiance's (eta_air /
# eta_water)^2 on the way to the camera matters.
WATER = SLAB_ABOVE.replace('<integer name="max_depth" value="6"/>', '<integer name="max_depth" value="4"/>').replace(
    '<scale x="4" y="0.25" z="4"/><translate y="1.0"/>', '<scale x="4" y="0.75" z="4"/><translate y="0.25"/>').replace(
    '<float name="int_ior" value="1.5"/>', '<float name="int_ior" value="1.333"/>')


def _water_expected(res=8, sub=4, fov=40.0):
    """T_cam (1/eta)^2 rho/pi I (1 - F) |d omega_L / dA_D|: the camera ray
    refracted into the water at y = 1 down to the floor; the light's path
    from the floor up through the surface (the 1D solution with the slab's
    bottom at the floor), omega_L in the air."""
    eta, I, rho = 1.333, 10.0, 0.5
    xL, o = np.array([0.0, 2.5, 0.0]), np.array([0.6, 5.0, 0.2])

    def radiance(d):
        p, c = floor_below_refraction(o, d, eta, 1.0, 0.0)
        w = _slab_path(p, xL, 0.0, 1.0, eta)
        G = swept_solid_angle(lambda q: _slab_path(q, xL, 0.0, 1.0, eta), p)
        return (1 - _fresnel(c, eta)) / eta**2 * rho / np.pi * I * (1 - _fresnel(w[1], eta)) * G

    return pixel_means(radiance, o, np.array([0.6, 0.0, 0.2]), np.array([0.0, 0.0, -1.0]), res, sub, fov)


@pytest.mark.parametrize("integ,spp", [({"type": "sms_star"}, 512),
                                       ({"type": "sms_star", "light_trace": 64, "light_trace_through": True}, 256)])
def test_floor_under_water_matches_the_closed_form(integ, spp):
    """The camera in the air, the floor and its caustic under water: the
    photons connected through the surface (m = 1: the camera-side chain's
    radiance scaling (eta_air / eta_water)^2 = 1/1.78) match the closed form
    per pixel and in the mean; the estimator (radiance-mode weights on the
    camera path, flux weights for the point light's chain) in the mean only:
    its uniform seeds on the water box rarely find the surface's chain (about
    one sample in 24 contributes), so many pixels have no contribution and no
    variance (measured: mean 6 % high, z = 1.0)."""
    got, var, exp = _render_through(WATER, integ, spp, 3, _water_expected())
    assert abs(got.mean() - exp.mean()) / (np.sqrt(var.sum()) / got.size) < 5
    if integ.get("light_trace_through", False):
        assert np.all(np.abs(got - exp) < 5 * np.sqrt(var)), (got, exp)
        assert abs(got.mean() / exp.mean() - 1) < 0.03
    else:   # (either side's eta^2 wrong would be 1.78x off)
        assert abs(got.mean() / exp.mean() - 1) < 0.2


def test_light_tracer_takes_only_the_types_sms_owns():
    """sms estimates one chain type; the photons of any other type are
    nobody's (the path tracer cannot reach a point light), so the light tracer
    drops them: a mirror makes only R, so with tau = T nothing is splatted."""
    sc = mpg.load_string(mirror_scene())
    img = mpg.render(sc, integrator={"type": "sms", "tau": "T", "light_trace": 4}, spp=8, seed=1, progress=False)
    assert img.stats["lt_photons"] > 0 and img.stats["lt_splats"] == 0 and img.stats["chain_lt_skipped"] > 0
    r = mpg.render(sc, integrator={"type": "sms", "tau": "R", "light_trace": 4}, spp=8, seed=1, progress=False)
    assert r.stats["lt_splats"] > 0


def test_two_lights_and_a_crop_window_match_the_closed_form():
    """Two point lights of different power (the light is picked by power: its
    probability divides the photon's flux) and a crop window (splats land at
    the crop's pixel indices): the window of the closed form, pixel by pixel."""
    xml = mirror_scene().replace(
        '<emitter type="point">',
        '<emitter type="point"><point name="position" x="0.5" y="1" z="0"/><rgb name="intensity" value="6"/></emitter>'
        '<emitter type="point">').replace(
        '<rfilter type="box"/>',
        '<rfilter type="box"/><integer name="crop_offset_x" value="5"/><integer name="crop_offset_y" value="9"/>'
        '<integer name="crop_width" value="14"/><integer name="crop_height" value="11"/>')
    sc = mpg.load_string(xml)
    img = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 64}, spp=64, seed=2, progress=False)
    assert img.rgb.shape[:2] == (11, 14)
    exp = (mirror_expected() + 2.0 * mirror_expected(lx=0.5))[9:20, 5:19]
    a = img.rgb[..., 0].astype(np.float64)
    var = img.variance[..., 0].astype(np.float64)
    assert img.stats["lt_splats"] > 20 * a.size
    assert np.abs((a - exp) / np.sqrt(var)).max() < 5
    assert abs(a.mean() - exp.mean()) / (np.sqrt(var.sum()) / a.size) < 5


def test_caustic_seen_through_glass_stays_the_estimators_bit_for_bit():
    """test_chains' slab seen from above: every first hit is the glass, so the
    estimator skips nothing, no photon reaches the camera, and the image is
    the one without light tracing, bit for bit."""
    sc = mpg.load_string(SLAB_POINT)
    on = mpg.render(sc, integrator={"type": "sms", "tau": "TT", "light_trace": 4}, spp=16, seed=1, progress=False)
    off = mpg.render(sc, integrator={"type": "sms", "tau": "TT"}, spp=16, seed=1, progress=False)
    assert on.stats["lt_photons"] > 0 and on.stats["lt_splats"] == 0 and on.stats["chain_lt_skipped"] == 0
    assert np.array_equal(on.rgb, off.rgb)


def test_light_trace_is_deterministic_and_thread_independent(scenes_dir):
    sc = mpg.load_file(scenes_dir / "eval" / "sphere_point.xml", res="24")
    integ = {"type": "sms_star", "light_trace": 8}   # (5 blocks of photons a pass at 4 spp)
    a = mpg.render(sc, integrator=integ, spp=4, seed=5, threads=1, progress=False)
    b = mpg.render(sc, integrator=integ, spp=4, seed=5, threads=2, progress=False)
    assert a.stats["lt_splats"] > 0
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.variance, b.variance)
    c = mpg.render(sc, integrator=integ, spp=4, seed=6, threads=2, progress=False)
    assert not np.array_equal(a.rgb, c.rgb)


def test_photon_waves_and_threads_give_the_same_pass(scenes_dir):
    """The first wave of photon blocks runs in the tiles' threads, later waves
    after them (RenderJob, PassConfig::lt_wave_blocks): one wave or three, one
    thread or up to six (more than the tiles), the pass's splat sums and the
    photons' counted work are the same, to the bit."""
    sc = mpg.load_file(scenes_dir / "eval" / "sphere_point.xml", res="24")
    integ = _core.make_integrator(sc.core, "sms_star", {"light_trace": 8})   # 5 blocks at 4 spp

    def run(threads, wave):
        job = _core.RenderJob(sc.core, integ, 4, 5, 0, threads, lt_wave_blocks=wave)
        while not job.wait(0.05):
            pass
        return job.result()

    ref = run(2, 1024)
    assert ref["lt_photons"] > 4 * 4096 and ref["stats"]["lt_splats"] > 0
    # (4 tiles and 5 photon blocks: 6 threads run 5, one of them photons only)
    for threads, wave in ((1, 1024), (1, 2), (2, 2), (3, 1), (6, 2)):
        r = run(threads, wave)
        assert np.array_equal(r["lt_sum"], ref["lt_sum"]) and np.array_equal(r["lt_sum_sq"], ref["lt_sum_sq"])
        assert np.array_equal(r["sum"], ref["sum"])
        assert (r["lt_work_rays"], r["lt_work_walk_steps"]) == (ref["lt_work_rays"], ref["lt_work_walk_steps"])
    with pytest.raises(ValueError, match="lt_wave_blocks"):
        _core.RenderJob(sc.core, integ, 1, 0, 0, 0, lt_wave_blocks=0)


def test_area_lights_are_light_traced_only_on_request(scenes_dir):
    """No point or spot light and no light_trace_area (the peers' default): no
    light tracer, no photon, no warning, and the image is bit-identical to
    light_trace = 0."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="16")
    on = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 4}, spp=4, seed=1, progress=False)
    off = mpg.render(sc, integrator={"type": "sms_star"}, spp=4, seed=1, progress=False)
    assert on.stats["lt_photons"] == 0 and not any("light_trace" in w for w in on.stats["warnings"])
    assert np.array_equal(on.rgb, off.rgb)


@pytest.mark.parametrize("change,reason", [
    (('<rfilter type="box"/>', '<rfilter type="gaussian"/>'), "filter"),
    (('<bsdf type="conductor"><string name="material" value="none"/></bsdf>',
      '<bsdf type="roughconductor"><string name="material" value="none"/><float name="alpha" value="0.05"/></bsdf>'),
     "glossy"),
])
def test_cases_it_cannot_take_warn_and_stay_with_the_estimator(change, reason):
    """A Gaussian pixel filter (a photon would splat into several pixels) or a
    glossy chain vertex (its adjoint BSDF is not done): a warning names why,
    no photon is traced, and the estimator keeps the light (its closed form
    still holds for the filter case)."""
    sc = mpg.load_string(mirror_scene().replace(*change))
    img = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 4}, spp=16, seed=1, progress=False)
    assert img.stats["lt_photons"] == 0 and img.stats["chain_lt_skipped"] == 0
    warn = [w for w in img.stats["warnings"] if "light_trace is off" in w]
    assert len(warn) == 1 and reason in warn[0], img.stats["warnings"]
    assert img.stats["chain_contributions"] > 0


@pytest.mark.parametrize("name", ["light_trace", "light_trace_glossy"])
@pytest.mark.parametrize("bad", [-1, 65, "lots", float("nan")])
def test_bad_light_trace_values_are_errors(bad, name):
    sc = mpg.load_string(mirror_scene())
    with pytest.raises(mpg.RenderError, match=name):
        mpg.render(sc, integrator={"type": "sms_star", name: bad}, spp=1, progress=False)


def test_light_inside_the_glass_gives_finite_counted_splats(scenes_dir):
    """A point light inside the glass ball (photons from inside the chain
    shapes' bound: the whole sphere of directions; total internal reflection
    at most nmax times): finite image, nothing rejected, photons splatted."""
    xml = (scenes_dir / "eval" / "sphere_point.xml").read_text()
    xml = xml.replace('value="-4.59627, 4.85673, 2.8144e-16"', 'value="0.2, 1.3, 0.1"')
    sc = mpg.load_string(xml, res="24")
    img = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 4}, spp=8, seed=1, progress=False)
    assert np.isfinite(img.rgb).all() and np.isfinite(img.variance).all()
    assert img.stats["lt_splats"] > 0 and img.stats["lt_rejected"] == 0 and img.stats["rejected_samples"] == 0


def _photons_at(st: dict, spp: int, npix: int, rate: float | None = None) -> bool:
    """The final render traced rate (default: the learned one, or the core's
    0.25 where none was learned) x spp x pixels photons (each pass rounds its
    own count; the core holds the rate as a float)."""
    r = st.get("light_trace_learned", 0.25) if rate is None else rate
    return abs(st["lt_photons"] - np.float32(r) * spp * npix) <= st["passes"] + 1


def test_mpg_light_traces_its_final_render_only(scenes_dir):
    """mpg light traces by default (photons per camera sample learned after
    training, light_trace "auto"; through glass too) where the scene has a
    point light; its training passes trace none (they never reach the image),
    nor does the photon rate's pilot: the photons are the learned rate x the
    final render's spp x pixels per pass."""
    sc = mpg.load_file(scenes_dir / "eval" / "sphere_point.xml", res="24")
    img = mpg.render(sc, integrator="mpg", spp=16, seed=1, progress=False)
    st = img.stats
    assert _photons_at(st, img.spp, 24 * 24) and st["integrator_params"]["light_trace"] == "auto"
    assert st["lt_chain_splats"] > 0   # (light_trace_through: the ball's focus seen in the ball)
    assert st["lt_splats"] > 0 and st["chain_lt_skipped"] > 0 and st["rejected_samples"] == 0
    assert np.isfinite(img.rgb).all()


def test_mpg_render_reports_the_photons(tmp_path, capsys, scenes_dir):
    from mpg.cli import main

    rc = main([str(scenes_dir / "eval" / "sphere_point.xml"), "-D", "res=16", "--spp", "8", "--integrator", "mpg",
               "-o", str(tmp_path / "a.exr"), "--no-preview"])
    assert rc == 0 and (tmp_path / "a.exr").exists()
    err = capsys.readouterr().err
    assert "light traced the caustics the camera sees" in err and "through glass" in err


def test_a_point_and_an_area_light_keep_their_sum():
    """The mirror scene with a small area light added: the estimator draws
    either light by power; at the camera's first hits a drawn point light is
    left to the photons (value 0 there) while the area light's estimates and
    the path tracer's shares of them stay as they were. sms_star with and
    without photons agree over the image and its nine blocks (the planar
    mirror's chains have K = 1: both renders have small variance); so do
    they with the area light's photons as well (light_trace_area)."""
    from stats_util import REGIONS_24, image_zmax

    xml = mirror_scene().replace(
        '<emitter type="point">',
        '<shape type="rectangle"><transform name="to_world"><scale value="0.3"/><rotate x="1" angle="90"/>'
        '<translate x="-0.5" y="2" z="0.5"/></transform>'
        '<emitter type="area"><rgb name="radiance" value="5"/></emitter></shape><emitter type="point">')
    sc = mpg.load_string(xml)
    on = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 16}, spp=256, seed=5, progress=False)
    off = mpg.render(sc, integrator={"type": "sms_star"}, spp=256, seed=6, progress=False)
    assert on.stats["lt_splats"] > 0 and on.stats["chain_lt_skipped"] > 0
    # the area light's chains through the mirror are still estimated with photons
    # on (the point light, drawn most often by power, gives none there), and
    # its light is there: about 4 % above the point light's closed form
    assert on.stats["chain_contributions"] > 1000 and off.stats["chain_contributions"] > 0
    assert on.rgb[..., 0].mean() > 1.02 * mirror_expected().mean()
    assert on.stats["rejected_samples"] == 0 and off.stats["rejected_samples"] == 0
    assert image_zmax(on, off, REGIONS_24) < 5
    # ... and with the area light's photons too: both lights' mirror chains
    # at the first hits are the photons' (no estimate contributes there)
    both = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 16, "light_trace_area": True}, spp=256,
                      seed=7, progress=False)
    assert both.stats["chain_contributions"] == 0 and both.stats["lt_pt_dropped"] > 0
    assert both.stats["rejected_samples"] == 0 and both.stats["lt_rejected"] == 0
    assert image_zmax(both, off, REGIONS_24) < 5


def area_mirror_scene(res=24):
    """mirror_scene's floor and mirror wall with a small area light (0.2 x 0.2,
    radiance 20, facing down at (0.8, 1, 1), outside the view) instead of the point light."""
    return mirror_scene(res).replace(
        '<emitter type="point"><point name="position" x="0" y="1" z="0"/><rgb name="intensity" value="3"/></emitter>',
        '<shape type="rectangle"><transform name="to_world"><scale value="0.1"/><rotate x="1" angle="90"/>'
        '<translate x="0.8" y="1" z="1"/></transform><bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>'
        '<emitter type="area"><rgb name="radiance" value="20"/></emitter></shape>')


def area_mirror_expected(res=24, sub=6, nq=8, image=True):
    """rho/pi * E, E the irradiance from the light and its image in the mirror
    x = 1 (reflected across it): Le * int cos_l cos_p / r^2 dA = Le * int dA / r^4
    for a light facing straight down at height 1 (cos_l = cos_p = 1 / r),
    by the midpoint rule over nq x nq nodes of the light."""
    X, Z = mirror_floor_points(res, sub)
    q = (np.arange(nq) + 0.5) / nq * 0.2 - 0.1
    dA = (0.2 / nq) ** 2
    E = np.zeros_like(X)
    for qx in q:
        for qz in q:
            for lx in (0.8 + qx, 2.0 - (0.8 + qx))[:2 if image else 1]:   # the light and its mirror image
                r2 = (X - lx) ** 2 + 1 + (Z - (1 + qz)) ** 2
                E += 20.0 * dA / r2**2
    return (0.5 / np.pi * E).reshape(res, sub, res, sub).mean(axis=(1, 3))


@pytest.mark.parametrize("integ", [{"type": "sms", "tau": "R"}, {"type": "sms_star"}])
def test_light_traced_area_light_mirror_matches_the_closed_form(integ):
    """light_trace_area: the area light's caustic in the mirror comes from the
    photons only; the estimator skips its chains at the camera's first hits and
    the path tracer drops its BSDF-sampled paths through the mirror to the
    light (lt_pt_dropped). Every pixel and the image mean match the closed form."""
    sc = mpg.load_string(area_mirror_scene())
    exp = area_mirror_expected()
    # (a pixel's few photon hits are a skewed sum: 16 photons x 64 spp gave
    # |z| up to 4.35 over five seeds, 64 x 128 2.9-4.2 over six)
    img = mpg.render(sc, integrator=dict(integ, light_trace=64, light_trace_area=True), spp=128, seed=3,
                     progress=False)
    st = img.stats
    assert st["lt_splats"] > 10 * 24 * 24 and st["chain_lt_skipped"] > 0 and st["lt_pt_dropped"] > 0
    assert st["chain_contributions"] == 0 and st["rejected_samples"] == 0 and st["lt_rejected"] == 0
    a = img.rgb[..., 0].astype(np.float64)
    var = img.variance[..., 0].astype(np.float64)
    z = (a - exp) / np.sqrt(var)
    assert np.abs(z).max() < 5, np.abs(z).max()
    assert abs(a.mean() - exp.mean()) / (np.sqrt(var.sum()) / a.size) < 5
    # (the test's power: the mirror's part, photons only here, is a third of the light or more)
    assert area_mirror_expected(image=False).mean() < 0.75 * exp.mean()


def test_mpg_light_traces_area_lights_by_default(scenes_dir):
    """mpg's default light_trace_area: on the glass ball under an area light
    its final render traces the learned rate x spp x pixels photons, the
    estimator skips the area light's chains at the camera's first hits and the
    path tracer drops its paths through the ball to the light there; the
    image is finite and nothing is rejected. (Unbiasedness: test_guiding's
    mpg renders against the path tracer run with this default.) With the
    learned maps (handoff_all 0): handoff_all=auto may hand every pixel of
    this short training off, and then no estimate runs to skip anything."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    img = mpg.render(sc, integrator={"type": "mpg", "handoff_all": 0}, spp=32, seed=1, progress=False)
    st = img.stats
    assert _photons_at(st, img.spp, 24 * 24)
    assert st["lt_splats"] > 0 and st["chain_lt_skipped"] > 0 and st["lt_pt_dropped"] > 0
    assert st["lt_chain_splats"] == 0   # (an area light's photons are not connected through glass)
    assert st["rejected_samples"] == 0 and st["lt_rejected"] == 0 and np.isfinite(img.rgb).all()
    # (the default, every pixel handed off here: the photons still take the
    # first hits' area-light chains, which the path tracer drops)
    auto = mpg.render(sc, integrator="mpg", spp=32, seed=1, progress=False).stats
    assert auto["lt_splats"] > 0 and auto["lt_pt_dropped"] > 0 and auto["rejected_samples"] == 0
    off = mpg.render(sc, integrator={"type": "mpg", "light_trace_area": False, "handoff_all": 0}, spp=32, seed=1,
                     progress=False)
    assert off.stats["lt_photons"] == 0 and off.stats["chain_lt_skipped"] == 0


def test_area_light_tracing_asked_for_where_it_cannot_run_warns():
    """light_trace_area asked for with a glossy mirror (no adjoint of a rough
    chain vertex): a warning names why and the estimator keeps the area light;
    mpg's default asks nothing, so it does not warn there."""
    glossy = area_mirror_scene().replace(
        '<bsdf type="conductor"><string name="material" value="none"/></bsdf>',
        '<bsdf type="roughconductor"><string name="material" value="none"/><float name="alpha" value="0.05"/></bsdf>')
    sc = mpg.load_string(glossy)
    img = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 4, "light_trace_area": True}, spp=8,
                     seed=1, progress=False)
    warn = [w for w in img.stats["warnings"] if "light_trace is off" in w]
    assert len(warn) == 1 and "glossy" in warn[0] and "area" in warn[0], img.stats["warnings"]
    assert img.stats["lt_photons"] == 0 and img.stats["chain_contributions"] > 0
    m = mpg.render(sc, integrator="mpg", spp=8, seed=1, progress=False)
    assert not any("light_trace is off" in w for w in m.stats["warnings"])


def test_a_sphere_lights_mirror_caustic_from_photons_matches_the_closed_form():
    """A small sphere light (radius 0.05 at (0.8, 1, 1), out of view) over the
    floor beside the mirror: photons leave points uniform on the sphere,
    outward. A sphere of radiance Le fully above the horizon gives the
    irradiance pi Le (r / d)^2 cos(theta) exactly; the mirror adds its image at
    x' = 2 - x. Every pixel and the image mean against rho/pi (E + E'),
    |z| < 5; the mirror's part comes from photons only."""
    xml = mirror_scene().replace(
        '<emitter type="point"><point name="position" x="0" y="1" z="0"/><rgb name="intensity" value="3"/></emitter>',
        '<shape type="sphere"><point name="center" x="0.8" y="1" z="1"/><float name="radius" value="0.05"/>'
        '<bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>'
        '<emitter type="area"><rgb name="radiance" value="100"/></emitter></shape>')
    sc = mpg.load_string(xml)
    # (16 photons x 64 spp gave |z| up to 6.2 over three seeds: a pixel's few
    # photon hits are a skewed sum; 64 x 256 gave 3.0-3.9)
    img = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 64, "light_trace_area": True}, spp=256,
                     seed=4, progress=False)
    st = img.stats
    assert st["lt_splats"] > 0 and st["chain_contributions"] == 0 and st["lt_rejected"] == 0
    sub, res = 6, 24
    X, Z = mirror_floor_points(res, sub)
    E = np.zeros_like(X)
    for cx in (0.8, 1.2):   # the light and its mirror image
        d2 = (X - cx) ** 2 + 1 + (Z - 1) ** 2
        E += np.pi * 100.0 * 0.05**2 / d2 * (1 / np.sqrt(d2))
    exp = (0.5 / np.pi * E).reshape(res, sub, res, sub).mean(axis=(1, 3))
    a = img.rgb[..., 0].astype(np.float64)
    var = img.variance[..., 0].astype(np.float64)
    z = (a - exp) / np.sqrt(var)
    assert np.abs(z).max() < 5, np.abs(z).max()
    assert abs(a.mean() - exp.mean()) / (np.sqrt(var.sum()) / a.size) < 5


# ---- glossy mode: casters glossy under a normal map, no chain estimator ----
NORMALMAP = (pathlib.Path(__file__).resolve().parents[1] / "scenes" / "eval" / "textures"
             / "normalmap_gaussian.exr")


def _bumpy(inner: str) -> str:
    return (f'<bsdf type="normalmap"><texture name="normalmap" type="bitmap"><string name="filename" '
            f'value="{NORMALMAP}"/><boolean name="raw" value="true"/></texture>{inner}</bsdf>')


MIRROR_BSDF = '<bsdf type="conductor"><string name="material" value="none"/></bsdf>'


ROUGH_MIRROR = ('<bsdf type="roughconductor"><string name="material" value="none"/>'
                '<float name="alpha" value="0.05"/></bsdf>')
ROUGH_PANE = '<bsdf type="roughdielectric"><float name="int_ior" value="1.5"/><float name="alpha" value="0.05"/></bsdf>'
BLACK = '<bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>'


def glossy_mirror_scene(receiver: str = "diffuse", caster: str = "conductor", max_depth: int = 3,
                        light: str = "area") -> str:
    """area_mirror_scene with bumpy glossy casters no walk takes: the mirror
    wall as a normal-mapped roughconductor (alpha 0.05; caster "conductor"),
    a normal-mapped roughdielectric pane (alpha 0.05, eta 1.5) at height 0.7
    over x in [0.1, 1.5] under the light, the camera seeing the floor beside
    it and, for x > 0.5, through it ("dielectric"; the wall then black), or
    both ("both"); the floor diffuse, a glossy caustic_receiver, or smooth
    plastic (a delta coating lobe); the area light, or a point light at
    (0.3, 3.5, 0.5). (An isotropic light where the area light is grazes the
    wall: the adjoint's shading-normal factor 1 / |cos(n_g, w_l)| and the
    path tracer's NEE at the bumpy casters were both heavy-tailed there, |z|
    8 at 32768 spp; the pane seen by the camera with a point light above it
    made the camera side's own NEE through it as heavy-tailed.)"""
    xml = area_mirror_scene().replace('<integer name="max_depth" value="3"/>',
                                      f'<integer name="max_depth" value="{max_depth}"/>')
    xml = xml.replace(MIRROR_BSDF, _bumpy(ROUGH_MIRROR) if caster in ("conductor", "both") else BLACK)
    if caster in ("dielectric", "both"):
        xml = xml.replace(
            '</scene>',
            '<shape type="rectangle"><transform name="to_world"><scale x="0.7" y="1.5"/><rotate x="1" angle="90"/>'
            '<translate x="0.8" y="0.7" z="0.5"/></transform>' + _bumpy(ROUGH_PANE) + '</shape></scene>')
    floor = '<bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>'
    if receiver == "glossy":
        xml = xml.replace(floor, '<boolean name="caustic_receiver" value="true"/><bsdf type="roughconductor">'
                          '<string name="material" value="none"/><float name="alpha" value="0.2"/></bsdf></shape>', 1)
    elif receiver == "plastic":
        xml = xml.replace(floor, '<bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.5"/></bsdf></shape>',
                          1)
    if light == "point":
        start = xml.index('<shape type="rectangle"><transform name="to_world"><scale value="0.1"/>')
        end = xml.index('</shape>', start) + len('</shape>')
        xml = xml[:start] + ('<emitter type="point"><point name="position" x="0.3" y="3.5" z="0.5"/>'
                             '<rgb name="intensity" value="6"/></emitter>') + xml[end:]
    return xml


GLOSSY_CASES = [("diffuse", "conductor", 3, "area"), ("glossy", "conductor", 3, "area"),
                ("diffuse", "dielectric", 3, "area"), ("glossy", "dielectric", 3, "area"),
                # chains of two casters, roulette and max_chain (-1), a delta lobe at the first hit
                ("plastic", "both", -1, "area"),
                # a point light's photons (max_depth 4); the plastic's coating
                # sees the wall's glints of it (without the first hit's delta
                # lobe left to the path tracer, |z| 16)
                ("plastic", "conductor", 4, "point")]


@pytest.mark.parametrize("receiver,caster,max_depth,light", GLOSSY_CASES)
def test_glossy_casters_photons_agree_with_the_path_tracer(receiver, caster, max_depth, light):
    """light_trace_glossy: no walk takes a caster glossy under a normal map, so
    no chain estimator runs; the photons then follow the casters' BSDF samples
    (glossy lobes, the adjoint's eta^2 and shading-normal weights) and bring
    camera -> floor -> casters -> light whole, while the path tracer drops those
    paths, its NEE at the last caster and its BSDF samples hitting the light
    alike. The sum agrees with the path tracer alone over the image and its
    nine blocks (|z| < 5); the photons carry many standard errors of it."""
    from stats_util import REGIONS_24, image_zmax

    xml = glossy_mirror_scene(receiver, caster, max_depth, light)
    sc = mpg.load_string(xml)
    on = mpg.render(sc, integrator={"type": "sms_star", "light_trace_glossy": 16}, spp=256, seed=11,
                    progress=False)
    # (the path tracer's floor -> bumpy caster -> light is heavy-tailed: at
    # 512 spp its variance estimate had not yet seen the tail and |z| reached
    # 21; at 8192 spp its standard error is still 3-5x the photons')
    ref = mpg.render(sc, integrator="path", spp=8192, seed=12, progress=False)
    st = on.stats
    assert st["lt_splats"] > 1000 and st["lt_pt_dropped"] > 0
    assert st["rejected_samples"] == 0 and st["lt_rejected"] == 0 and np.isfinite(on.rgb).all()
    # (the glossy floor's blocks far from the light, < 1e-3 of the image mean:
    # there the path tracer's value is rare events whose variance its samples
    # have not seen; one such block, photons 3.9e-5 +- 0.03e-5, path at
    # 8192 spp 2.2e-5 +- 0.003e-5 (|z| 44), at 32768 spp with another seed
    # 3.1e-5 +- 0.8e-5)
    top = on.rgb[..., 0].mean()
    regions = [r for r in REGIONS_24 if max(on.rgb[r].mean(), ref.rgb[r].mean()) > 1e-3 * top]
    assert len(regions) >= 5
    assert image_zmax(on, ref, regions) < 5
    # (the test's power: the casters' light, the photons' alone here, is many
    # standard errors of the image mean (> 15: a 1/3 error in it fails the
    # test); a render without it disagrees)
    dark = xml.replace(ROUGH_MIRROR, BLACK).replace(ROUGH_PANE, BLACK)
    none = mpg.render(mpg.load_string(dark), integrator="path", spp=64, seed=13, progress=False)
    assert image_zmax(none, ref, REGIONS_24[:1]) > 15


def test_glossy_mode_runs_only_where_no_chain_estimator_does():
    """Glossy mode is the light tracer of scenes whose casters no walk takes:
    with a smooth mirror the chain estimator runs and the photons are its
    usual ones (none from an area light unless light_trace_area), and a
    render of the smooth scene is the same bit for bit with the option on."""
    sc = mpg.load_string(area_mirror_scene())
    a = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 4}, spp=16, seed=2, progress=False)
    b = mpg.render(sc, integrator={"type": "sms_star", "light_trace": 4, "light_trace_glossy": 4}, spp=16,
                   seed=2, progress=False)
    assert np.array_equal(a.rgb, b.rgb) and b.stats["lt_photons"] == a.stats["lt_photons"]
    g = mpg.load_string(glossy_mirror_scene())
    off = mpg.render(g, integrator={"type": "sms_star", "light_trace": 4, "light_trace_area": True}, spp=16, seed=2,
                     progress=False)
    p = mpg.render(g, integrator="path", spp=16, seed=2, progress=False)
    assert off.stats["lt_photons"] == 0 and np.array_equal(off.rgb, p.rgb)
    # mpg's default traces them: light_trace_glossy "auto", which without a
    # chain estimator has no training to learn from, is 0.5 photons per sample
    m = mpg.render(g, integrator="mpg", spp=16, seed=2, progress=False)
    assert m.stats["lt_photons"] == round(0.5 * m.spp * 24 * 24) and m.stats["lt_pt_dropped"] > 0
    assert m.stats["integrator_params"]["light_trace_glossy"] == "auto" and "light_trace_learned" not in m.stats
    assert m.stats["rejected_samples"] == 0 and m.stats["lt_rejected"] == 0
    s = mpg.render(g, integrator={"type": "sms_star", "light_trace_glossy": 1}, spp=4, seed=2, progress=False)
    assert any("light_trace_glossy" in w for w in s.stats["warnings"]), s.stats["warnings"]


@pytest.mark.parametrize("light", ["tiny", "grazing"])
def test_glossy_photons_at_a_tiny_or_grazing_light_stay_finite(light):
    """Glossy mode's numerically hard cases: a 0.002-wide area light, and a
    point light 0.01 from the bumpy wall (every photon grazes it: the
    adjoint's shading-normal factor 1 / |cos(n_g, w_l)| is large). The image
    is finite and non-negative; whatever a splat could not give is counted
    (lt_rejected), never an image value."""
    xml = glossy_mirror_scene()
    if light == "tiny":
        xml = xml.replace('<scale value="0.1"/><rotate x="1" angle="90"/>', '<scale value="0.001"/><rotate x="1" angle="90"/>')
        xml = xml.replace('<rgb name="radiance" value="20"/>', '<rgb name="radiance" value="2e5"/>')
    else:
        start = xml.index('<shape type="rectangle"><transform name="to_world"><scale value="0.1"/>')
        end = xml.index('</shape>', start) + len('</shape>')
        xml = xml[:start] + ('<emitter type="point"><point name="position" x="0.99" y="0.5" z="0"/>'
                             '<rgb name="intensity" value="1"/></emitter>') + xml[end:]
    img = mpg.render(mpg.load_string(xml), integrator={"type": "sms_star", "light_trace_glossy": 4}, spp=32, seed=3,
                     progress=False)
    st = img.stats
    assert st["lt_photons"] > 0 and st["lt_splats"] > 0 and st["lt_pt_dropped"] >= 0
    assert np.isfinite(img.rgb).all() and (img.rgb >= 0).all() and st["rejected_samples"] == 0
    assert st["lt_rejected"] <= st["lt_splats"] // 100


def test_mpg_learns_its_photon_rate_where_it_traces_photons(scenes_dir):
    """light_trace "auto" (mpg's default): after training, a pilot pass (two
    camera samples per pixel, at least PHOTON_PILOT photons, its image unused)
    measures what Eq. 5 needs, and the render traces at the learned rate,
    inside [PHOTON_RATE_MIN, PHOTON_RATE_MAX]; the model's parts are reported.
    Below PHOTON_PILOT_MIN_TRAINING training spp no pilot runs (the core's
    0.25). A number is used as given, with no pilot; "auto" belongs to mpg; a
    scene without photons runs no pilot."""
    from mpg.chain_rates import PHOTON_PILOT, PHOTON_RATE_MAX, PHOTON_RATE_MIN
    from mpg.guiding import PHOTON_PILOT_MIN_TRAINING
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    img = mpg.render(sc, integrator="mpg", spp=256, seed=4, threads=2, progress=False)
    st = img.stats
    # counted work, not timed: the same rate and image on one thread
    one = mpg.render(sc, integrator="mpg", spp=256, seed=4, threads=1, progress=False)
    assert one.stats["light_trace_learned"] == st["light_trace_learned"] and np.array_equal(one.rgb, img.rgb)
    assert PHOTON_RATE_MIN <= st["light_trace_learned"] <= PHOTON_RATE_MAX
    assert _photons_at(st, img.spp, 24 * 24)
    from mpg.guiding import PHOTON_PILOT_SPP
    assert st["photon_pilot"] == PHOTON_PILOT_SPP * min(PHOTON_PILOT, 64 * 24 * 24)
    assert st["seconds_photon_pilot"] > 0
    for k in ("v_camera", "v_photon", "c_camera", "c_photon"):
        assert st[f"light_trace_model_{k}"] > 0, k
    assert st["light_trace_model_gain"] >= 1.0
    assert st["spp_training"] >= PHOTON_PILOT_MIN_TRAINING
    given = mpg.render(sc, integrator={"type": "mpg", "light_trace": 0.5}, spp=256, seed=4, progress=False)
    assert "light_trace_learned" not in given.stats and _photons_at(given.stats, given.spp, 24 * 24, 0.5)
    short = mpg.render(sc, integrator="mpg", spp=32, seed=4, progress=False)
    assert short.stats["spp_training"] < PHOTON_PILOT_MIN_TRAINING and "light_trace_learned" not in short.stats
    assert _photons_at(short.stats, short.spp, 24 * 24, 0.25)
    with pytest.raises(mpg.RenderError, match="light_trace 'auto'"):
        mpg.render(sc, integrator={"type": "sms_star", "light_trace": "auto"}, spp=1, progress=False)
    # the photons declined (a Gaussian pixel filter): trained, but no pilot
    gauss = mpg.load_string(mirror_scene().replace('<rfilter type="box"/>', '<rfilter type="gaussian"/>'))
    g = mpg.render(gauss, integrator="mpg", spp=256, seed=4, progress=False)
    assert g.stats["spp_training"] >= PHOTON_PILOT_MIN_TRAINING and g.stats["lt_photons"] == 0
    assert "light_trace_learned" not in g.stats and "photon_pilot" not in g.stats
    room = mpg.load_file(scenes_dir / "eval" / "diffuse_room.xml", res="16")
    plain = mpg.render(room, integrator="mpg", spp=8, seed=4, progress=False)
    assert "light_trace_learned" not in plain.stats and plain.stats["lt_photons"] == 0


def test_photon_variance_model_matches_independent_passes(scenes_dir):
    """Eq. 5's photon term: a pass of N photons gives each pixel's light-traced
    part a variance v_p / N, v_p from the splats' sums and squares
    (learn_photon_rate's light_trace_model_v_photon = mean v_p / P). Against
    the spread of that part over 64 independent passes: with these seeds the
    ratio was 0.94-1.02 (4 seeds, 2 304 photons a pass); 15 % is more than 4
    of its standard deviations, while a splat counted twice or a photon that
    is not one independent sample of every pixel (v_p / N^2, v_p / N per
    splat) moves it by 2x and more."""
    from mpg.chain_rates import learn_photon_rate
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    integ = _core.make_integrator(sc.core, "sms_star", {"light_trace": 4.0, "light_trace_area": True})
    est, s1, s2, n = [], 0.0, 0.0, 0
    for k in range(64):
        job = _core.RenderJob(sc.core, integ, 1, 9, k, 2)
        while not job.wait(0.05):
            pass
        r = job.result()
        assert r["lt_photons"] == 4 * 24 * 24
        est.append(r["lt_sum"] / r["lt_photons"])
        s1, s2, n = s1 + r["lt_sum"], s2 + r["lt_sum_sq"], n + r["lt_photons"]
    spread = float(np.mean(np.var(np.array(est), axis=0, ddof=1)))
    _, info = learn_photon_rate(1.0, 1.0, s1, s2, n, 1.0, 0.25)
    predicted = info["light_trace_model_v_photon"] * (24 * 24) / (4 * 24 * 24)
    assert spread > 0 and abs(spread / predicted - 1.0) < 0.15, (spread, predicted)


def test_the_photon_pilot_keeps_the_split_paths_off_the_renders_sequence(scenes_dir, monkeypatch):
    """The photon pilot runs mpg with the render's seed and maps; with the
    delta split's extra paths on their per-pixel Sobol sequence
    (delta_split_sobol, mpg's default) it would trace the render's own first
    points. Its integrator has the sequence off; the render's has it on."""
    from mpg import _core
    made = []
    real = _core.make_integrator

    def spy(scene, kind, params):
        made.append((kind, dict(params)))
        return real(scene, kind, params)
    monkeypatch.setattr(_core, "make_integrator", spy)
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    img = mpg.render(sc, integrator="mpg", spp=256, seed=4, progress=False)
    assert "light_trace_learned" in img.stats   # (the pilot ran)
    final = [p for k, p in made if k == "mpg" and not p.get("record")]
    assert len(final) == 2   # the pilot, then the render
    assert final[0]["delta_split_sobol"] is False and final[1]["delta_split_sobol"] is True
