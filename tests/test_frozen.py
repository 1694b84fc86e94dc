"""Frozen walks (frozen.py): a pass whose walks replay a recording gives the image and
the decision the traced walks give for the same seed, a new seed records nothing, and
a change the tracing sees (another scene, another max_depth, a new pool capacity)
records anew instead of replaying kernels made for something else."""
import numpy as np
import pytest

import bdpt_drjit
import mitsuba as mi
from bdpt_drjit import frozen
from conftest import scene_path

# The film's float atomics add a pass's footprints in thread order (test_determinism).
TOL = dict(rtol=1e-5, atol=1e-6)

# The default budget (conftest.fixed_budget): its pilot pass and the passes it chooses
# are what these tests replay.
pytestmark = pytest.mark.auto_budget


@pytest.fixture
def freezing():
    old = frozen.ENABLED
    yield
    frozen.ENABLED = old


def _render(scene, on: bool, **kw):
    frozen.ENABLED = on
    out = bdpt_drjit.render(scene, **{"spp": 32, "max_depth": 8, **kw})
    return out.image, out.stats["budget"]


@pytest.mark.parametrize("name", ["glass-pane.xml", "cornell-box.xml"])
def test_replayed_pilot_gives_the_traced_image(freezing, name):
    """The pilot pass's walks (and, in the Cornell box, the chosen budget's passes)
    recorded, then replayed with new seeds: each image and decision is the traced
    one's."""
    scene = mi.load_file(scene_path(name), resx=24, resy=24)
    _render(scene, True, seed=100)                      # records
    for seed in (1, 2):
        traced, traced_budget = _render(scene, False, seed=seed)
        replayed, budget = _render(scene, True, seed=seed)
        assert budget == traced_budget
        np.testing.assert_allclose(replayed, traced, **TOL)
        assert traced.mean() > 0


def test_a_path_traced_pass_replays_the_traced_image_and_aovs(freezing):
    """Where the pilot chooses path tracing, each later pass is recorded whole
    (render._recorded_path_pass: its sampler, Mitsuba's path and the film's put, AOVs
    included), and a later render replays it: the image and channels of the traced
    pass."""
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=24, resy=24)
    kw = dict(aovs="al:albedo,dd:depth")
    _render(scene, True, seed=100, **kw)                # records
    traced, budget = _render(scene, False, seed=1, **kw)
    replayed, _ = _render(scene, True, seed=1, **kw)
    assert budget == "light_paths=0 connections=0"
    assert replayed.shape[-1] == 3 + 3 + 1
    np.testing.assert_allclose(replayed, traced, **TOL)


def test_a_new_seed_records_nothing(freezing):
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=24, resy=24)
    _render(scene, True, seed=1)
    _render(scene, True, seed=2)        # a first render may record again (its pools)
    before = frozen._frozen.n_recordings
    for seed in (3, 4):
        _render(scene, True, seed=seed)
    assert frozen._frozen.n_recordings == before


def test_what_the_tracing_sees_records_anew(freezing):
    """Another max_depth (a Python value in the walk's kernel) and another scene of the
    same structure: each renders its own image, not the recording of the other."""
    box = mi.load_file(scene_path("cornell-box.xml"), resx=24, resy=24)
    _render(box, True, seed=1, max_depth=8)
    shallow, _ = _render(box, True, seed=1, max_depth=2)
    np.testing.assert_allclose(shallow, _render(box, False, seed=1, max_depth=2)[0], **TOL)
    light_up = mi.load_file(scene_path("cornell-light-up.xml"), resx=24, resy=24)
    other, _ = _render(light_up, True, seed=1)
    np.testing.assert_allclose(other, _render(light_up, False, seed=1)[0], **TOL)


def test_keys_name_python_values_and_widths():
    """The key holds what tracing bakes into a kernel, the state every array."""
    class Holder:
        pass
    a, b = Holder(), Holder()
    a.n, a.x = 3, mi.Float([1.0, 2.0])
    b.n, b.x = 4, mi.Float([5.0, 6.0])
    keys, states = [], []
    for h in (a, b, a):
        key, state = [], []
        frozen._inputs(h, key, state, {})
        keys.append(tuple(key))
        states.append(state)
    assert keys[0] != keys[1] and keys[0] == keys[2]
    assert states[0][0] is a.x and len(states[0]) == 1


def test_swapped_values_record_anew(freezing):
    """Technique (3, 2) after (2, 3): keys with two values swapped.  Passed to
    ``dr.freeze`` as a tuple they matched, and (3, 2) replayed (2, 3)'s light walk,
    which stores no vertex for s = 3: a black image (frozen._digest)."""
    box = mi.load_file(scene_path("cornell-box.xml"), resx=16, resy=16)
    for technique in ((2, 3), (3, 2)):
        replayed, _ = _render(box, True, seed=1, max_depth=4, technique=technique)
        traced, _ = _render(box, False, seed=1, max_depth=4, technique=technique)
        assert traced.mean() > 0
        np.testing.assert_allclose(replayed, traced, **TOL)


def test_a_changed_scalar_parameter_records_anew(freezing):
    """A dielectric's eta is a Python float that Mitsuba bakes into the walks' kernels:
    changed between renders (mi.traverse), the pass records anew (support.SceneFacts.values)
    instead of replaying the kernels of the old eta."""
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=16, resy=16)
    _render(scene, True, seed=1, light_paths=1, connections="all")
    params = mi.traverse(scene)
    params["pane.bsdf.eta"] = 2.4
    params.update()
    replayed, _ = _render(scene, True, seed=1, light_paths=1, connections="all")
    traced, _ = _render(scene, False, seed=1, light_paths=1, connections="all")
    np.testing.assert_allclose(replayed, traced, **TOL)


