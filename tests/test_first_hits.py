"""Light tracing of first hits (budgets.Budget.light_first_hits, ``first_hits``):
paths whose first camera vertex z_1 scatters smoothly are the light image's alone,
and the camera walk goes on past z_1 only through delta lobes.

Unlike Mitsuba's ``ptracer`` it is unbiased in any scene, so every image must agree
with a reference whatever the camera sees: a diffuse floor (only the light image
works), glass between camera and scene (only the camera walk works), mirror and
glass spheres (both), a fog (media vertices are smooth)."""
import numpy as np
import pytest

import mitsuba as mi
import bdpt_drjit
from bdpt_drjit.budgets import Budget
from bdpt_drjit.optimizer import Costs, MomentSample, MomentSamples, PilotMeans, candidates
from conftest import ROOT, mitsuba_render, scene_path
from stats import assert_statistically_equal

SEEDS = 8
FIRST = dict(connections=0, first_hits="light_image")

CASES = {
    # the camera sees only the floor: light tracing renders everything
    "point caustic": ("point-caustic.xml", "ptracer", 6, dict(light_paths=2)),
    # every camera ray crosses the glass pane first: the light image renders nothing
    "glass pane": ("glass-pane.xml", "path", 6, dict(light_paths=1)),
    "diffuse box": ("cornell-box.xml", "path", 5, dict(light_paths=2)),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_agrees_with_mitsuba(case):
    name, integrator, depth, budget = CASES[case]
    scene = mi.load_file(scene_path(name), resx=16, resy=16)
    ours = [bdpt_drjit.render(scene, spp=64, seed=s, max_depth=depth, **FIRST, **budget).image
            for s in range(SEEDS)]
    assert all(np.isfinite(i).all() for i in ours)
    ref = [mitsuba_render(scene, integrator, 256, seed=400 + s, max_depth=depth)
           for s in range(SEEDS)]
    assert_statistically_equal(ours, ref, what=case)


def test_agrees_with_every_strategy_where_the_camera_sees_delta_spheres():
    """Mirror and glass spheres seen directly: pixels on them are rendered by camera
    subpaths, the rest by the light image; the same budget with every strategy is
    the reference (both unbiased; a path-traced reference is too noisy here)."""
    scene = mi.load_file(scene_path("cornell-spheres.xml"), resx=16, resy=16)
    a = [bdpt_drjit.render(scene, spp=128, seed=s, max_depth=6, light_paths=1, **FIRST).image
         for s in range(SEEDS)]
    b = [bdpt_drjit.render(scene, spp=128, seed=100 + s, max_depth=6, light_paths=1,
                           connections=0).image for s in range(SEEDS)]
    assert_statistically_equal(a, b, what="spheres")


def test_agrees_with_volpath_in_fog():
    scene = mi.load_file(str(ROOT / "scenes" / "media" / "fog-cube.xml"), resx=16, resy=16)
    ours = [bdpt_drjit.render(scene, spp=64, seed=10 + s, max_depth=8, light_paths=2,
                              **FIRST).image[..., :3] for s in range(SEEDS)]
    ref = [mitsuba_render(scene, "volpath", 1024, 100 + s, max_depth=8)[..., :3]
           for s in range(SEEDS)]
    assert_statistically_equal(ours, ref, what="fog")


def test_settings_that_cannot_light_trace_are_refused(box):
    for kwargs in [dict(light_paths=0), dict(light_image=False), dict(strategy_subset="pt")]:
        with pytest.raises(ValueError, match="first_hits"):
            bdpt_drjit.render(box, spp=1, first_hits="light_image", **kwargs)


def test_moments_of_a_first_hit_candidate():
    """A pilot sample the light image can make (u_lt > 0) costs the candidate
    F^2 / (r u_lt); one it cannot (a delta z_1) costs what the base budget pays."""
    samples = MomentSamples(1)
    samples.items = MomentSample(pixel=mi.UInt32([0, 1]), f2=mi.Float([1.0, 1.0]),
                                 u_pt=mi.Float([0.5, 1.0]), u_lt=mi.Float([0.25, 0.0]),
                                 u_vm=mi.Float([0.0, 0.0]), f2_pairs=mi.Float([0.0, 0.0]), query=mi.Float([0.0, 0.0]))
    samples.count = mi.UInt32([2])
    samples.SLOTS = 2
    rates = np.array([[2.0, 0.0, 0.0], [2.0, 0.0, 1.0]])
    means = PilotMeans(mi.Float([1.0, 1.0]), mi.Float([0.0, 0.0]), 0.0)
    plain, first = samples.relative_moments(rates, means)
    assert plain == pytest.approx(1.0 / (0.5 + 2 * 0.25) + 1.0)
    assert first == pytest.approx(1.0 / (2 * 0.25) + 1.0)


def test_first_hit_candidates_only_with_a_light_image():
    assert any(b.light_first_hits for b in candidates(False, True))
    assert not any(b.light_first_hits for b in candidates(False, False))
    # the camera walk's cost shrinks to the share of its rays that it still traces
    costs = Costs(camera_rays=1.0, light_rays=1.0, first_hit_share=0.25)
    assert costs.of(Budget(2.0, 0, True)) == pytest.approx(0.25 + 2.0)
    assert costs.of(Budget(2.0, 0)) == pytest.approx(1.0 + 2.0)
