"""Glints: the small area lights seen from the camera through chain vertices
only, found by walks from the camera (ChainEstimator::glint; design-notes
"Glints"). The path tracer drops exactly those paths, so the image must stay
the same in expectation: against a closed form (a disk light in a plane
mirror), against the path tracer (a disk light seen through a glass ball, two
refractions and the internal reflections), and the rule that picks the
lights. z-tests at |z| < 5 (p < 6e-7 per comparison)."""

from __future__ import annotations

import numpy as np
import pytest

import mpg
from mpg import _core
from stats_util import REGIONS_24, image_zmax

RES = 24
FOV = 20.0


def _cam(origin, target, res=RES, rfilter='<rfilter type="box"/>', fov=FOV):
    return f"""<sensor type="perspective"><float name="fov" value="{fov:g}"/>
      <transform name="to_world"><lookat origin="{origin}" target="{target}" up="0, 1, 0"/></transform>
      <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/>
      {rfilter}</film></sensor>"""


# A plane mirror y = 0 and a disk light of radius R centred at L = (1, 2, 0)
# facing the mirror's point M = (0, 0, 0); the camera at C = (-1, 2, 0) sees
# the light's mirror image face-on along C -> M, at distance D = |C - M| +
# |M - L| = 2 sqrt(5). It looks at (0, 0, aim_z): the image is off the axis
# by atan(aim_z / sqrt(5)).
MIRROR_R = 0.13
MIRROR_LE = 10.0
MIRROR_BSDF = '<bsdf type="conductor"><string name="material" value="none"/></bsdf>'
GLASS_BSDF = '<bsdf type="dielectric"><float name="int_ior" value="1.5"/></bsdf>'


def mirror_light_scene(radius=MIRROR_R, res=RES, rfilter='<rfilter type="box"/>', max_depth=4, fov=FOV, aim_z=0.0,
                       bsdf=MIRROR_BSDF, light_target="0, 0, 0"):
    return f"""<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="{max_depth}"/></integrator>
      {_cam("-1, 2, 0", f"0, 0, {aim_z:g}", res, rfilter, fov)}
      <shape type="rectangle"><transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/></transform>
        {bsdf}</shape>
      <shape type="disk"><transform name="to_world"><scale value="{radius:g}"/>
        <lookat origin="1, 2, 0" target="{light_target}" up="0, 1, 0"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="{MIRROR_LE:g}"/></emitter></shape>
    </scene>"""


def _solid_angle_sum(img, cos_img, res=RES, fov=FOV):
    """sum_j I_j A_pix cos^3(theta) = int L d omega over the image (box filter:
    a pixel's value is the mean radiance over its film area, and the film at
    unit distance has dA = d omega / cos^3 theta), theta the direction of the
    light's image (under a pixel across here)."""
    t = np.tan(np.radians(fov / 2))
    w = (2 * t / res) ** 2 * cos_img**3
    lum = img.rgb.astype(np.float64).mean(axis=2)
    var = img.variance.astype(np.float64).mean(axis=2)
    return float(lum.sum() * w), float(np.sqrt(var.sum()) * w)


def _fresnel(cos_i, eta):
    """Unpolarised Fresnel reflectance of a dielectric interface (from outside)."""
    sin_t2 = (1 - cos_i**2) / eta**2
    cos_t = np.sqrt(1 - sin_t2)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return 0.5 * (rs * rs + rp * rp)


