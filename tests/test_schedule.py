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
