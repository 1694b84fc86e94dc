"""Participating media (bdpt_drjit/media.py): volumetric BDPT against Mitsuba's
``volpath`` on scenes that each isolate one setup (a fog cube, a heterogeneous cloud
under a sky, camera and light inside fog, a global medium), single techniques against
volpath restricted to one path length, the volumetric caustic that volpath cannot
render, and stability where free-flight sampling fails (dense, white, black fog).
The partition of unity with medium vertices is in test_mis.py."""
import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit
from conftest import SCENES, assert_agrees_in_variant, mitsuba_render, specular_pixels
from stats import assert_statistically_equal, t_threshold, welch_dof

MEDIA = SCENES / "media"
RES = 24


def _load(name, res=RES, **params):
    return mi.load_file(str(MEDIA / name), resx=res, resy=res, **params)


def _bdpt(scene, spp, seeds, **kw):
    return [bdpt_drjit.render(scene, spp=spp, seed=10 + s, **kw).image[..., :3]
            for s in range(seeds)]


def _volpath(scene, spp, seeds, max_depth=8):
    return [mitsuba_render(scene, "volpath", spp, 100 + s, max_depth=max_depth)[..., :3]
            for s in range(seeds)]


# -- whole images against volpath ------------------------------------------------------
CASES = {
    # chromatic homogeneous fog (sigma_t differs per channel), isotropic
    "fog-cube": ("fog-cube.xml", {}),
    # strongly forward and backward scattering
    "fog-cube-hg+0.7": ("fog-cube.xml", {"g": 0.7}),
    "fog-cube-hg-0.7": ("fog-cube.xml", {"g": -0.7}),
    # heterogeneous (null collisions, ratio tracking) under a constant sky; it was 10%
    # too bright while camera rays that collided took the sky as an emission hit
    "cloud": ("cloud.xml", {}),
    # the sensor's medium, and a light that declares none, inside a fog-filled room
    "fog-room": ("fog-room.xml", {}),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_agrees_with_volpath(case):
    name, params = CASES[case]
    scene = _load(name, **params)
    b = _bdpt(scene, 64, 8, max_depth=8)
    assert not any(np.isnan(x).any() for x in b)
    assert_statistically_equal(b, _volpath(scene, 1024, 8), what=case)


def test_global_medium_without_boundary():
    """The sensor's medium with no shape around it fills the whole scene."""
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = RES
    d["fog"] = {"type": "homogeneous", "sigma_t": 0.4, "albedo": 0.7}
    d["sensor"]["medium"] = {"type": "ref", "id": "fog"}
    scene = mi.load_dict(d)
    assert_statistically_equal(_bdpt(scene, 64, 8, max_depth=8), _volpath(scene, 1024, 8),
                               what="global fog")


def test_a_mask_in_a_scene_with_media_still_scatters():
    """A mask floor of opacity 0.5 under a constant sky, beside a fog cube: in a scene
    with media only a null BSDF is a medium boundary (media.is_boundary); a mask stays
    a surface that scatters half the light and lets half pass.  Failed before: every
    BSDF with a null lobe was crossed as a boundary, the mask was fully transparent,
    and the image read 0.80 against volpath's 0.70."""
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at([0, 1, 4], [0, 0.3, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3),
                  "bsdf": {"type": "mask", "opacity": 0.5, "bsdf": {"type": "diffuse"}}},
        "fog": {"type": "cube", "bsdf": {"type": "null"},
                "to_world": T().translate([0, 0.5, 0]).scale(0.5),
                "interior": {"type": "homogeneous", "sigma_t": 1.5, "albedo": 0.8}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.7, 0.8, 1.0]}}})
    assert_statistically_equal(_bdpt(scene, 32, 8, max_depth=-1), _volpath(scene, 128, 8, max_depth=-1),
                               what="mask beside fog")


def test_area_light_on_a_shape_with_media():
    """A sphere light whose shape declares the fog outside it (and another medium
    inside): light subpaths start in the medium on the side they leave by."""
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "fog": {"type": "homogeneous", "id": "fog", "sigma_t": 0.4, "albedo": 0.8},
        "room": {"type": "cube", "bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "fog"},
                 "to_world": T().scale(2.0)},
        "lamp": {"type": "sphere", "center": [0, 1, 0], "radius": 0.15,
                 "exterior": {"type": "ref", "id": "fog"},
                 "interior": {"type": "homogeneous", "sigma_t": 5.0},
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 20.0}}},
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(1.5)},
        "sensor": {"type": "perspective", "fov": 60, "medium": {"type": "ref", "id": "fog"},
                   "to_world": T().look_at([0, 0, 1.8], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}}})
    assert_statistically_equal(_bdpt(scene, 64, 8, max_depth=6), _volpath(scene, 1024, 8, max_depth=6),
                               what="area light with media")