@pytest.mark.parametrize("surface, spp", [("mirror", 1024), ("glass", 8192)])
def test_glint_of_a_tiny_light_matches_the_closed_form(surface, spp):
    """The walks' glint of a disk light 0.5 px across, seen 24 degrees off the
    axis (cos^3 = 0.76) in a perfect mirror or in a glass surface (R only:
    max_depth 2), alone (camera_delta only): its image's int L d omega is
    Le F times the disk's solid angle seen face-on from its mirror image's
    distance, 2 pi (1 - D / sqrt(D^2 + R^2)). On glass a seed draws R with
    probability F (0.042 here), so the Bernoulli count K of 1/P is about 1/F."""
    r, fov, aim_z = 0.05, 60.0, 1.0
    glass = surface == "glass"
    sc = mpg.load_string(mirror_light_scene(radius=r, fov=fov, aim_z=aim_z, max_depth=2 if glass else 4,
                                            bsdf=GLASS_BSDF if glass else MIRROR_BSDF))
    integ = {"type": "sms_star", "camera_delta": "only", "glints": 100.0}
    img = mpg.render(sc, integrator=integ, spp=spp, seed=1, progress=False)
    st = img.stats
    # (the path tracer's hits of the light through the surface: dropped, counted)
    assert st["glint_found"] > 0 and st["glint_pt_dropped"] > 0 and st["glint_rejected"] == 0
    D = 2 * np.sqrt(5.0)
    F = _fresnel(2 / np.sqrt(5.0), 1.5) if glass else 1.0
    exact = MIRROR_LE * F * 2 * np.pi * (1 - D / np.sqrt(D * D + r * r))
    C, M, T = np.array([-1.0, 2, 0]), np.zeros(3), np.array([0, 0, aim_z])
    cos_img = np.dot(M - C, T - C) / np.linalg.norm(M - C) / np.linalg.norm(T - C)
    got, se = _solid_angle_sum(img, cos_img, fov=fov)
    assert abs(got - exact) < 5 * se + 1e-3 * exact, (got, exact, se)
    # (the test's power: 5 se under 30 % on the mirror, 50 % on glass, where
    # K's spread adds to the light point's)
    assert se < (0.1 if glass else 0.06) * exact, (se, exact)
    K = st["glint_trials"] / st["glint_found"]
    if glass:
        assert 0.5 / F < K < 2 / F, K
    else:
        # a plane mirror: every seed converges to the one solution, K = 1
        # nearly always (K > 1 only where a trial's seed fails the capture test)
        assert K < 1.2, K


def test_glint_larger_than_a_pixel_agrees_with_the_path_tracer_and_closed_form():
    """A light 3.5 px across in the image's centre: each light point's solution
    lands in one of the pixels the image covers (the walks' variance grows
    with the image's size, which is why mpg's rule keeps them to lights under
    2 px), and the image agrees with the path tracer's pixel by pixel."""
    sc = mpg.load_string(mirror_light_scene())
    img = mpg.render(sc, integrator={"type": "sms_star", "camera_delta": "only", "glints": 100.0}, spp=256,
                     seed=1, progress=False)
    plain = mpg.render(sc, integrator={"type": "sms_star", "camera_delta": "only"}, spp=1024, seed=2,
                       progress=False)
    assert img.stats["glint_found"] > 0 and plain.stats["glint_found"] == 0
    assert image_zmax(img, plain, REGIONS_24) < 5
    D = 2 * np.sqrt(5.0)
    exact = MIRROR_LE * 2 * np.pi * (1 - D / np.sqrt(D * D + MIRROR_R**2))
    for im in (img, plain):
        got, se = _solid_angle_sum(im, 1.0)   # (cos^3 > 0.9995 over the image)
        assert abs(got - exact) < 5 * se + 1e-3 * exact, (got, exact, se)


def test_glints_and_the_path_tracer_split_the_paths_exactly():
    """With glints the path tracer drops its hits of the owned light through
    the mirror (counted) and nothing else: the whole image (all paths) agrees
    with glints off, and a light too large for the rule stays the path tracer's."""
    sc = mpg.load_string(mirror_light_scene())
    on = mpg.render(sc, integrator={"type": "sms_star", "glints": 100.0}, spp=256, seed=3, progress=False)
    off = mpg.render(sc, integrator={"type": "sms_star"}, spp=256, seed=4, progress=False)
    assert on.stats["glint_pt_dropped"] > 0 and on.stats["glint_found"] > 0
    assert off.stats["glint_pt_dropped"] == 0 and off.stats["glint_seeds"] == 0
    assert image_zmax(on, off, REGIONS_24) < 5
    # the light is about 4 px across: a rule of 2 px leaves it alone
    small = mpg.render(sc, integrator={"type": "sms_star", "glints": 2.0}, spp=4, seed=3, progress=False)
    assert small.stats["glint_seeds"] == 0 and small.stats["glint_pt_dropped"] == 0


# A glass ball (radius 0.5, IOR 1.5) at the origin, a disk light of radius 0.05
# behind it facing it, and the camera in front: the light seen through the
# ball (TT, and its internal reflections TRT, TRRT, ...).
BALL = f"""<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="8"/></integrator>
  {_cam("0, 0, 4", "0, 0, 0")}
  <shape type="sphere"><float name="radius" value="0.5"/>
    <bsdf type="dielectric"><float name="int_ior" value="1.5"/></bsdf></shape>
  <shape type="disk"><transform name="to_world"><scale value="0.05"/>
    <lookat origin="0.05, 0.08, -1.2" target="0, 0, 0" up="0, 1, 0"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
    <emitter type="area"><rgb name="radiance" value="40"/></emitter></shape>
</scene>"""


