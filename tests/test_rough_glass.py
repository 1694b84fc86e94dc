"""Light subpaths through rough glass: the light walk's throughput at a rough dielectric.

A light subpath scatters with Mitsuba's sampler (``bsdf.sample`` in importance mode) but
takes its weight from the adjoint BSDF, f_adj / pdf (walk._scatter, surface.eval_adjoint).
That is only right for samples the BSDF accepts.  ``roughdielectric`` samples a
microfacet normal m and reflects or refracts wi about it; where the result lands on the
wrong side of the macrosurface (a reflection below it, a refraction back above) the
sample is invalid and Mitsuba returns weight 0, with bs.wo and the pdf of the sampled
lobe still set.  Evaluating the BSDF at that wo sees the *other* lobe (with a different
half vector), so f_adj / bs.pdf is large and positive for a path that no density
accounts for.  At normal incidence on GGX alpha 0.5 about 1% of samples are such, and
they carried 40% of the transported energy (1.60 instead of 0.97).

Three checks, each failing before the fix by a wide margin (t-values in the asserts):
  * one light-walk scatter off a flat rough-glass interface transports the BSDF's
    directional albedo (Mitsuba's own sample weights give it);
  * a point light inside a rough-glass globe (scenes/stress/rough-glass-lamp.xml):
    light tracing (strategy_subset="lt") agrees with Mitsuba's ptracer;
  * the single unweighted technique (3,1) agrees with (1,3), the same path length
    sampled from the camera side.
About 5 s on 2 cores.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
import bdpt_drjit
from bdpt_drjit.mis import Weights
from bdpt_drjit.settings import Settings
from bdpt_drjit.strategies import StrategySet
from bdpt_drjit.surface import Vertex
from bdpt_drjit.walk import DepthSamples, PathState, _scatter
from conftest import mitsuba_render, scene_path
from stats import assert_statistically_equal

LAMP = scene_path("stress/rough-glass-lamp.xml")
SEEDS = 8
IMPORTANCE = mi.BSDFContext(mi.TransportMode.Importance)


def _interface_hits(alpha: float, cos_i: float, side: int, n: int):
    """n hits on a flat GGX rough-glass square (normal +z), arriving at incidence
    cos_i from the front (side 1) or from inside the glass (side -1)."""
    scene = mi.load_dict({
        "type": "scene",
        "glass": {"type": "rectangle",
                  "bsdf": {"type": "roughdielectric", "distribution": "ggx", "alpha": alpha,
                           "int_ior": 1.5, "ext_ior": 1.0}}})
    sin_i = math.sqrt(1 - cos_i * cos_i)
    d = mi.Vector3f(sin_i, 0.0, -side * cos_i)            # toward the surface
    ray = mi.Ray3f(mi.Point3f(-0.5 * sin_i, 0.0, 0.5 * side * cos_i) + dr.zeros(mi.Point3f, n), d)
    si = scene.ray_intersect(ray)
    assert dr.all(si.is_valid())
    return scene, si


def _sampler(seed: int, n: int) -> mi.Sampler:
    s = mi.load_dict({"type": "independent"})
    s.seed(seed, n)
    return s


@pytest.mark.parametrize("alpha, cos_i, side", [(0.5, 0.99, 1), (0.5, 0.99, -1),
                                                (0.3, 0.99, -1), (0.3, 0.7, -1)])
def test_light_walk_scatter_transports_the_bsdf_albedo(alpha, cos_i, side):
    """E[beta] after one light-walk scatter (walk._scatter, importance=True) equals the
    directional albedo that Mitsuba's own importance-mode sample weights estimate.
    Before the fix: 1.62 vs 0.97 (alpha 0.5, front, t=30), 1.34 vs 0.75 (alpha 0.5
    from inside, t=43), 1.63 vs 0.90 (alpha 0.3 near normal incidence from inside, as
    in the globe below, t=17), 1.13 vs 0.82 (alpha 0.3, cos 0.7 from inside, t=65)."""
    n = 1 << 18
    scene, si = _interface_hits(alpha, cos_i, side, n)
    bsdf = si.bsdf()
    settings = Settings(rr_depth=1000)
    ctx = SimpleNamespace(weights=Weights("power", StrategySet(settings, True)), settings=settings,
                          moments=None, media=SimpleNamespace(present=False))
    state = PathState.start(dr.zeros(mi.Ray3f, n), dr.ones(mi.Spectrum, n), 0.0, 0.0,
                            dr.zeros(mi.Interaction3f, n), True)
    _scatter(ctx, state, Vertex(si, bsdf), DepthSamples.draw(_sampler(1, n)),
             dr.full(mi.Bool, True, n), importance=True)
    ours = np.array(state.beta[0])                          # the scatter's weight
    sampler = _sampler(2, n)
    _, w = bsdf.sample(IMPORTANCE, si, sampler.next_1d(), sampler.next_2d())
    ref = np.array(w[0])
    assert np.isfinite(ours).all()
    se = math.sqrt(ours.var() / n + ref.var() / n)
    t = abs(ours.mean() - ref.mean()) / se
    # iid lanes, 2^18 per side: a 5-sigma bound false-alarms with probability 6e-7.
    assert t < 5, ("alpha %g, cos %g, side %d: light walk transports %.4f, the BSDF %.4f "
                   "(se %.2g, t=%.1f)" % (alpha, cos_i, side, ours.mean(), ref.mean(), se, t))


@pytest.fixture(scope="module")
def lamp():
    return mi.load_file(LAMP)


def test_light_tracing_through_rough_glass_matches_ptracer(lamp):
    """strategy_subset="lt" (all t = 1 strategies, weight 1) vs Mitsuba's ptracer at
    max_depth 3.  Before the fix: 0.875 vs 0.749 (+17%, t=17.6 on the image mean over
    these 8 seeds)."""
    ours = [bdpt_drjit.render(lamp, spp=512, seed=s, max_depth=3, strategy_subset="lt").image
            for s in range(SEEDS)]
    ref = [mitsuba_render(lamp, "ptracer", 512, seed=100 + s, max_depth=3) for s in range(SEEDS)]
    assert_statistically_equal(ours, ref, blocks=2, what="rough-glass lamp, lt vs ptracer")


def test_single_light_technique_matches_camera_technique(lamp):
    """(3,1) and (1,3) unweighted estimate the same paths of length 3 (light -> globe ->
    floor or globe -> camera); (1,3) is next-event estimation on the camera side, with
    Mitsuba's radiance-mode sample weights.  Before the fix (3,1) was 1.92x (1,3)
    (0.289 vs 0.151, t=25 on the image mean over these 8 seeds)."""
    ours = [bdpt_drjit.render(lamp, spp=512, seed=s, max_depth=3, technique=(3, 1)).image
            for s in range(SEEDS)]
    ref = [bdpt_drjit.render(lamp, spp=512, seed=200 + s, max_depth=3, technique=(1, 3)).image
           for s in range(SEEDS)]
    assert_statistically_equal(ours, ref, blocks=2, what="rough-glass lamp, (3,1) vs (1,3)")