@pytest.mark.auto_budget
def test_auto_budget_agrees_with_volpath():
    """The default budget (its pilot included) with medium vertices on both walks."""
    scene = _load("fog-cube.xml")
    assert_statistically_equal(_bdpt(scene, 64, 8, max_depth=8), _volpath(scene, 1024, 8),
                               what="fog-cube, budget auto")


# -- single techniques against volpath at one path length ----------------------------------
def _assert_means_equal(a, b, what, p_false=1e-4):
    a, b = np.asarray(a), np.asarray(b)
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    t = abs(a.mean() - b.mean()) / np.sqrt(va + vb)
    assert t < t_threshold(welch_dof(va, vb, len(a), len(b)), p_false), \
        "%s: %g vs %g (t = %.1f)" % (what, a.mean(), b.mean(), t)


def _assert_techniques_match_volpath(scene, k, ref_scene=None, seeds=6):
    """Each (s, t) with s + t - 1 = k, unweighted, against volpath's paths of length k:
    volpath at max_depth k minus max_depth k - 1 with the same seed, whose samples
    then draw the same paths up to length k - 1 (the difference is exactly their
    length-k part, not two independent renders' noise).  ``ref_scene``: the scene
    volpath renders, if not ``scene``."""
    ref_scene = scene if ref_scene is None else ref_scene
    ref = [(mitsuba_render(ref_scene, "volpath", 1024, 100 + s, max_depth=k)
            - (mitsuba_render(ref_scene, "volpath", 1024, 100 + s, max_depth=k - 1) if k > 1 else 0.0)
            )[..., :3].mean() for s in range(seeds)]
    for s_ in range(0, k + 1):
        t = k + 1 - s_
        est = [x.mean() for x in _bdpt(scene, 256, seeds, max_depth=k, technique=(s_, t))]
        _assert_means_equal(est, ref, "technique (%d, %d)" % (s_, t))


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_every_technique_matches_volpath_at_its_length(k):
    """Each (s, t) with s + t - 1 = k, unweighted, estimates the paths of length k
    through fog (volpath at max_depth k minus max_depth k - 1): the distance
    densities, transmittances and phase functions of every strategy, one at a time."""
    _assert_techniques_match_volpath(_load("fog-room.xml", res=12), k)


def _lamp_over_fog(res, lamp_bsdf):
    """Issue 27's fog without its room: the Cornell box's lamp (0.01 under where the
    ceiling was, facing down) 0.09 above the null top face of a fog cube (scale 0.9,
    chromatic albedo), a floor under the cube, the camera outside.  Light subpaths
    start in vacuum, enter the fog through its top face and leave it through its
    sides and bottom (to the floor and back); next-event rays from the fog cross the
    top face at grazing angles just under the lamp.

    ``lamp_bsdf`` "black" for bdpt, "null" for volpath: Mitsuba 3.9.1's volpath has
    the flaw bdpt's connections had (media.Media._march): past a null face its
    next-event ray goes on along the old direction with the old remaining distance,
    from an origin offset along the face's normal, so the lamp's own surface blocks
    it at grazing crossings (here 4% of the rays from the fog to the lamp, with 7% of
    the light they carry; volpath's paths of length 2 are 13% too dark with a black
    lamp).  A null lamp lets those rays through, and with nothing behind it renders
    the image a black lamp does."""
    T = mi.ScalarTransform4f
    bsdf = ({"type": "null"} if lamp_bsdf == "null" else
            {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}})
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 39.3077,
                   "to_world": T().look_at([0, 0, 3.9], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "lamp": {"type": "rectangle", "bsdf": bsdf,
                 "to_world": T().translate([0, 0.99, 0]).rotate([1, 0, 0], 90).scale([0.23, 0.19, 1]),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [18.387, 13.9873, 6.75357]}}},
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90)},
        "fog": {"type": "cube", "to_world": T().scale(0.9), "bsdf": {"type": "null"},
                "interior": {"type": "homogeneous", "sigma_t": 0.6,
                             "albedo": {"type": "rgb", "value": [0.8, 0.7, 0.6]}}}})


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_every_technique_through_null_boundaries_matches_volpath(k):
    """The single techniques where light subpaths start outside the fog and cross its
    null faces in and out (issue 27): the (1, t) strategies' next-event rays were
    blocked by the lamp's own surface (media.Media._march), (1, 2) read 0.0178 against
    volpath's 0.0209."""
    _assert_techniques_match_volpath(_lamp_over_fog(12, "black"), k,
                                     ref_scene=_lamp_over_fog(12, "null"))


