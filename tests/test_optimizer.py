"""Efficiency-aware budgets (optimizer.py): the decision, and the images it leads to.

The decision rests on measured kernel times, so these tests check choices with wide
margins (the decision the optimizer logs, never a timing), and images statistically
(every budget is unbiased, so any choice must agree with the reference)."""
import sys

import numpy as np
import pytest

import mitsuba as mi
import bdpt_drjit
from bdpt_drjit.budgets import Budget
from bdpt_drjit.optimizer import Costs, candidates, decide
from conftest import external, mitsuba_render, scene_path
from stats import assert_statistically_equal

pytestmark = pytest.mark.auto_budget


def test_decide_trades_cost_against_second_moments():
    cands = [Budget(0.0, 0), Budget(1.0, "all")]
    costs = Costs(path_per_sample=1.0, light_per_path=1.0, connect_per_sample=2.0)
    # BDPT costs 4x path tracing: it wins only with less than a quarter of the moment.
    assert decide(cands, np.array([1.0, 0.3]), costs).budget == cands[0]
    assert decide(cands, np.array([1.0, 0.2]), costs).budget == cands[1]
    # A path only light subpaths sample makes path tracing's moment huge (optimizer.py).
    assert decide(cands, np.array([1e9, 1.0]), costs).budget == cands[1]


def test_candidates_respect_spectral_variants():
    assert {b.light_ratio for b in candidates(True)} == {0.0, 1.0}
    assert {b.light_ratio for b in candidates(False)} == {0.0, 0.25, 0.5, 1.0, 2.0}


def _decision(scene, spp=32, **settings):
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=spp, seed=1, **settings)
    while not r.done:
        r.run_pass()
    return r.pilot.decision.budget, r.result()


def test_path_tracing_behind_a_glass_pane():
    """The light image cannot reach the camera through glass: light subpaths only cost."""
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=48, resy=48)
    budget, res = _decision(scene, max_depth=8)
    assert budget.light_ratio == 0, budget
    assert res.stats["budget"] == str(budget)


def test_light_subpaths_for_a_point_caustic():
    """Path tracing cannot render a point-light caustic: its moment is infinite."""
    scene = mi.load_file(scene_path("point-caustic.xml"), resx=48, resy=48)
    budget, _ = _decision(scene, max_depth=8)
    assert budget.light_ratio > 0, budget


def test_connections_in_veach_bidirectional_room():
    path = external("veach-bidir", "scene.xml")
    from benchmarks.scenes import SCENES
    spec = SCENES["veach-bidir"]
    w, h, _ = spec.resolution(64)
    budget, _ = _decision(spec.load(w, h), spp=64, max_depth=spec.max_depth)
    assert budget.connects and budget.light_ratio > 0, budget
    assert path.exists()


@pytest.mark.slow
def test_auto_budgets_agree_with_path(box):
    ours = [bdpt_drjit.render(box, spp=32, seed=s, max_depth=5).image for s in range(8)]
    ref = [mitsuba_render(box, "path", 128, seed=300 + s, max_depth=5) for s in range(8)]
    assert_statistically_equal(ours, ref, what="auto budgets")