def test_glints_through_a_glass_ball_agree_with_the_path_tracer():
    sc = mpg.load_string(BALL)
    on = mpg.render(sc, integrator={"type": "sms_star", "camera_delta": "only", "glints": 100.0}, spp=256,
                    seed=5, progress=False)
    off = mpg.render(sc, integrator={"type": "sms_star", "camera_delta": "only"}, spp=4096, seed=6,
                     progress=False)
    st = on.stats
    assert st["glint_found"] > 0 and st["glint_rejected"] == 0
    assert np.isfinite(on.rgb).all() and off.rgb.max() > 0
    assert image_zmax(on, off, REGIONS_24) < 5
    # the light seen through the ball is the whole image here: it is non-zero
    assert on.rgb.sum() > 0.5 * off.rgb.sum()


def test_the_rule_picks_the_small_area_lights_the_camera_can_see_in_glass():
    sc = mpg.load_string(mirror_light_scene())
    make = lambda **p: _core.make_integrator(sc.core, "sms_star", dict(p, max_depth=4))
    # the light's image is 2 R / D / (2 tan(10 deg) / 24) = 3.5 px across
    assert make(glints=4.0).glint_emitters == [0]
    assert make(glints=3.0).glint_emitters == []
    assert make().glint_emitters == [] and make(glints=0.0).glint_max_chain == 0
    # mpg's default rule (2 px) in the tool's units
    assert _core.make_integrator(sc.core, "mpg", {}).glint_emitters == []
    tiny = mpg.load_string(mirror_light_scene(radius=0.05))
    assert _core.make_integrator(tiny.core, "mpg", {}).glint_emitters == [0]
    # chains of m vertices need m + 1 segments: max_depth 4 leaves 3
    assert make(glints=4.0).glint_max_chain == 3
    assert make(glints=4.0, max_chain=2).glint_max_chain == 2
    # the walks' pixel is a box of one pixel: another filter has no glints
    gauss = mpg.load_string(mirror_light_scene(rfilter='<rfilter type="gaussian"/>'))
    assert _core.make_integrator(gauss.core, "sms_star", {"glints": 4.0}).glint_emitters == []
    # a path tracer has no walks
    assert _core.make_integrator(sc.core, "path", {"glints": 4.0}).glint_emitters == []


@pytest.mark.parametrize("bad", [-1.0, float("nan")])
def test_bad_glints_values_are_errors(bad):
    sc = mpg.load_string(mirror_light_scene())
    with pytest.raises(Exception, match="glints"):
        mpg.render(sc, integrator={"type": "sms_star", "glints": bad}, spp=1, progress=False)


def test_mpg_takes_the_tiny_lights_glints_by_default(scenes_dir):
    """emitter_size_001's light (0.2 px across at 64^2): mpg walks its glints,
    and the suite's larger lights keep the path tracer (no glint light)."""
    sc = mpg.load_file(str(scenes_dir / "eval" / "emitter_size_001.xml"), res=64)
    img = mpg.render(sc, integrator="mpg", spp=64, seed=1, progress=False)
    assert img.stats["glint_found"] > 0 and img.stats["glint_rejected"] == 0
    assert img.stats["rejected_nan"] == 0 and np.isfinite(img.rgb).all()
    # (the rule is in pixels: emitter_size_010's light is 3.4 px across at
    # 128^2, 1.7 px at 64^2)
    for name, res in (("sphere", 256), ("double_slabs", 256), ("emitter_size_010", 128)):
        s = mpg.load_file(str(scenes_dir / "eval" / f"{name}.xml"), res=res)
        assert _core.make_integrator(s.core, "mpg", {}).glint_emitters == [], name


def test_mpg_render_reports_the_glints(tmp_path, capsys, scenes_dir):
    from mpg.cli import main

    rc = main([str(scenes_dir / "eval" / "emitter_size_001.xml"), "-D", "res=32", "--spp", "16", "--integrator",
               "mpg", "-o", str(tmp_path / "a.exr"), "--no-preview"])
    assert rc == 0 and (tmp_path / "a.exr").exists()
    err = capsys.readouterr().err
    assert "walked the small lights' glints seen in the glass" in err and "found in their pixel" in err