def test_light_tracing_through_null_boundaries_agrees_with_volpath():
    """Light tracing alone (every s, t = 1) in the scene above, against volpath."""
    lt = _bdpt(_lamp_over_fog(16, "black"), 64, 8, max_depth=8, strategy_subset="lt")
    assert_statistically_equal(lt, _volpath(_lamp_over_fog(16, "null"), 1024, 8),
                               what="light tracing, lamp over fog")


def test_fog_just_under_the_light_of_the_cornell_box():
    """Issue 27's scene: Mitsuba's Cornell box and a fog cube (scale 0.9, null faces)
    whose top face lies 0.09 under the light.  Connections across its top face were
    blocked by the light itself (media.Media._march): path tracing with next-event
    estimation read 7% darker than light tracing (red, 16x16: 0.1865 against 0.2014;
    Veach's BDPT 0.1995), at every path length from 2 on.  Volpath, which has the
    same flaw (see ``_lamp_over_fog``), cannot be the reference here; light tracing,
    path tracing and Veach's BDPT must agree."""
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=16, height=16, rfilter={"type": "box"})
    d["fog"] = {"type": "cube", "to_world": mi.ScalarTransform4f().scale(0.9), "bsdf": {"type": "null"},
                "interior": {"type": "homogeneous", "sigma_t": 0.6,
                             "albedo": {"type": "rgb", "value": [0.8, 0.7, 0.6]}}}
    scene = mi.load_dict(d)
    lt = _bdpt(scene, 64, 8, max_depth=8, strategy_subset="lt")
    assert_statistically_equal(_bdpt(scene, 256, 8, max_depth=8, strategy_subset="pt"), lt,
                               what="path tracing vs light tracing")
    assert_statistically_equal(_bdpt(scene, 64, 8, max_depth=8, light_paths=1, connections="all"), lt,
                               what="Veach's BDPT vs light tracing")


# -- the volumetric caustic ------------------------------------------------------------------
def test_volumetric_caustic_light_tracing_agrees_with_bdpt():
    """A point light focused by a glass ball into fog: volpath cannot render the
    cone (a camera path would have to reach a point light through glass), Mitsuba's
    ptracer has no media.  Light tracing alone (every s, t = 1) and full BDPT estimate
    the same image, except on the ball, which light tracing cannot see through."""
    scene = _load("volumetric-caustic.xml", res=16)
    lt = _bdpt(scene, 64, 8, max_depth=8, strategy_subset="lt")
    full = _bdpt(scene, 64, 8, max_depth=8)
    mask = ~specular_pixels(scene)
    assert_statistically_equal(lt, full, what="volumetric caustic", mask=mask)


def test_volumetric_caustic_of_a_sphere_light_agrees_with_volpath():
    """The same scene with a small sphere light of the same power, which volpath can
    render (slowly: its camera paths must hit the light through the ball)."""
    scene = _load("volumetric-caustic-sphere.xml", res=16)
    assert_statistically_equal(_bdpt(scene, 64, 8, max_depth=8), _volpath(scene, 2048, 8),
                               what="volumetric caustic, sphere light")


@pytest.mark.slow
@pytest.mark.parametrize("variant, scene", [("llvm_ad_spectral", "fog-cube.xml"),
                                            ("llvm_ad_spectral", "cloud.xml"),
                                            ("llvm_ad_mono", "fog-cube.xml")])
def test_spectral_and_mono_variants(variant, scene):
    """Media in the spectral (the hero wavelength's free-flight density) and mono
    variants; the spectral variant crashed while the RGB one passed (a transmittance of
    the medium's unpolarized type mixed into a Spectrum)."""
    assert_agrees_in_variant(variant, str(MEDIA / scene), "volpath")


# -- stability -------------------------------------------------------------------------------
@pytest.mark.parametrize("params", [{"scale": 100.0}, {"albedo": 0.999}, {"albedo": 0.0}],
                         ids=["dense", "white", "black"])
def test_stable_where_free_flights_fail(params):
    """Dense fog (optical depth ~100 across the cube), fog that scatters almost all
    light (long walks) and fog that absorbs everything: no NaN or inf, and two seeds
    agree with volpath."""
    scene = _load("fog-cube.xml", res=16, **params)
    b = _bdpt(scene, 32, 6, max_depth=-1 if params.get("albedo") == 0.999 else 8)
    assert all(np.isfinite(x).all() for x in b)
    md = 64 if params.get("albedo") == 0.999 else 8
    assert_statistically_equal(b, _volpath(scene, 512, 6, max_depth=md), what=str(params))


