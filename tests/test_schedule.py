"""The walks' schedule is not the estimator: a render whose walks run as symbolic
loops (one kernel per walk, the default) equals, sample for sample, the same render
with Dr.Jit's evaluated loops (one kernel per depth, a wavefront), and both trace the
same rays.  This catches loop state that a symbolic loop would not carry over from
one depth to the next."""
import drjit as dr
import numpy as np
import pytest

import bdpt_drjit


@pytest.mark.parametrize("settings", [dict(max_depth=8), dict(max_depth=-1),
                                      dict(max_depth=-1, mis="lafortune"),
                                      dict(max_depth=7, technique=(3, 5), rr_depth=1)])
def test_evaluated_loops_give_the_same_samples(box, settings):
    symbolic = bdpt_drjit.render(box, spp=8, seed=11, **settings)
    with dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False):
        evaluated = bdpt_drjit.render(box, spp=8, seed=11, **settings)
    assert symbolic.rays == evaluated.rays
    assert np.all(np.isfinite(symbolic.image))
    scale = max(float(np.abs(symbolic.image).max()), 1e-6)
    assert np.abs(symbolic.image - evaluated.image).max() <= 1e-5 * scale


def test_a_light_pool_overflows_once_per_render(monkeypatch):
    """A pool that overflows makes the light walk run again with larger pools, and the
    passes after it keep them whatever their number of light subpaths (kept per number,
    every new one overflowed again: Veach's room ran a light walk twice per render).
    A closed box of albedo 0.9 stores more light vertices per subpath than the pools
    start with; passes of 3 and 2 spp have two numbers of light subpaths."""
    import sys

    import mitsuba as mi
    from conftest import SCENES
    store = sys.modules["bdpt_drjit.vertices"].LightVertexStore
    checked, overflowed = [], store.overflowed
    monkeypatch.setattr(store, "overflowed", lambda self: checked.append(overflowed(self)) or checked[-1])
    scene = mi.load_file(str(SCENES / "stress" / "closed-box.xml"), max_depth="16")
    res = bdpt_drjit.render(scene, spp=5, samples_per_pass=3, seed=2, max_depth=16)
    assert res.passes == 2 and checked.count(True) == 1, checked


def test_a_pass_whose_pools_overflow_renders_what_room_would(monkeypatch):
    """A pass whose light walk outgrew its pools runs that walk again with larger ones,
    and gives the image of a render whose pools had room from the start (the same
    light subpaths, all of their vertices connected)."""
    import sys

    import mitsuba as mi
    from conftest import SCENES
    render = sys.modules["bdpt_drjit.render"]
    scene = mi.load_file(str(SCENES / "stress" / "closed-box.xml"), resx=16, resy=16)
    settings = dict(spp=4, seed=3, max_depth=12, rr_depth=100, light_paths=1,
                    connections="all")

    def run(r):
        while not r.done:
            r.run_pass()
        return r.result()
    overflowing = render.Renderer(scene, **settings)
    grown = run(overflowing)
    assert overflowing._capacity[0] > render._VERTICES_PER_LANE
    monkeypatch.setattr(render, "_VERTICES_PER_LANE", 4 * overflowing._capacity[0])
    roomy = run(render.Renderer(scene, **settings))
    assert grown.rays == roomy.rays
    np.testing.assert_allclose(grown.image, roomy.image, rtol=1e-5, atol=1e-6)


def _pass_peaks(renderer) -> list:
    """Each pass's peak memory (bytes) above what was held when it began."""
    from benchmarks.memory import pass_peaks
    return [peak for _, peak in pass_peaks(renderer)]


def test_passes_hold_to_the_memory_budget():
    """Each pass of Veach's BDPT holds no more than ``memory_budget``, also where light
    subpaths store more vertices than the pools start with: the pass that finds out
    frees its first pools before it allocates larger ones (it holds those), and the
    passes after it are sized for them.  In a closed box of albedo 0.9 (about 9 stored
    vertices per subpath) the passes after the first held 1.8x the budget."""
    import sys

    import mitsuba as mi
    from conftest import SCENES
    render = sys.modules["bdpt_drjit.render"]
    scene = mi.load_file(str(SCENES / "stress" / "closed-box.xml"), resx=64, resy=64)
    budget = 16 << 20
    r = render.Renderer(scene, spp=16, seed=2, max_depth=12, rr_depth=100, light_paths=1,
                        connections="all", memory_budget=budget)
    planned = r._lanes_for(r.budget)
    peaks = _pass_peaks(r)
    assert r._capacity[0] > render._VERTICES_PER_LANE       # the pools grew
    # The first pass holds its larger pools (on the lanes planned with the smaller).
    grown = budget * planned / r._lanes_for(r.budget)
    assert peaks[0] <= grown and max(peaks[1:]) <= budget, \
        ["%.1f MiB" % (p / 2 ** 20) for p in peaks + [grown]]


def test_passes_are_sized_for_the_budget_chosen():
    """A budget with more light subpaths per camera sample runs in smaller passes (and
    holds to the memory budget); one with fewer in passes as large as Veach's BDPT's,
    not larger (on the CPU a larger pass is slower: ``_lanes_for``).  light_paths=4
    held 3x the plan's memory when every budget was planned as one light subpath per
    lane."""
    import sys

    import mitsuba as mi
    from conftest import SCENES
    render = sys.modules["bdpt_drjit.render"]
    scene = mi.load_file(str(SCENES / "cornell-box.xml"), resx=64, resy=64)

    def lanes(**budget):
        r = render.Renderer(scene, spp=64, seed=2, memory_budget=32 << 20, **budget)
        return max(n * spp for _, n, spp in r.plan), r
    veach, _ = lanes(light_paths=1, connections="all")
    quarter, _ = lanes(light_paths=0.25, connections=0)
    four, r = lanes(light_paths=4, connections=0)
    assert four < veach == quarter
    assert max(_pass_peaks(r)) <= 32 << 20
