"""Mitsuba's own render regression scenes (../shared/scenes/external/mitsuba-tests):
every BSDF on a grid of spheres under an area light, a point light, a constant and an
environment-map sky, with normal and bump maps and textures (max_depth 2); mirror
spheres reflecting each other under an environment map (max_depth 8); a textured spot
light; a sphere under a directional light.  The references are Mitsuba's path tracer at 32000 samples per pixel, written
by another Mitsuba version; BDPT must agree with them statistically (block means,
t-test over seeds, ``conftest.assert_matches_reference``).  The scene with a
projector, which bdpt does not support, must raise an error naming the plugin.
"""
from pathlib import Path

import numpy as np
import pytest

import mitsuba as mi
import bdpt_drjit
from conftest import assert_matches_reference, external

TESTS = Path("mitsuba-tests", "tests", "scenes")
BSDF_SPHERES = ["arealight", "bumpmap", "constant", "envmap", "normalmap",
                "normalmap_identity_roughconductor", "normalmap_roughconductor", "pointlight",
                "roughdielectric", "roughplastic_linear", "roughplastic_nonlinear",
                "textured_diffuse", "textured_roughconductor", "texturedprincipled1",
                "texturedprincipled2", "texturedprincipledthin"]
CASES = ([("bsdf_spheres", "test_%s_path.xml" % n, "test_%s_ref_rgb" % n, 2) for n in BSDF_SPHERES]
         + [("infinite_mirrors", "scene_path.xml", "scene_ref_rgb", 8),
            ("spot_light", "test_spot_direct.xml", "test_spot_ref_rgb", 2),
            ("floating_sphere", "test_directional_direct.xml", "test_directional_ref_rgb", 2)])
REF_SPP = 32000


@pytest.mark.slow
@pytest.mark.parametrize("folder, xml, ref, max_depth", CASES, ids=[c[1] for c in CASES])
def test_agrees_with_mitsuba_reference(folder, xml, ref, max_depth):
    path = external(*TESTS.parts, folder, xml)
    # The scenes wrap their integrator in "moment"; only the scene is used here.
    scene = mi.load_file(str(path), integrator="path")
    ref_img = bdpt_drjit.read_exr(path.parent / "refs" / (ref + ".exr"))[0]
    ref_var = bdpt_drjit.read_exr(path.parent / "refs" / (ref + "_var.exr"))[0]
    imgs = [bdpt_drjit.render(scene, spp=128, seed=s, max_depth=max_depth).image[..., :3]
            for s in range(8)]
    assert all(np.isfinite(im).all() for im in imgs)
    assert_matches_reference(imgs, ref_img, ref_var, REF_SPP, what=xml)


def test_unsupported_emitters_are_refused():
    path = external(*TESTS.parts, "various_emitters", "test_various_emitters_ptracer.xml")
    scene = mi.load_file(str(path), integrator="path")
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="'projector'"):
        bdpt_drjit.render(scene, spp=1)