def _room_seen_from(z, medium):
    """A fog room (the cube [-2, 2]^3) with a point light and a floor inside; the camera
    on the axis at z, looking in, with the sensor's medium ``medium``."""
    T = mi.ScalarTransform4f
    sensor = {"type": "perspective", "fov": 60, "to_world": T().look_at([0, 0, z], [0, 0, 0], [0, 1, 0]),
              "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}}
    if medium:
        sensor["medium"] = {"type": "ref", "id": "fog"}
    return mi.load_dict({
        "type": "scene", "sensor": sensor,
        "fog": {"type": "homogeneous", "id": "fog", "sigma_t": 0.5, "albedo": 0.8},
        "room": {"type": "cube", "bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "fog"},
                 "to_world": T().scale(2.0)},
        "light": {"type": "point", "position": [0, 1, 0], "intensity": {"type": "rgb", "value": 5.0}},
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(1.5)}})


def test_camera_on_a_medium_boundary():
    """A camera exactly on the null face of a fog room, looking in.  Its rays start at
    near_clip, inside the fog: declaring the fog as the sensor's medium renders as
    volpath does; declaring none was an image whose light-image half (3.2x too bright)
    disagreed with its camera half, and is now refused, naming the medium."""
    scene = _room_seen_from(2.0, medium=True)
    imgs = _bdpt(scene, 32, 6, max_depth=6)
    assert all(np.isfinite(x).all() for x in imgs)
    assert_statistically_equal(imgs, _volpath(scene, 512, 6, max_depth=6), what="camera on boundary")
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="near_clip.*'fog'|'fog'.*near_clip"):
        bdpt_drjit.render(_room_seen_from(2.0, medium=False), spp=1)


def test_camera_outside_a_fog_room():
    scene = _room_seen_from(2.5, medium=False)
    assert_statistically_equal(_bdpt(scene, 32, 6, max_depth=6), _volpath(scene, 512, 6, max_depth=6),
                               what="camera outside the fog")


# -- what is refused ----------------------------------------------------------------------
def _fog_box(**over):
    T = mi.ScalarTransform4f
    d = {"type": "scene",
         "sensor": {"type": "perspective", "to_world": T().look_at([0, 1, 3], [0, 0, 0], [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 8, "height": 8}},
         "box": {"type": "cube", "bsdf": {"type": "null"},
                 "interior": {"type": "homogeneous", "id": "fog", "sigma_t": 2.0}},
         "light": {"type": "point", "position": [0, 2, 0]}}
    d.update(over)
    return mi.load_dict(d)


def test_sggx_phase_is_refused_by_name():
    box = {"type": "cube", "bsdf": {"type": "null"},
           "interior": {"type": "homogeneous", "id": "flakes", "sigma_t": 2.0,
                        "phase": {"type": "sggx", "S": {"type": "gridvolume", "grid": mi.VolumeGrid(
                            np.tile(np.float32([1, 1, 1, 0, 0, 0]), (2, 2, 2, 1)))}}}}
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="flakes"):
        bdpt_drjit.render(_fog_box(box=box), spp=1)


def test_sensor_medium_that_is_not_around_the_camera_is_refused():
    """The camera is outside the fog box but declares the fog as its medium: the two
    subpaths would disagree about where they travel."""
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "fog": {"type": "homogeneous", "id": "fog", "sigma_t": 1.0},
        "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "fog"}},
        "light": {"type": "point", "position": [0, 0.5, 0]},
        "sensor": {"type": "perspective", "medium": {"type": "ref", "id": "fog"},
                   "to_world": T().look_at([0, 1, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8}}})
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="rays start inside"):
        bdpt_drjit.render(scene, spp=1)


def test_environment_inside_an_unbounded_medium_is_refused():
    scene = mi.load_dict({
        "type": "scene",
        "fog": {"type": "homogeneous", "id": "fog", "sigma_t": 0.2},
        "sky": {"type": "constant"},
        "sensor": {"type": "perspective", "medium": {"type": "ref", "id": "fog"},
                   "film": {"type": "hdrfilm", "width": 8, "height": 8}}})
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="infinity"):
        bdpt_drjit.render(scene, spp=1)


def test_info_reports_media_as_rendered():
    """``bdpt info`` says what the render does with each medium."""
    from bdpt_drjit import support
    scene = _load("cloud.xml", res=8)
    verdicts = [v for v in support.inspect(scene, scene.sensors()[0]) if v.kind == "medium"]
    assert len(verdicts) == 1 and verdicts[0].status == support.SUPPORTED
    assert "heterogeneous" in verdicts[0].name and "distance densities" in verdicts[0].reason
