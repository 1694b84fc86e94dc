"""Environment and directional emitters (``constant``, ``envmap``, ``directional``):
light subpaths that start at infinity, on a disk beyond the scene's bounding sphere,
with solid-angle densities in MIS (VCM technical report, section 5.1).

1. Analytic: a convex diffuse sphere of albedo r under a constant environment L
   reflects exactly r L everywhere (it sees nothing but the environment), for every
   heuristic, with and without the light image, for the path-tracing and
   light-tracing subsets, and for each strategy of those length-2 paths alone
   (s = 0 on an escaping ray, next-event estimation, and light paths from infinity).
2. Analytic: a diffuse floor of albedo r under a directional light of irradiance E
   has radiance r E / pi, for each heuristic and strategy set.
3. Against Mitsuba's ``path``: an environment map (a bright lobe over a dim sky) lights
   a floor, a diffuse sphere, a rough metal sphere and a glass sphere; statistical
   agreement over independent seeds, with ``hide_emitters`` on and off.
"""
import numpy as np
import pytest

import mitsuba as mi
import bdpt_drjit
from conftest import mitsuba_render
from stats import assert_statistically_equal

T = mi.ScalarTransform4f
L, ALBEDO = 1.0, 0.5


def _sensor(res, origin, target, fov):
    return {"type": "perspective", "fov": fov,
            "to_world": T().look_at(origin=origin, target=target, up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}}


@pytest.fixture(scope="module")
def sphere_under_sky():
    # The camera sees only the sphere (half-angle 10 deg against 14.5 deg).
    return mi.load_dict({
        "type": "scene",
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": L}},
        "ball": {"type": "sphere", "bsdf": {"type": "diffuse",
                                            "reflectance": {"type": "rgb", "value": ALBEDO}}},
        "sensor": _sensor(16, [0, 0, 4], [0, 0, 0], 20)})


@pytest.mark.parametrize("settings", [
    dict(), dict(mis="balance"), dict(mis="uniform"), dict(light_image=False),
    dict(strategy_subset="pt"), dict(strategy_subset="lt"), dict(max_depth=-1),
    # Every reflected path has length 2: each of its strategies alone sees all of it.
    dict(technique=(0, 3)), dict(technique=(1, 2)), dict(technique=(2, 1))])
def test_convex_sphere_under_constant_sky_reflects_albedo_times_sky(sphere_under_sky, settings):
    settings = {"max_depth": 4, **settings}
    means = [bdpt_drjit.render(sphere_under_sky, spp=64, seed=seed, **settings).image[4:12, 4:12]
             for seed in range(6)]
    assert all(np.isfinite(m).all() for m in means)
    per_seed = np.array([m.mean() for m in means])
    mean, se = per_seed.mean(), per_seed.std(ddof=1) / np.sqrt(len(per_seed))
    # 4.5 standard errors (false alarm ~1e-5), and 1e-4 for renders without variance.
    assert abs(mean - ALBEDO * L) <= 4.5 * se + 1e-4, (mean, se)


def _sky_bitmap():
    """A dim blue sky with a bright warm lobe (what importance sampling is for)."""
    h, w = 32, 64
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1)
    lobe = np.exp(40 * (d @ np.array([0.5, 0.7, 0.5]) / np.linalg.norm([0.5, 0.7, 0.5]) - 1))
    img = 0.2 * np.array([0.4, 0.6, 1.0]) + 20 * lobe[..., None] * np.array([1.0, 0.8, 0.5])
    return mi.Bitmap(img.astype(np.float32))


@pytest.fixture(scope="module")
def envmap_scene():
    def sphere(x, bsdf):
        return {"type": "sphere", "center": [x, 0, 0], "radius": 0.4, "bsdf": bsdf}
    return mi.load_dict({
        "type": "scene",
        "sky": {"type": "envmap", "bitmap": _sky_bitmap()},
        "floor": {"type": "rectangle", "to_world": T().translate([0, -0.4, 0]).rotate([1, 0, 0], -90)
                  @ T().scale(3), "bsdf": {"type": "diffuse"}},
        "matte": sphere(-1.0, {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.3, 0.3]}}),
        "metal": sphere(0.0, {"type": "roughconductor", "alpha": 0.2}),
        "glass": sphere(1.0, {"type": "dielectric"}),
        "sensor": _sensor(24, [0, 1.0, 4], [0, 0, 0], 45)})


