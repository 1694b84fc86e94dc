"""Mitsuba's own render regression scenes (../shared/scenes/external/mitsuba-tests):
every BSDF on a grid of spheres under an area light, a point light, a constant and an
environment-map sky, with normal and bump maps and textures (max_depth 2); mirror
spheres reflecting each other under an environment map (max_depth 8); a textured spot
light; a sphere under a directional light; area lights (two of them textured, one
on a sphere mesh), spots (one textured), a textured projector and a point light side
by side (max_depth 4).  The references are Mitsuba's path tracer at 32000 samples
per pixel, written by another Mitsuba version; BDPT must agree with them
statistically (block means, t-test over seeds, ``stats.assert_matches_reference``).
"""
from pathlib import Path

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
import bdpt_drjit
from bdpt_drjit import support
from conftest import external
from stats import assert_matches_reference

TESTS = Path("mitsuba-tests", "tests", "scenes")
BSDF_SPHERES = ["arealight", "bumpmap", "constant", "envmap", "normalmap",
                "normalmap_identity_roughconductor", "normalmap_roughconductor", "pointlight",
                "roughdielectric", "roughplastic_linear", "roughplastic_nonlinear",
                "textured_diffuse", "textured_roughconductor", "texturedprincipled1",
                "texturedprincipled2", "texturedprincipledthin"]
CASES = ([("bsdf_spheres", "test_%s_path.xml" % n, "test_%s_ref_rgb" % n, 2) for n in BSDF_SPHERES]
         + [("infinite_mirrors", "scene_path.xml", "scene_ref_rgb", 8),
            ("spot_light", "test_spot_direct.xml", "test_spot_ref_rgb", 2),
            ("floating_sphere", "test_directional_direct.xml", "test_directional_ref_rgb", 2),
            ("various_emitters", "test_various_emitters_ptracer.xml", "test_various_emitters_ref_rgb", 4)])
REF_SPP = 32000


@pytest.mark.slow
@pytest.mark.parametrize("folder, xml, ref, max_depth", CASES, ids=[c[1] for c in CASES])
def test_agrees_with_mitsuba_reference(folder, xml, ref, max_depth):
    path = external(*TESTS.parts, folder, xml)
    # The scenes wrap their integrator in "moment"; only the scene is used here.  Loaded
    # as the API loads files: Mitsuba's shape merging orders the emitters of
    # test_various_emitters_ptracer.xml differently from process to process.
    scene = support.load_file(path, integrator="path")
    ref_img = bdpt_drjit.read_exr(path.parent / "refs" / (ref + ".exr"))[0]
    ref_var = bdpt_drjit.read_exr(path.parent / "refs" / (ref + "_var.exr"))[0]
    imgs = [bdpt_drjit.render(scene, spp=128, seed=s, max_depth=max_depth).image[..., :3]
            for s in range(8)]
    assert all(np.isfinite(im).all() for im in imgs)
    assert_matches_reference(imgs, ref_img, ref_var, REF_SPP, what=xml)


@pytest.mark.parametrize("name", BSDF_SPHERES)
def test_light_vertex_record_evaluates_like_the_interaction(name):
    """A stored light vertex keeps only part of its SurfaceInteraction
    (surface.VertexRecord).  Every BSDF here (normal and bump maps, textures,
    principled) must give the same values and pdfs, in both transport modes, from the
    record as from the full interaction: the reference scenes render at max_depth 2,
    where no stored vertex is ever connected (s, t >= 2 needs k >= 3), so only this
    test sees a field the record drops (a bump map reads dp_du and dp_dv)."""
    from bdpt_drjit.surface import Vertex, VertexRecord
    path = external(*TESTS.parts, "bsdf_spheres", "test_%s_path.xml" % name)
    scene = mi.load_file(str(path), integrator="path")
    n = 4096
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7, n)
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, sampler.next_2d(), sampler.next_2d())
    si = scene.ray_intersect(ray)
    hit = si.is_valid()
    assert dr.count(hit)[0] > n // 8, "the camera should see the spheres"
    record = VertexRecord.of(Vertex(si, si.bsdf())).interaction(si.time, si.wavelengths)
    wo = mi.warp.square_to_uniform_sphere(sampler.next_2d())
    for mode in (mi.TransportMode.Radiance, mi.TransportMode.Importance):
        ctx = mi.BSDFContext(mode)
        f_full, pdf_full = si.bsdf().eval_pdf(ctx, si, wo, hit)
        f_rec, pdf_rec = record.bsdf().eval_pdf(ctx, record, wo, hit)
        for full, rec, what in ((f_full, f_rec, "value"), (pdf_full, pdf_rec, "pdf")):
            full, rec = np.array(full), np.array(rec)
            assert np.isfinite(full).all() and np.isfinite(rec).all()
            np.testing.assert_allclose(rec, full, rtol=1e-5, atol=1e-6,
                                       err_msg="%s: %s in %s mode" % (name, what, mode))
