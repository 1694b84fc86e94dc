"""Statistical agreement with Mitsuba's own integrators.

Every comparison pools pixels into blocks and runs a z-test whose variance comes
from independent seeds of both renderers (stats.assert_statistically_equal).
"""
import numpy as np
import pytest

import mitsuba as mi
import bdpt_drjit
from conftest import mitsuba_render, scene_path, specular_pixels
from stats import assert_statistically_equal

SEEDS = 10


def load(name, res=24, **params):
    return mi.load_file(scene_path(name), resx=res, resy=res, **params)


def bdpt_images(scene, spp, seeds=SEEDS, **settings):
    return [bdpt_drjit.render(scene, spp=spp, seed=100 + s, **settings).image for s in range(seeds)]


def mitsuba_images(scene, integrator, spp, seeds=SEEDS, **props):
    return [mitsuba_render(scene, integrator, spp, seed=200 + s, **props) for s in range(seeds)]


@pytest.fixture(scope="module")
def cornell():
    return load("cornell-box.xml", res=16)


def path_images_by_length(scene, k_max=4, spp=256):
    """Mitsuba's path tracer restricted to paths of exactly k edges, k = 1..k_max:
    path(max_depth=k) - path(max_depth=k-1), from independent seeds."""
    out = {}
    prev = [0.0] * SEEDS
    for k in range(1, k_max + 1):
        cur = mitsuba_images(scene, "path", spp, max_depth=k)
        out[k] = [c - p for c, p in zip(cur, prev)]
        prev = [mitsuba_render(scene, "path", spp, seed=300 + s, max_depth=k) for s in range(SEEDS)]
    return out


@pytest.fixture(scope="module")
def path_by_length(cornell):
    return path_images_by_length(cornell)


@pytest.mark.slow
@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_every_single_technique_matches_path_tracing(cornell, path_by_length, k):
    """Each (s,t) alone, unweighted, is an unbiased estimator of all paths of length
    k on a diffuse scene (no delta vertices: every technique can sample every path)."""
    for s in range(k + 1):
        t = k + 1 - s
        imgs = bdpt_images(cornell, 32, technique=(s, t), max_depth=k)
        assert all(np.isfinite(i).all() for i in imgs)
        assert_statistically_equal(imgs, path_by_length[k], what="technique (%d,%d)" % (s, t))


@pytest.mark.slow
@pytest.mark.parametrize("name, settings, res, spp, ref_spp", [
    ("cornell-box.xml", {}, 24, 32, 128),
    ("cornell-light-up.xml", {}, 24, 32, 256),
    ("glass-pane.xml", {}, 24, 32, 128),
])
def test_full_bdpt_matches_path_tracing(name, settings, res, spp, ref_spp):
    scene = load(name, res=res)
    ours = bdpt_images(scene, spp, max_depth=8, **settings)
    ref = mitsuba_images(scene, "path", ref_spp, max_depth=8, **settings)
    for img in ours:
        assert np.isfinite(img).all()
    assert_statistically_equal(ours, ref, what=name)


@pytest.mark.slow
def test_point_light_caustic_matches_particle_tracer():
    """A point light focused by a glass sphere onto a floor, seen from where the
    sphere is out of view.  A path tracer cannot render this caustic at all: the
    light is a point (never hit) and the sphere is a delta BSDF (no NEE through it),
    so only light tracing (t = 1) samples these paths; Mitsuba's ptracer converges."""
    scene = load("point-caustic.xml", res=24)
    ours = bdpt_images(scene, 32, max_depth=8)
    ref = mitsuba_images(scene, "ptracer", 128, max_depth=8)
    assert_statistically_equal(ours, ref, what="point caustic")
    # and the caustic is really there: far brighter than what path tracing sees
    path = mitsuba_images(scene, "path", 64, seeds=1, max_depth=8)[0]
    assert np.mean(ours) > 2 * path.mean()


@pytest.mark.slow
def test_glass_and_mirror_spheres_small_light():
    """Glass and mirror spheres under a small area light.  No Mitsuba integrator
    converges everywhere here, so each pixel class gets the reference that does:
      * pixels that see only diffuse surfaces: Mitsuba's ptracer (the mirror's and the
        glass's caustics on the walls, ceiling and floor are light-traced paths that
        Mitsuba's path tracer finds only as rare fireflies: at 5000 spp its mean on the
        caustic-lit ceiling is still unconverged, with a seed spread that hides them);
      * pixels that see the glass or the mirror: Mitsuba's path tracer (a light tracer
        cannot reach the camera through a delta surface).
    Emitters are hidden: the light's sub-pixel images dominate the variance otherwise."""
    scene = load("cornell-spheres.xml", res=24)
    spec = specular_pixels(scene)
    assert 0.05 < spec.mean() < 0.6
    ours = bdpt_images(scene, 64, max_depth=8, hide_emitters=True)
    assert all(np.isfinite(i).all() for i in ours)
    lt = mitsuba_images(scene, "ptracer", 256, max_depth=8, hide_emitters=True)
    assert_statistically_equal(ours, lt, mask=~spec, what="spheres, diffuse pixels vs ptracer")
    pt = mitsuba_images(scene, "path", 512, max_depth=8, hide_emitters=True)
    assert_statistically_equal(ours, pt, mask=spec, blocks=2, what="spheres, specular pixels vs path")


def _light_above_a_mirror():
    """A floor lit only through a mirror: a large area light 1 above it faces up, to a
    mirror 1 above the light (L, mirror, floor, camera)."""
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 50,
                   "to_world": T().look_at(origin=[0, 0.8, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16,
                            "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}},
        "mirror": {"type": "rectangle", "bsdf": {"type": "conductor"},
                   "to_world": T().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(3)},
        "light": {"type": "rectangle",
                  "to_world": T().translate([0, 1, 0]).rotate([1, 0, 0], -90).scale(0.5),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 10.0}}},
    })


def test_lafortune_weights_keep_light_through_a_mirror():
    """L&W's weights follow the camera vertices' specularity; a connection from the
    floor to the mirror's vertex cannot be made, yet it got the path's whole weight, and
    the image came out black.  Its share now goes on along the camera path (to the
    camera subpath that hits the light through the mirror): Veach's BDPT agrees."""
    scene = _light_above_a_mirror()
    ours = bdpt_images(scene, 64, seeds=8, max_depth=4, mis="lafortune")
    ref = bdpt_images(scene, 64, seeds=8, max_depth=4, light_paths=1, connections="all")
    assert np.mean(ref) > 0.05
    assert_statistically_equal(ours, ref, what="L&W weights, light through a mirror")
