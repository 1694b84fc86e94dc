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