def test_glints_from_the_command_line(tmp_path, capsys, scenes_dir):
    from mpg.cli import main

    scene = str(scenes_dir / "eval" / "emitter_size_001.xml")
    rc = main([scene, "-D", "res=16", "--spp", "4", "--integrator", "mpg", "-P", "glints=0",
               "-o", str(tmp_path / "a.exr"), "--no-preview"])
    assert rc == 0 and "walked the small lights" not in capsys.readouterr().err
    rc = main([scene, "-D", "res=16", "--spp", "4", "--integrator", "mpg", "-P", "glints=abc",
               "-o", str(tmp_path / "b.exr"), "--no-preview"])
    err = capsys.readouterr().err
    assert rc != 0 and "glints" in err and "abc" in err and not (tmp_path / "b.exr").exists()


def test_exclude_and_only_split_the_glints_too():
    """camera_delta exclude leaves out every path seen through delta scattering
    only, the glints' included; only renders them (with the glints): the two
    add up to all."""
    from types import SimpleNamespace
    sc = mpg.load_string(mirror_light_scene(bsdf=GLASS_BSDF))
    ims = {m: mpg.render(sc, {"type": "sms_star", "glints": 100.0, "camera_delta": m}, spp=256, seed=8,
                         progress=False) for m in ("all", "exclude", "only")}
    assert ims["exclude"].stats["glint_seeds"] == 0 and ims["only"].stats["glint_found"] > 0
    assert ims["all"].stats["glint_found"] > 0
    e, o = ims["exclude"], ims["only"]
    both = SimpleNamespace(rgb=e.rgb.astype(np.float64) + o.rgb, variance=e.variance.astype(np.float64) + o.variance)
    assert image_zmax(ims["all"], both, REGIONS_24) < 5
    # the glints are in `only`: exclude has no light there
    assert o.rgb.sum() > 0 and e.rgb.sum() < 1e-3 * o.rgb.sum()


def test_the_delta_splits_branched_paths_leave_the_glints_to_the_walks():
    """The delta split's extra paths (Li_delta, branched at the glass: the
    reflection that sees the light and the refraction) drop the glints'
    paths as the camera path does: with a split of 4 everywhere the glint of
    a 0.5-px light in glass still matches the closed form (kept, the branched
    reflections would count it twice)."""
    from types import SimpleNamespace
    from stats_util import run_pass
    r_, fov, aim_z, spp = 0.05, 60.0, 1.0, 8192
    sc = mpg.load_string(mirror_light_scene(radius=r_, fov=fov, aim_z=aim_z, max_depth=2, bsdf=GLASS_BSDF))
    r = run_pass(sc, "sms_star", spp, 9, {"glints": 100.0, "delta_branch": 2, "max_depth": 2},
                 delta_split_map=np.full((RES, RES), 4, np.float32))
    st = r["stats"]
    assert st["delta_split_paths"] > 0 and st["delta_branches"] > 0 and st["glint_found"] > 0
    assert st["glint_pt_dropped"] > 0
    m = r["sum"] / spp
    split = SimpleNamespace(rgb=m, variance=np.maximum(r["sum_sq"] / spp - m * m, 0) / (spp - 1))
    D = 2 * np.sqrt(5.0)
    exact = MIRROR_LE * _fresnel(2 / np.sqrt(5.0), 1.5) * 2 * np.pi * (1 - D / np.sqrt(D * D + r_ * r_))
    C, M, T = np.array([-1.0, 2, 0]), np.zeros(3), np.array([0, 0, aim_z])
    cos_img = np.dot(M - C, T - C) / np.linalg.norm(M - C) / np.linalg.norm(T - C)
    got, se = _solid_angle_sum(split, cos_img, fov=fov)
    assert abs(got - exact) < 5 * se + 1e-3 * exact and se < 0.15 * exact, (got, exact, se)


def test_a_light_seen_from_behind_in_the_mirror_has_no_glint():
    """A one-sided disk light facing away from the mirror: the camera sees its
    back in the mirror, which emits nothing, with glints as without."""
    sc = mpg.load_string(mirror_light_scene(light_target="2, 4, 0"))
    img = mpg.render(sc, integrator={"type": "sms_star", "camera_delta": "only", "glints": 100.0}, spp=64, seed=1,
                     progress=False)
    assert img.stats["glint_walks"] > 0            # the walks reach the light ...
    assert img.stats["glint_found"] == 0 and img.rgb.max() == 0.0   # ... from behind: nothing