@pytest.mark.slow
@pytest.mark.parametrize("hide", [False, True])
def test_envmap_scene_matches_mitsuba_path(envmap_scene, hide):
    seeds = range(8)
    ours = [bdpt_drjit.render(envmap_scene, spp=64, seed=s, max_depth=6, hide_emitters=hide).image
            for s in seeds]
    ref = [mitsuba_render(envmap_scene, "path", 64, 100 + s, max_depth=6, hide_emitters=hide)
           for s in seeds]
    assert all(np.isfinite(im).all() for im in ours)
    assert_statistically_equal(ours, ref, what="envmap, hide_emitters=%s" % hide)


@pytest.fixture(scope="module")
def floor_under_sun():
    return mi.load_dict({
        "type": "scene",
        "sun": {"type": "directional", "direction": [0, -1, 0],
                "irradiance": {"type": "rgb", "value": 2.0}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90) @ T().scale(5),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": ALBEDO}}},
        "sensor": _sensor(16, [0, 3, 3], [0, 0, 0], 30)})


@pytest.mark.parametrize("settings", [
    dict(), dict(mis="balance"), dict(mis="uniform"), dict(light_image=False),
    dict(strategy_subset="lt"), dict(technique=(1, 2)), dict(technique=(2, 1))])
def test_floor_under_directional_light(floor_under_sun, settings):
    per_seed = np.array([bdpt_drjit.render(floor_under_sun, spp=64, seed=s, max_depth=3,
                                           **settings).image[..., :3].mean() for s in range(6)])
    mean, se = per_seed.mean(), per_seed.std(ddof=1) / np.sqrt(len(per_seed))
    assert abs(mean - ALBEDO * 2.0 / np.pi) <= 4.5 * se + 1e-4, (mean, se)


@pytest.mark.parametrize("direction", [[0.3, -1, -0.2], [0.3, -1, 0.2]])
def test_light_from_infinity_covers_merged_meshes(direction):
    """A floor and a wall that share a BSDF, beside a sphere, under a directional light:
    Mitsuba merges the two into one mesh whose bounding box is invalid, and
    scene.bbox() leaves it out.  Light subpaths from infinity start on a disk that must
    cover the whole scene (support.scene_bbox), and shadow rays toward the light must
    leave it (Emitters.past_the_scene), so light tracing alone and path tracing alone
    agree.  Failed before: the disk covered the sphere only (light tracing read 0.038
    against path tracing's 0.375); with the light behind the wall, Mitsuba's shadow
    rays ended inside the scene (path tracing read 4% bright, as Mitsuba's path and
    volpath still do: 0.233 against 0.2245 unmerged)."""
    shared = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at(origin=[0, 1, 4], target=[0, 0.3, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3), "bsdf": shared},
        "wall": {"type": "rectangle", "to_world": T().translate([0, 1.5, -1.5]).scale(3), "bsdf": shared},
        "ball": {"type": "sphere", "to_world": T().translate([0, 0.5, 0]).scale(0.5)},
        "sun": {"type": "directional", "direction": direction,
                "irradiance": {"type": "rgb", "value": 3.0}}})
    assert any(s.is_mesh() and not s.bbox().valid() for s in scene.shapes())  # merged
    lt = [bdpt_drjit.render(scene, spp=2048, seed=s, max_depth=-1, strategy_subset="lt").image
          for s in range(8)]
    pt = [bdpt_drjit.render(scene, spp=64, seed=100 + s, max_depth=-1, strategy_subset="pt").image
          for s in range(8)]
    assert_statistically_equal(lt, pt, what="directional light over merged meshes")
