"""Mitsuba plugins beyond the basic set (scenes/plugins): curves and instances beside
an area light, projectors, sunsky, pass-through (null-lobe) BSDFs, and the
refusal of emitters on shapes that cannot be sampled.  Each image is compared with
Mitsuba's own integrators by statistics (stats.assert_statistically_equal, Welch's
t-test on block means over independent seeds)."""
import gc
import os
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit
from bdpt_drjit.emitters import Emitters, ProjectorModel
from conftest import ROOT, cli_env, mitsuba_render
from stats import assert_statistically_equal

PLUGINS = ROOT / "scenes" / "plugins"
SEEDS = 8


def load(name, **params):
    return mi.load_file(str(PLUGINS / name), resx=16, resy=16, **params)


def agree(scene, reference, max_depth, ref_spp=256, spp=64, what=""):
    """bdpt against Mitsuba's ``reference`` integrator; returns the means and the
    worst t as a fraction of its threshold."""
    # Dr.Jit traces a virtual call for every registered object: let other tests'
    # scenes go first (Mitsuba's own integrators trip on some of them).
    gc.collect()
    ref = [mitsuba_render(scene, reference, ref_spp, seed, max_depth=max_depth)
           for seed in range(SEEDS)]
    ours = [bdpt_drjit.render(scene, spp=spp, seed=100 + seed, max_depth=max_depth).image
            for seed in range(SEEDS)]
    worst = assert_statistically_equal(ours, ref, what=what)
    return np.mean(ours), np.mean(ref), worst


# -- curves and instances (task: they crashed as soon as there was an area light) --------
@pytest.mark.parametrize("name, params", [
    ("curve-beside-box.xml", {"curve": "bsplinecurve"}),
    ("curve-beside-box.xml", {"curve": "linearcurve"}),
    ("instance-beside-box.xml", {})], ids=["bsplinecurve", "linearcurve", "instance"])
def test_curves_and_instances_beside_an_area_light_agree_with_path(name, params):
    """Light subpaths once started with ``emitter.get_shape().sample_position``: a
    virtual call over *every* registered shape, and curves and instances raise
    "Shape::sample_position(): not implemented!"."""
    agree(load(name, **params), "path", 6, what=name)


def test_a_curve_alive_in_another_scene_does_not_matter(box):
    """Dr.Jit traces a virtual call for every instance it has registered, so a curve
    loaded for another scene broke renders of the Cornell box in the same process."""
    other = load("curve-beside-box.xml")
    res = bdpt_drjit.render(box, spp=1, max_depth=3)
    assert np.isfinite(res.image).all() and res.image.mean() > 0
    del other


def test_cli_renders_curves_beside_an_area_light(tmp_path):
    p = subprocess.run([sys.executable, "-m", "bdpt_drjit", "render",
                        str(PLUGINS / "curve-beside-box.xml"), "-D", "resx=8", "-D", "resy=8",
                        "--spp", "1", "-o", str(tmp_path / "c.exr")],
                       capture_output=True, text=True, timeout=300,
                       env=cli_env())
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "c.exr").is_file()


def test_an_area_light_on_a_curve_is_refused_naming_the_shape():
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="'bsplinecurve'"):
        bdpt_drjit.render(load("area-light-on-curve.xml"), spp=1)


@pytest.mark.parametrize("shape", ["rectangle", "disk", "sphere", "cylinder", "cube"])
@pytest.mark.parametrize("textured", [False, True], ids=["uniform", "textured"])
def test_light_subpaths_start_with_density_one_over_area(shape, textured):
    """The MIS weights of s = 0 and s = 1 assume that light subpaths start uniformly,
    density 1/A, on an area light; a textured light would sample its texture, so its
    shape is sampled directly."""
    radiance = ({"type": "checkerboard", "color0": 1.0, "color1": 5.0} if textured else 1.0)
    scene = mi.load_dict({"type": "scene", "light": {
        "type": shape, "to_world": mi.ScalarTransform4f().scale([0.5, 0.7, 1.3]),
        "emitter": {"type": "area", "radiance": radiance}}})
    emitters = Emitters(scene)
    k = np.arange(4096)
    u = mi.Point2f((k + 0.5) / k.size, (k * 0.618034) % 1.0)
    ps = emitters.sample_position(mi.UInt32(0), dr.gather(mi.EmitterPtr, emitters.ptrs,
                                                           mi.UInt32(0)), 0.0, u)
    area = scene.shapes()[0].surface_area()[0]
    np.testing.assert_allclose(ps.pdf.numpy(), 1.0 / area, rtol=1e-4)
    # Uniform: the points' mean is the centroid, the middle of these symmetric shapes.
    center = np.array(scene.shapes()[0].bbox().center())
    assert np.abs(np.mean(ps.p.numpy(), axis=-1) - center).max() < 0.02


