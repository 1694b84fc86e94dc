"""Compaction of sparse work is a schedule, not an estimator: it changes no sample."""
import numpy as np
import pytest

import bdpt_drjit


@pytest.mark.parametrize("settings", [dict(max_depth=8), dict(max_depth=-1),
                                      dict(max_depth=-1, mis="lafortune"),
                                      dict(max_depth=7, technique=(3, 5), rr_depth=1)])
def test_compaction_changes_no_sample(box, settings, monkeypatch):
    """Compacting the camera wavefront and gathering sparse light vertices into items
    (compact.COMPACT_BELOW) is a schedule, not an estimator: with the same seed it gives
    the same image (to float rounding) and traces the same rays as masked full-width
    kernels."""
    import bdpt_drjit.compact as compact
    import bdpt_drjit.walk as walk
    gathers = []
    real_gather = walk.gather_vertex
    counting = lambda *a: gathers.append(1) or real_gather(*a)        # noqa: E731
    monkeypatch.setattr(walk, "gather_vertex", counting)
    monkeypatch.setattr(compact, "gather_vertex", counting)
    monkeypatch.setattr(compact, "MIN_LANES", 0)                    # this box has 2048 lanes
    out = {}
    for below in (0.0, 0.25):
        monkeypatch.setattr(compact, "COMPACT_BELOW", below)
        out[below] = bdpt_drjit.render(box, spp=8, seed=11, **settings)
        assert bool(gathers) == (below > 0)                 # it did compact
    a, b = out[0.0], out[0.25]
    assert a.rays == b.rays
    assert np.all(np.isfinite(b.image))
    scale = max(float(np.abs(a.image).max()), 1e-6)
    assert np.abs(a.image - b.image).max() <= 1e-5 * scale
