"""Technique budgets (budgets.py): every fixed budget is an unbiased estimator.

light_paths is the number of light subpaths per camera sample (0: path tracing),
connections is "all" (Veach's BDPT), a count M drawn from the pass's light vertices,
or 0.  The MIS side is proved by tests/test_mis.py (partition of unity for every
rate); here the images agree with Mitsuba's integrators."""
import numpy as np
import pytest

import mitsuba as mi
import bdpt_drjit
from conftest import mitsuba_render, scene_path
from stats import assert_statistically_equal

SEEDS = 8
BUDGETS = [(1, "all"), (0.25, "all"), (2, "all"), (1, 0), (0.5, 0), (1, 1), (1, 4), (0.5, 2), (0, 0)]


@pytest.fixture(scope="module")
def box_reference(box):
    return [mitsuba_render(box, "path", 128, seed=300 + s, max_depth=5) for s in range(SEEDS)]


@pytest.mark.parametrize("light_paths, connections", BUDGETS)
def test_fixed_budgets_agree_with_path(box, box_reference, light_paths, connections):
    ours = [bdpt_drjit.render(box, spp=32, seed=s, max_depth=5, light_paths=light_paths,
                              connections=connections).image for s in range(SEEDS)]
    assert all(np.isfinite(i).all() for i in ours)
    assert_statistically_equal(ours, box_reference,
                               what="light_paths=%s connections=%s" % (light_paths, connections))


@pytest.mark.slow
@pytest.mark.parametrize("light_paths, connections", [(1, 0), (0.5, "all"), (2, 3)])
def test_budgets_with_light_subpaths_render_a_point_caustic(light_paths, connections):
    """A point-light caustic that path tracing cannot render: every budget with light
    subpaths agrees with Mitsuba's ptracer."""
    scene = mi.load_file(scene_path("point-caustic.xml"), resx=16, resy=16)
    ours = [bdpt_drjit.render(scene, spp=64, seed=s, max_depth=6, light_paths=light_paths,
                              connections=connections).image for s in range(SEEDS)]
    ref = [mitsuba_render(scene, "ptracer", 256, seed=400 + s, max_depth=6) for s in range(SEEDS)]
    assert_statistically_equal(ours, ref, what="caustic, %s %s" % (light_paths, connections))


def test_no_light_subpaths_is_path_tracing(box):
    """light_paths 0 is the strategy subset "pt", sample for sample."""
    a = bdpt_drjit.render(box, spp=8, seed=3, max_depth=5, light_paths=0, connections=0)
    b = bdpt_drjit.render(box, spp=8, seed=3, max_depth=5, strategy_subset="pt")
    np.testing.assert_array_equal(a.image, b.image)


def test_budget_values_are_checked(box):
    for kwargs, word in [(dict(light_paths=-1), "light_paths"), (dict(connections="some"), "connections"),
                         (dict(technique="1,2", light_paths=1), "technique"),
                         (dict(strategy_subset="pt", connections=0), "strategy_subset")]:
        with pytest.raises(ValueError, match=word):
            bdpt_drjit.render(box, spp=1, **kwargs)


@pytest.mark.parametrize("light_paths, connections", [(1, "all"), (1, 2), (0, 0)])
def test_same_seed_same_image(box, light_paths, connections):
    """A vertex cache draws from the stored vertices in a fixed order (pool appends
    land in thread order), so the same seed gives the same samples; what differs is
    the rounding of the light image's splats, added atomically in thread order.  Path
    tracing (no splats) is bit-identical."""
    a, b = (bdpt_drjit.render(box, spp=16, seed=3, max_depth=6, light_paths=light_paths,
                              connections=connections).image for _ in range(2))
    if light_paths == 0:
        np.testing.assert_array_equal(a, b)
    assert np.abs(a - b).max() <= 1e-5 * max(float(np.abs(a).max()), 1e-6)