def test_a_walk_that_cannot_be_recorded_is_traced(freezing):
    """Mitsuba's various-emitters scene (textured area lights, a textured spot, a
    projector): Dr.Jit 1.5 cannot record its light walk (a virtual call whose
    instances it does not find).  The pass runs again traced (frozen.RecordingFailed),
    and later passes trace that walk: the image is the traced one.  Failed before:
    the recording's RuntimeError ended the render."""
    from bdpt_drjit import support
    from conftest import external
    path = external("mitsuba-tests", "tests", "scenes", "various_emitters",
                    "test_various_emitters_ptracer.xml")
    scene = support.load_file(path, integrator="path", resx=16, resy=16)
    replayed, _ = _render(scene, True, seed=1, max_depth=4)
    assert frozen._calls.failed
    traced, _ = _render(scene, False, seed=1, max_depth=4)
    np.testing.assert_allclose(replayed, traced, **TOL)
    assert traced.mean() > 0


def test_a_textured_scene_is_traced_under_cuda():
    """Under CUDA a scene that holds texture data (here an environment map's bitmap)
    is traced, not recorded: Dr.Jit 1.5 aborted the process recording its camera walk
    on an H100 (tests/test_environment.py), the texture object being outside what the
    frozen function traverses.  The Cornell box (no texture) is recorded, and the
    CPU's backend records both."""
    sky, box = (mi.load_file(scene_path(name), resx=16, resy=16)
                for name in ("envmap-open.xml", "cornell-box.xml"))
    assert frozen._reads_cuda_textures("cuda", [box, sky])
    assert not frozen._reads_cuda_textures("cuda", [box])
    assert not frozen._reads_cuda_textures("llvm", [sky])


def test_deferred_connections_are_the_walks_own(freezing, monkeypatch):
    """With connect.DEFERRED, a render pass connects after its camera walk
    (connect.link_pool, run_links): the same image and strategy images as connecting
    in the walk, to the rounding of the sums' order, traced or recorded and replayed,
    so with vcm's merge queries deferred as well, and where the pool overflowed and
    the walk ran again with a larger one (Renderer._camera_subpaths); a vertex cache,
    media, a moment pass or a pool past the memory budget connects in the walk, and
    every pass does where DEFERRED is off."""
    from types import SimpleNamespace
    from bdpt_drjit import connect
    from bdpt_drjit.budgets import Budget
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=24, resy=24)
    kw = dict(spp=8, seed=7, max_depth=5, samples_per_pass=2, light_paths=1,
              connections="all", strategy_images=True)
    pools, link_pool = [], connect.link_pool

    def recorded(*args):
        pools.append(link_pool(*args))
        return pools[-1]

    monkeypatch.setattr(connect, "link_pool", recorded)
    inline = bdpt_drjit.render(scene, **kw)
    assert pools and all(p is None for p in pools)
    monkeypatch.setattr(connect, "DEFERRED", True)
    for per_lane in (connect.LINKS_PER_LANE, 0.05):   # 0.05: every pass's first overflows
        monkeypatch.setattr(connect, "LINKS_PER_LANE", per_lane)
        pools.clear()
        deferred = bdpt_drjit.render(scene, **kw)
        assert all(p is not None and 0 < p.size() <= p.capacity for p in pools[-4:])
        assert (len(pools) > 4) == (per_lane < 1), len(pools)
        np.testing.assert_allclose(deferred.image, inline.image, **TOL)
        assert deferred.strategy_images.keys() == inline.strategy_images.keys()
        for key, layer in inline.strategy_images.items():
            np.testing.assert_allclose(deferred.strategy_images[key], layer, **TOL)
    monkeypatch.setattr(connect, "LINKS_PER_LANE", 0.05)
    del kw["strategy_images"]                   # the walks recorded, then replayed
    for seed in (7, 8):
        monkeypatch.setattr(connect, "DEFERRED", False)
        frozen_inline = bdpt_drjit.render(scene, **{**kw, "seed": seed})
        monkeypatch.setattr(connect, "DEFERRED", True)
        frozen_deferred = bdpt_drjit.render(scene, **{**kw, "seed": seed})
        np.testing.assert_allclose(frozen_deferred.image, frozen_inline.image, **TOL)
    # With vcm's merge queries deferred too (merge.DEFERRED): both kernels after the walk.
    from bdpt_drjit import merge
    vcm = dict(kw, merging=True, radius=0.05)
    monkeypatch.setattr(connect, "DEFERRED", False)
    walk = bdpt_drjit.render(scene, **vcm)
    monkeypatch.setattr(connect, "DEFERRED", True)
    monkeypatch.setattr(merge, "DEFERRED", True)
    np.testing.assert_allclose(bdpt_drjit.render(scene, **vcm).image, walk.image, **TOL)
    strategies = SimpleNamespace(max_depth=5, max_camera_vertices=lambda: 5)
    veach, cache = Budget(1.0, "all"), Budget(1.0, 2)
    assert link_pool(strategies, veach, 1024, False, False, 1 << 30, 2.5).capacity == 2560
    assert link_pool(strategies, veach, 1024, False, False, 1 << 30, 9.0).capacity == 4096
    assert link_pool(SimpleNamespace(max_depth=-1, max_camera_vertices=lambda: None),
                     veach, 1024, False, False, 1 << 30, 9.0).capacity == 9216
    assert link_pool(strategies, veach, 1024, True, False, 1 << 30, 3.0) is None   # moments
    assert link_pool(strategies, veach, 1024, False, True, 1 << 30, 3.0) is None   # media
    assert link_pool(strategies, cache, 1024, False, False, 1 << 30, 3.0) is None  # a cache
    assert link_pool(strategies, veach, 1024, False, False, 1 << 18, 3.0) is None  # too large