# -- projector -------------------------------------------------------------------------------
def test_projector_model_is_mitsubas_sample_ray():
    """ProjectorModel's density and intensity give, sample by sample, the weight
    Mitsuba's sample_ray returns (I(d) / pdf(d)), and its directions."""
    scene = load("projector-wall.xml")
    emitter = scene.emitters()[0]
    model = ProjectorModel(emitter)
    rng = np.random.default_rng(3)
    u = mi.Point2f(*rng.random((2, 20000)).astype(np.float32))
    ray, weight = emitter.sample_ray(0.0, 0.5, mi.Point2f(0.5), u)
    d, uv = model.sample(u)
    np.testing.assert_allclose(d.numpy(), ray.d.numpy(), atol=2e-6)
    intensity = Emitters(scene).emitted(mi.EmitterPtr(emitter), ray.o, model.to_world @ mi.Vector3f(0, 0, 1),
                                        uv, ray.d, True, dr.zeros(mi.Interaction3f).wavelengths, 0.0)
    ok = weight.x.numpy() > 0
    assert ok.mean() > 0.5
    ratio = (intensity.x / model.pdf_w(ray.d)).numpy()[ok] / weight.x.numpy()[ok]
    np.testing.assert_allclose(ratio, 1.0, rtol=1e-4)


@pytest.mark.parametrize("reference", ["path", "ptracer"])
def test_projector_agrees_with_path_and_ptracer(reference):
    """A textured projector (a ramp with a black cross and a bright cell) on a wall:
    direct and indirect light, max_depth 4."""
    agree(load("projector-wall.xml"), reference, 4, what="projector vs " + reference)


def test_a_scaled_projector_is_refused():
    """Mitsuba's projector leaves a to_world scale out of sample_ray and squares it in
    sample_direction: scaled by 2, path renders 0.155 and ptracer 0.077 (max_depth 2),
    so there is no right image to match."""
    scene = load("projector-wall.xml")
    params = mi.traverse(scene)
    params["projector.to_world"] = params["projector.to_world"] @ mi.ScalarTransform4f().scale(2)
    params.update()
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="'projector'.*scales"):
        bdpt_drjit.render(scene, spp=1)


# -- sunsky -----------------------------------------------------------------------------------
def test_sunsky_agrees_with_path():
    """Sun and sky: an environment emitter with its own direction sampling."""
    agree(load("sunsky-ball.xml"), "path", 3, what="sunsky")


def test_timed_sunsky_is_refused():
    """Mitsuba 3.9.1's own path fails on it in JIT variants (jit_var_schedule(): not
    permitted, from inside its traced emitter call)."""
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="'timed_sunsky'"):
        bdpt_drjit.render(load("sunsky-ball.xml", sky="timed_sunsky"), spp=1)


# -- pass-through BSDFs ------------------------------------------------------------------------
@pytest.mark.parametrize("pane", ["null", "thindielectric"])
def test_pass_through_panes_agree_with_volpath(pane):
    """A null or thin-dielectric pane between the light and the floor: bdpt makes a
    vertex where a path crosses it, and every strategy that would connect there gets
    weight 0 (the null lobe has no density), so the image is right.  Unbounded depth:
    bdpt (like path) counts each crossing as a bounce, volpath does not."""
    with pytest.warns(UserWarning, match="pass through"):
        agree(load("null-pane.xml", pane=pane), "volpath", -1, ref_spp=512, spp=128,
              what=pane)
