"""Vertex connection and merging (merge.py, mis.py's merging terms; issue 30).

Merging is consistent, not unbiased, so it is checked against unbiased renders by the
way its error behaves: exactly right where the photon density is uniform (the
furnace, tests/test_furnace.py), bias that shrinks as passes shrink the radius (the
Cornell box), and the caustic seen in a mirror that no connection renders (the SDS
scene).  The weights' sum to one with merging is in tests/test_mis.py; here the hash
grid against brute force, kernel reuse, the settings merging refuses, the plugin, and
the stress scenes rendered finite.
"""
import gc
from pathlib import Path
from types import SimpleNamespace

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit
from bdpt_drjit import merge
from bdpt_drjit.settings import Settings
from bdpt_drjit.units import UnitCosts
from conftest import ROOT, scene_path
from stats import regions

SDS = str(ROOT / "benchmarks" / "scene_files" / "sds.xml")


# -- the hash grid ------------------------------------------------------------------------
def _points(rng, n):
    """Clustered points around the origin (negative cell coordinates included)."""
    centres = rng.uniform(-1.0, 1.0, (8, 3))
    return centres[rng.integers(0, 8, n)] + rng.normal(0.0, 0.15, (n, 3))


@pytest.mark.parametrize("radius", [0.02, 0.1, 0.4])
def test_grid_finds_each_vertex_within_r_once(radius):
    """Every query returns exactly the stored vertices within r, each once (the count
    and the sum of their indices equal brute force's): no vertex of a colliding bucket
    and none twice where two of the 8 cells share a bucket, medium vertices and the
    pool's unused tail never."""
    rng = np.random.default_rng(int(radius * 1000))
    n, capacity = 3000, 4096
    pts = np.zeros((capacity, 3))
    pts[:n] = _points(rng, n)
    in_medium = np.zeros(capacity, bool)
    in_medium[rng.integers(0, n, 200)] = True
    record = SimpleNamespace(p=mi.Point3f(*[pts[:, i].astype(np.float32) for i in range(3)]),
                             in_medium=mi.Bool(in_medium))
    store = SimpleNamespace(vertices=SimpleNamespace(       # the pool, read in order
        gather=lambda index, active=True: SimpleNamespace(record=record),
        count=mi.UInt32([n]), capacity=capacity))
    grid = merge.HashGrid.build(store, radius, n, photons=False)
    queries = (pts[rng.integers(0, n, 500)] + rng.normal(0.0, radius, (500, 3))).astype(np.float32)
    q = mi.Point3f(*[queries[:, i] for i in range(3)])
    one = lambda item, near: dr.select(near, 1.0, 0.0)                       # noqa: E731
    index = lambda pos, near: dr.select(                                      # noqa: E731
        near, mi.Float(dr.gather(mi.UInt32, grid.order, pos, near)), 0.0)
    count = merge.visit(grid, store, q, mi.Bool(True), one, dr.zeros(mi.Float, 500)).numpy()
    total = merge.visit(grid, store, q, mi.Bool(True), index, dr.zeros(mi.Float, 500)).numpy()
    d2 = ((queries[:, None, :] - pts[None, :n, :].astype(np.float32)) ** 2).sum(-1)
    within = (d2 <= np.float32(radius * radius)) & ~in_medium[None, :n]
    np.testing.assert_array_equal(count, within.sum(1))
    np.testing.assert_allclose(total, (within * np.arange(n)).sum(1), rtol=1e-6)
    assert within.sum() >= 100         # the queries do find vertices


def test_a_querys_cells_lie_in_distinct_buckets():
    """The 8 cells a query visits hash into 8 distinct buckets (merge._bucket), at any
    bucket count the grid uses: a query then visits a bucket once, and tells a
    collision's foreign items by their distance alone (merge.visit has no own-cell
    test: with two of the 8 cells in one bucket it would count its items twice)."""
    rng = np.random.default_rng(5)
    cells = rng.integers(-2000, 2000, (4000, 3)).astype(np.int32)
    cell = mi.Vector3i(*[cells[:, i] for i in range(3)])
    grid = SimpleNamespace(neighbour=merge.HashGrid.neighbour.__get__(object()))
    for buckets in (64, 1 << 14, 1 << 22):
        for signs in ((-1, -1, -1), (1, 1, 1), (1, -1, 1)):
            away = mi.Vector3i(*[np.full(len(cells), s, np.int32) for s in signs])
            b = np.stack([merge._bucket(grid.neighbour(cell, away, k), mi.UInt32(buckets)).numpy()
                          for k in range(8)], 1)
            assert b.max() < buckets
            assert all(len(set(row)) == 8 for row in b)


# -- kernels ------------------------------------------------------------------------------
def test_passes_and_radii_compile_no_kernel():
    """Each pass merges at its own radius, and a new seed or radius compiles nothing:
    radius, cell size, bucket count and normalization are opaque (tests/test_kernels.py's
    count)."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=16, resy=16)

    def launches(**kw):
        dr.kernel_history()
        bdpt_drjit.render(scene, spp=4, samples_per_pass=1, max_depth=4, merging=True, **kw)
        return [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]

    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        launches(seed=1, radius=0.05)
        for kw in (dict(seed=2, radius=0.05), dict(seed=3, radius=0.2, radius_alpha=0.5)):
            again = launches(**kw)
            fresh = [e for e in again if not e.get("cache_hit", 1) or e.get("cache_disk", 0)]
            assert again and not fresh, "%s compiled %d kernels" % (kw, len(fresh))


# -- consistency --------------------------------------------------------------------------
def _block_bias2(images, ref, blocks=4):
    """The squared bias of renders against a reference, summed over blocks: each
    block's squared mean difference less its variance (an unbiased estimate of the
    squared bias, so noise alone sums to about 0)."""
    a = np.stack(images)[..., :3].mean(-1)
    r = np.asarray(ref)[..., :3].mean(-1)
    out = 0.0
    for reg in regions(*r.shape, blocks)[1:]:
        m = a[(slice(None),) + reg].mean(axis=(1, 2))
        out += (m.mean() - r[reg].mean()) ** 2 - m.var(ddof=1) / len(m)
    return out


def test_cornell_box_bias_shrinks_with_passes():
    """VCM's bias against BDPT shrinks as passes shrink the radius: a first radius of
    0.3 (a seventh of the box) and alpha 0.05 (r_i = r_1 i^-0.475), 1, 4 and 16 passes
    of 4 spp.  The squared bias is summed over 16 image blocks, noise subtracted
    (``_block_bias2``).  At a fixed radius it falls with r (measured 4.5e-3, 2.2e-3,
    6.6e-4 and 1.0e-4 at r = 0.3, 0.15, 0.075, 0.03; BDPT itself 8.6e-5: the
    reference's own noise)."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=16, resy=16)
    ref = np.mean([bdpt_drjit.render(scene, spp=512, seed=100 + s, max_depth=4, light_paths=1,
                                     connections="all").image for s in range(4)], axis=0)
    bias = {}
    for passes in (1, 4, 16):
        imgs = [bdpt_drjit.render(scene, spp=4 * passes, seed=s, max_depth=4, merging=True,
                                  radius=0.3, radius_alpha=0.05, samples_per_pass=4).image
                for s in range(6)]
        assert all(np.isfinite(im).all() for im in imgs)
        bias[passes] = _block_bias2(imgs, ref)
    assert bias[1] > 1.3 * bias[4] and bias[4] > 1.3 * bias[16] and bias[16] > 0, bias


# -- the caustic seen in a mirror ---------------------------------------------------------
# benchmarks/scene_files/sds.xml at 32x32: the floor's caustic seen in the mirror
# (light -> glass -> glass -> floor -> mirror -> camera) fills these pixels.
CAUSTIC = (slice(18, 21), slice(13, 19))


@pytest.mark.slow
def test_sds_caustic_in_the_mirror():
    """The mirror caustic, which no connection renders (only a camera path hitting the
    small light can, so BDPT's samples are fireflies there), comes out of merging with
    a small error: its mean in the caustic's pixels matches Mitsuba's path at 4 x
    8192 spp (0.470 +- 0.016; 0.479 at 128x128 and 8192 spp, downsampled), roughly
    (the kernel blurs the caustic: 10%), and with a tenth of BDPT's seed-to-seed
    spread at the same spp (measured 0.027 against 0.26)."""
    scene = mi.load_file(SDS, resx=32, resy=32)
    path = mi.load_dict({"type": "path", "max_depth": 8})
    ref = np.mean([np.array(mi.render(scene, integrator=path, spp=8192, seed=s))[CAUSTIC].mean()
                   for s in range(4)])
    vcm = [bdpt_drjit.render(scene, spp=64, seed=s, max_depth=8, merging=True,
                             radius=0.02).image[CAUSTIC][..., :3].mean() for s in range(6)]
    bdpt = [bdpt_drjit.render(scene, spp=64, seed=s, max_depth=8, light_paths=1,
                              connections="all").image[CAUSTIC][..., :3].mean() for s in range(6)]
    assert abs(np.mean(vcm) / ref - 1) < 0.1, (np.mean(vcm), ref)
    assert np.std(vcm) < 0.25 * np.std(bdpt), (np.std(vcm), np.std(bdpt))


def test_sds_caustic_appears_with_merging_only():
    """Light tracing sees nothing in the mirror and BDPT's connections cannot make the
    path: the caustic's pixels get merging's share of the image (strategy images),
    most of their value."""
    scene = mi.load_file(SDS, resx=32, resy=32)
    r = bdpt_drjit.render(scene, spp=16, seed=1, max_depth=8, merging=True, radius=0.02,
                          strategy_images=True)
    total = r.image[CAUSTIC][..., :3].mean()
    merged = r.merge_image[CAUSTIC][..., :3].mean()
    assert total > 0.3 and merged > 0.8 * total, (total, merged)
    layers = sum(r.strategy_images.values()) + r.merge_image + sum(r.length_images.values(), 0)
    np.testing.assert_allclose(layers, r.image, rtol=1e-4, atol=1e-5)


# -- stability ----------------------------------------------------------------------------
STRESS = sorted(p.name for p in (ROOT / "scenes" / "stress").glob("*.xml"))


@pytest.mark.parametrize("name", STRESS)
def test_stress_scenes_render_finite(name):
    """Every stress scene (scenes/stress) renders finite with merging (16x16, 8 spp in
    2 passes, so two radii)."""
    try:
        scene = mi.load_file(str(ROOT / "scenes" / "stress" / name), resx=16, resy=16)
    except Exception as e:            # noqa: BLE001  (scenes whose parameters differ)
        pytest.skip("%s: %s" % (name, e))
    try:
        img = bdpt_drjit.render(scene, spp=8, seed=3, max_depth=6, merging=True,
                                samples_per_pass=4).image
    except ValueError as e:
        assert "bdpt:" in str(e)      # a refusal names itself (e.g. no emitters)
        return
    finally:
        del scene
        gc.collect()
    assert np.isfinite(img).all()


# -- settings and plugin ------------------------------------------------------------------
@pytest.mark.parametrize("settings, words", [
    (dict(merging=True, mis="lafortune"), ["merging", "lafortune"]),
    (dict(merging=True, technique=(1, 2), max_depth=4), ["technique", "merging"]),
    (dict(merging=True, strategy_subset="pt"), ["pt", "ppm"]),
    (dict(merging=True, light_paths=0), ["light subpaths"]),
    (dict(merging=True, first_hits="light_image"), ["first_hits"]),
    (dict(merging=True, radius_alpha=0.0), ["radius_alpha"]),
    (dict(merging=True, radius=-1), ["radius"]),
    (dict(strategy_subset="ppm", mis="lafortune"), ["lafortune"]),
])
def test_merging_refuses_what_it_cannot_do(settings, words):
    with pytest.raises(ValueError) as e:
        Settings(**settings)
    for w in words:
        assert w in str(e.value)


def test_settings_and_budgets():
    from bdpt_drjit.budgets import fixed_budget
    s = Settings(merging=True)
    assert s.radius == 0.0 and s.radius_alpha == 0.75
    assert fixed_budget(s) is None           # auto: the pilot decides, merging included
    assert str(fixed_budget(Settings(merging=True, light_paths="0.5", connections="2"))) \
        == "light_paths=0.5 connections=2"
    ppm = Settings(strategy_subset="ppm")
    assert ppm.merging and not ppm.light_image
    assert Settings(radius="0.01", merging=True).radius == 0.01
    assert merge.pass_radius(0.1, 0.75, 0) == 0.1
    assert merge.pass_radius(0.1, 0.75, 15) == pytest.approx(0.1 * 16 ** -0.125)


def test_vcm_plugin_is_bdpt_with_merging():
    """``vcm`` renders what bdpt renders with merging=True (the same samples: the same
    image), and its properties include radius and radius_alpha."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=12, resy=12)
    integ = mi.load_dict({"type": "vcm", "max_depth": 4, "radius": 0.05, "radius_alpha": 0.6})
    assert integ.settings["merging"] is True
    img = np.array(mi.render(scene, integrator=integ, spp=4, seed=5))
    res = bdpt_drjit.render(scene, spp=4, seed=5, max_depth=4, merging=True, radius=0.05,
                            radius_alpha=0.6)
    np.testing.assert_allclose(img, res.image, rtol=1e-5, atol=1e-6)
    assert "merging=True" in str(mi.load_dict({"type": "vcm"}))
    assert not mi.load_dict({"type": "bdpt"}).settings.get("merging", False)


def test_deferred_merges_are_the_walks_own(monkeypatch):
    """With merge.DEFERRED, a render pass merges after its camera walk (merge.query_pool,
    run_queries): the same image and merge layer as merging in the walk (merge_at), to
    the rounding of the sums' order, and the passes really deferred, traced or replayed
    (frozen.py); a moment pass, a depth without bound or a pool past the memory
    budget's share merges in the walk, and so does every pass where DEFERRED is off."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=24, resy=24)
    kw = dict(spp=8, seed=7, max_depth=5, samples_per_pass=2, merging=True, light_paths=1,
              connections="all", radius=0.05, strategy_images=True)
    pools = []
    query_pool = merge.query_pool
    monkeypatch.setattr(merge, "DEFERRED", True)

    def recorded(*args):
        pools.append(query_pool(*args))
        return pools[-1]

    monkeypatch.setattr(merge, "query_pool", recorded)
    deferred = bdpt_drjit.render(scene, **kw)
    assert pools and all(p is not None and p.size() > 0 for p in pools)
    monkeypatch.setattr(merge, "query_pool", lambda *args: None)
    inline = bdpt_drjit.render(scene, **kw)
    assert deferred.merge_image.sum() > 0
    np.testing.assert_allclose(deferred.image, inline.image, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(deferred.merge_image, inline.merge_image, rtol=1e-5, atol=1e-6)
    # Without strategy images the walks are recorded and replayed (frozen.py).
    del kw["strategy_images"]
    frozen_inline = bdpt_drjit.render(scene, **kw)
    monkeypatch.setattr(merge, "query_pool", query_pool)
    frozen_deferred = bdpt_drjit.render(scene, **kw)
    np.testing.assert_allclose(frozen_deferred.image, frozen_inline.image, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(frozen_deferred.image, deferred.image, rtol=1e-5, atol=1e-6)
    strategies = SimpleNamespace(max_depth=5, max_camera_vertices=lambda: 5)
    assert query_pool(strategies, 1024, True, 1 << 30) is None          # a moment pass
    assert query_pool(strategies, 1024, False, 1 << 30).capacity == 4 * 1024
    assert query_pool(SimpleNamespace(max_depth=-1, max_camera_vertices=lambda: None),
                      1024, False, 1 << 30) is None
    assert query_pool(strategies, 1024, False, 1 << 20) is None         # too large
    monkeypatch.setattr(merge, "DEFERRED", False)
    assert query_pool(strategies, 1024, False, 1 << 30) is None         # off


# -- efficiency-aware merging: merging as a candidate of the budget decision -------------
def _render_counting_merges(scene, monkeypatch, **kw):
    """A render, and the passes (by index) that built a hash grid and ran merge queries."""
    built, queried = [], []
    build, merge_at = merge.HashGrid.build, merge.merge_at
    import sys
    render_module = sys.modules["bdpt_drjit.render"]
    current = {}
    pass_ = render_module.Renderer._render_pass

    def spy_pass(self, index, *args):
        current["index"] = index
        return pass_(self, index, *args)

    def spy_build(*args, **kwargs):
        built.append(current["index"])
        return build(*args, **kwargs)

    def spy_merge(*args, **kwargs):
        queried.append(current["index"])
        return merge_at(*args, **kwargs)

    monkeypatch.setattr(render_module.Renderer, "_render_pass", spy_pass)
    monkeypatch.setattr(merge.HashGrid, "build", staticmethod(spy_build))
    monkeypatch.setattr(merge, "merge_at", spy_merge)
    res = bdpt_drjit.render(scene, **kw)
    return res, sorted(set(built)), sorted(set(queried))


@pytest.mark.auto_budget
def test_vcm_on_the_diffuse_box_leaves_merging_off_and_pays_for_no_grid(monkeypatch):
    """On the diffuse Cornell box merging buys nothing: ``vcm`` (merging on, budgets
    auto) prices it in the pilot and leaves it off.  Only the pilot pass (0) builds a
    grid and queries it, for the moments alone (its image is BDPT's: the same image as
    bdpt's where the decisions agree), the passes after build none and query nothing, and they are as large as bdpt's (no small passes for a
    radius that does not shrink).  Before, vcm fell back to Veach's budget with
    merging in every pass."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=32, resy=32)
    res, built, queried = _render_counting_merges(scene, monkeypatch, spp=64, seed=3,
                                                  max_depth=8, merging=True)
    assert "merging=off" in res.stats["budget"], res.stats["decision"]
    assert built == [0] and queried == [0], (built, queried)
    assert "merges=" in res.stats["cost_counts"]
    plain = bdpt_drjit.render(scene, spp=64, seed=3, max_depth=8)
    assert res.passes == plain.passes


@pytest.mark.auto_budget
def test_sds_scene_keeps_merging():
    """The caustic seen in the mirror is merging's alone: the pilot keeps merging on."""
    scene = mi.load_file(SDS, resx=32, resy=32)
    for seed in (1, 2):
        res = bdpt_drjit.render(scene, spp=32, seed=seed, max_depth=8, merging=True)
        assert "merging=on" in res.stats["budget"], res.stats["decision"]


@pytest.mark.auto_budget
def test_vcm_decision_is_the_same_for_a_seed(monkeypatch):
    """The merging decision reads no clock: the same seed gives the same budget, counts
    and image with the kernels' timings made random (tests/test_optimizer.py's rule)."""
    scene = mi.load_file(SDS, resx=32, resy=32)
    real = dr.kernel_history
    rng = np.random.default_rng(0)
    runs = []
    for patch in (False, True):
        if patch:
            monkeypatch.setattr(dr, "kernel_history", lambda *a: [
                dict(e, execution_time=float(rng.uniform(0, 100))) for e in real(*a)])
        r = bdpt_drjit.render(scene, spp=32, seed=5, max_depth=8, merging=True)
        runs.append((r.stats["budget"], r.stats["decision"], r.stats["cost_counts"], r.image))
    assert runs[0][:3] == runs[1][:3]
    np.testing.assert_allclose(runs[0][3], runs[1][3], rtol=1e-5, atol=1e-6)


def test_merging_candidates_and_their_cost():
    """Every budget with light subpaths (not light_first_hits) has a merging twin at
    each radius of MERGE_RADII; a merging candidate is covered only by a moment pass
    that merges; its cost adds the grid's build per stored vertex and the query steps,
    QUERY_STEPS per query plus the items, whose count grows with the candidate's eta
    (radius_scale^2 of it at a smaller radius)."""
    from bdpt_drjit.budgets import Budget
    from bdpt_drjit.optimizer import MERGE_RADII, QUERY_STEPS, Costs, candidates, covers
    from bdpt_drjit.units import UnitCosts
    plain = candidates(False)
    both = candidates(False, merging=True)
    twins = sum(b.light_ratio > 0 and not b.light_first_hits for b in plain)
    assert len(both) == len(plain) + twins * len(MERGE_RADII) and len(MERGE_RADII) > 1
    assert sorted({b.radius_scale for b in both if b.merging}) == sorted(MERGE_RADII)
    assert all(b.merging is not None for b in both)
    assert covers(Budget(0.5, 1, merging=True), Budget(0.5, 1, merging=True, radius_scale=0.25))
    on, off = Budget(0.5, "all", merging=True), Budget(0.5, "all", merging=False)
    assert covers(on, off) and covers(on, on) and not covers(off, on)
    units = UnitCosts(camera_ray=1, light_ray=1, stored_vertex=1, connection=1, path_ray=1,
                      grid_vertex=2.0, merge_step=3.0)
    c = Costs(units, camera_rays=4, light_rays=5, stored_per_path=3, connection_rays=6,
              merges=2, merge_items=0.01, merge_eta=100.0)
    assert c.of(on) - c.of(off) == pytest.approx(0.5 * 3 * 2.0 + (QUERY_STEPS * 2 + 0.01 * 0.5 * 100) * 3.0)
    light_only = Budget(0.5, 0, merging=True)      # merging stores vertices without connections
    assert c.of(light_only) - c.of(Budget(0.5, 0, merging=False)) == pytest.approx(
        0.5 * 3 * 1.0 + c.merging(0.5))
    small = Budget(0.5, "all", merging=True, radius_scale=0.5)
    assert c.of(small) - c.of(off) == pytest.approx(
        0.5 * 3 * 2.0 + (QUERY_STEPS * 2 + 0.01 * 0.5 * 100 * 0.25) * 3.0)
    assert "radius=0.5r" in str(small) and "radius" not in str(on)


def test_a_smaller_radius_is_a_smaller_rate_and_the_passes_merge_at_it(monkeypatch):
    """A merging candidate at radius_scale s merges at s r_i in the passes it renders,
    and its rate over the moment pass's (the v of P_c / P) is s^2 that of scale 1."""
    from dataclasses import replace
    from bdpt_drjit.budgets import Budget
    from bdpt_drjit.optimizer import Pilot
    from bdpt_drjit.render import Renderer
    pilot = Pilot(False, merging=True)
    pilot.costs.merge_eta = 100.0
    full, half = Budget(0.5, 1, merging=True), Budget(0.5, 1, merging=True, radius_scale=0.5)
    assert pilot._merge_rate(full, 10.0) == pytest.approx(5.0)
    assert pilot._merge_rate(half, 10.0) == pytest.approx(1.25)
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=16, resy=16)
    r = Renderer(scene, spp=4, seed=1, max_depth=4, merging=True, light_paths=1,
                 connections=1, unit_costs=UnitCosts())
    r.budget = replace(r.budget, merging=True, radius_scale=0.5)
    radii = []
    build = merge.HashGrid.build
    monkeypatch.setattr(merge.HashGrid, "build", staticmethod(
        lambda store, radius, *a, **k: radii.append(radius) or build(store, radius, *a, **k)))
    r.render_pass(0)
    assert radii == [pytest.approx(0.5 * merge.pass_radius(r.merge_radius, 0.75, 0))]


def test_merge_pairs_scale_with_the_merging_rate_squared():
    """A merge query's sample: its photons' squares count as independent samples (F^2 /
    share, as every other), the rest of its square, the pairs, as (v / share)^2: more
    photons (rate v) do not average away the camera path's own variance.  A candidate
    without merging reads the other samples alone, as BDPT's pilot would have them
    (F / (1 - u_vm), shares over 1 - u_vm)."""
    from bdpt_drjit.optimizer import MomentSample, MomentSamples, PilotMeans
    n = 3                                   # a query and another sample in each of 3 pixels
    samples = MomentSamples(2 * n)
    samples.items = MomentSample(pixel=mi.UInt32([0, 1, 2] * 2), f2=mi.Float([1.0] * 2 * n),
                                 u_pt=mi.Float([0.2] * n + [0.5] * n), u_lt=mi.Float([0.0] * 2 * n),
                                 u_vm=mi.Float([0.8] * n + [0.5] * n),
                                 f2_pairs=mi.Float([3.0] * n + [0.0] * n),
                                 query=mi.Float([1.0] * n + [0.0] * n))
    samples.count, samples.SLOTS = mi.UInt32([1] * 2 * n), 1
    means = PilotMeans(blurred=mi.Float([2.0] * n), own=mi.Float([0.0] * n), floor=1e-9)
    rates = np.array([[1.0, 1.0, 0.0, 0.0], [1.0, 1.0, 0.0, 1.0], [1.0, 1.0, 0.0, 4.0]])
    off, same, more = samples.relative_moments(rates, means, merging=True) / n
    assert off == pytest.approx(1.0 / 4 / (0.5 * 0.5))
    assert same == pytest.approx((1.0 + 3.0) / 4 + 1.0 / 4)      # the pass itself: F^2
    q, o = 0.2 + 4 * 0.8, 0.5 + 4 * 0.5
    assert more == pytest.approx(1.0 / 4 / q + 3.0 / 4 * (4 / q) ** 2 + 1.0 / 4 / o)


def test_a_path_only_merging_reaches_is_a_bias_not_an_infinite_moment():
    """A merge query of a path that no technique without merging samples (u_vm = 1: a
    point light's caustic seen in a mirror) adds nothing to those candidates' moments
    (before: its share floored at 1e-9, a moment of 1e9 F^2) but their squared
    relative bias B (optimizer.missed_bias): with the same value c in every pixel of a
    9x9 film, one sample each, and the image's mean m, B = c^2 (1 - 1/81) / m^2 (the
    window's (S^2 - Q) / n^2).  A query merging holds 99.99% of is still read from
    its merges (MERGE_ONLY)."""
    from bdpt_drjit.optimizer import MomentSample, MomentSamples, PilotMeans, missed_bias
    n, c, m = 81, 0.3, 2.0
    samples = MomentSamples(n)

    def fill(u_vm):
        samples.items = MomentSample(pixel=mi.UInt32(np.arange(n)), f2=mi.Float([c * c] * n),
                                     u_pt=mi.Float([0.0] * n), u_lt=mi.Float([0.0] * n),
                                     u_vm=mi.Float([u_vm] * n), f2_pairs=mi.Float([0.0] * n),
                                     query=mi.Float([1.0] * n))
    samples.count, samples.SLOTS = mi.UInt32([1] * n), 1
    means = PilotMeans(blurred=mi.Float([m] * n), own=mi.Float([0.0] * n), floor=1e-9)
    rates = np.array([[1.0, 1.0, 0.0, 0.0], [1.0, 1.0, 0.0, 1.0]])
    fill(1.0)
    off, on = samples.relative_moments(rates, means, merging=True) / n
    assert off == 0.0 and on == pytest.approx(c * c / (m * m), rel=1e-4)
    assert missed_bias(samples, means, (9, 9)) == pytest.approx(c * c * (1 - 1 / 81) / m ** 2,
                                                                rel=1e-4)
    fill(0.9999)
    off, on = samples.relative_moments(rates, means, merging=True) / n
    assert off == pytest.approx(c * c / (m * m) / 0.9999 / 1e-4, rel=1e-2)
    assert missed_bias(samples, means, (9, 9)) == 0.0


def test_a_re_decision_without_merging_still_weighs_merging():
    """A moment pass of a budget without merging cannot price merging, but it firms up
    the other candidates' moments: where they turn out far larger than the pilot's,
    the re-decision chooses merging, priced by the moments of the pass that merged
    (the pilot's).  Before, it chose among the candidates without merging alone: on
    SmallVCM's large glass sphere the pilot's few BDPT samples of the caustic seen
    through the glass left merging off in most seeds, for good."""
    from bdpt_drjit.optimizer import MomentSample, MomentSamples, Pilot
    pilot = Pilot(False, merging=True, units=UnitCosts(), spp=64)
    pilot.record(lanes=100, walk_rays=300, connection_rays=100, light_subpaths=100,
                 light_rays=300, stored=200)
    pilot.record_merging(100, merges=100, items=1000, eta=1.0)
    pilot.costs.merge_eta = 1.0
    pilot.moments = {c: (16.0, 16.0) for c in pilot.candidates}    # all alike: 1
    budget = next(c for c in pilot.candidates
                  if not c.merging and c.light_ratio == 0.5 and c.connections == 1)
    n = 16                  # one path-traced sample per pixel of a 4x4 film, F^2 = 100
    samples = MomentSamples(n)
    samples.items = MomentSample(pixel=mi.UInt32(np.arange(n)), f2=mi.Float([100.0] * n),
                                 u_pt=mi.Float([1.0] * n), u_lt=mi.Float([0.0] * n),
                                 u_vm=mi.Float([0.0] * n), f2_pairs=mi.Float([0.0] * n),
                                 query=mi.Float([0.0] * n))
    samples.count, samples.SLOTS = mi.UInt32([1] * n), 1
    kappa = budget.kappa(1, pilot.costs.stored_per_path)
    decision = pilot.redecide(samples, None, np.ones((4, 4)), 1e6, budget, (0.5, kappa, 0.0))
    assert decision.budget.merging, decision.describe()
    assert pilot.moments[decision.budget] == (16.0, 16.0)          # the pilot's alone


@pytest.mark.auto_budget
def test_a_vcm_moment_pass_records_enough_of_what_merging_sees(monkeypatch):
    """A later moment pass of a vcm render whose budget does not merge records about
    MOMENT_PILOTS times the pilot's camera lanes, a bdpt render's or a merging
    budget's one lane in 2 x spp (the pilot's memory).  Before, it recorded those:
    on SmallVCM's large glass sphere a budget without merging renders its passes of
    74 spp after the pilot, re-decides once, and that pass's 8192 samples held 0-3 of
    the caustic seen through the glass; merging stayed off in 3 of 12 seeds."""
    import importlib
    from bdpt_drjit.optimizer import MOMENT_PILOTS, Pilot, _pilot_lanes
    render = importlib.import_module("bdpt_drjit.render")      # (bdpt_drjit.render: the function)
    pixels, spp = 128 * 128, 74
    lanes = pixels * spp
    assert lanes // Pilot.moment_every(lanes, spp) == pixels // 2
    recorded = lanes // Pilot.moment_every(lanes, spp, unmerged_vcm=True)
    assert MOMENT_PILOTS * _pilot_lanes() <= recorded < 2 * MOMENT_PILOTS * _pilot_lanes()

    everies = []        # the passes of a render, as render.py sizes their records

    class Spy(render.MomentSamples):
        def __init__(self, lanes, every=1, *args, **kwargs):
            everies.append((lanes, every))
            super().__init__(lanes, every, *args, **kwargs)

    scene = mi.load_file(scene_path("cornell-box.xml"), resx=16, resy=16)
    monkeypatch.setattr(render, "MomentSamples", Spy)
    r = render.Renderer(scene, spp=128, seed=1, max_depth=4, merging=True, samples_per_pass=4,
                        unit_costs=UnitCosts())
    r.pilot.candidates = [c for c in r.pilot.candidates if c.light_ratio > 0]   # re-decides
    budgets = []
    while not r.done:
        budgets.append(r.budget)
        r.run_pass()
    assert r.pilot.rounds and len(everies) == 1 + len(r.pilot.rounds)
    for (lanes, every), i in zip(everies[1:], sorted(r._moment_passes)):
        _, n, spp = r.plan[i]
        assert lanes == n * spp
        assert every == Pilot.moment_every(lanes, spp, not budgets[i].merges)


def test_merging_is_priced_by_the_passes_a_merging_budget_renders():
    """After a choice without merging the plan's passes are larger (their radius need
    not shrink), but merging's eta, and the grid items its queries visit, are those
    of the small passes a merging budget would render: the same for any plan of the
    same samples.  Before, a re-decision on SmallVCM's large glass sphere priced
    merging's queries at 3x the pilot's cost."""
    from bdpt_drjit.budgets import Budget
    from bdpt_drjit.render import Renderer, plan_passes
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=16, resy=16)
    r = Renderer(scene, spp=256, seed=1, max_depth=4, merging=True, unit_costs=UnitCosts())
    r.budget = Budget(0.5, 1, merging=False)
    etas = []
    for lanes in (16 * 16 * 8, 16 * 16 * 128):
        r.plan = r.plan[:1] + plan_passes(240, r.pixels, lanes, 0, r._accepted_count)
        etas.append(r.merge_eta(0))
    assert etas[0] == pytest.approx(etas[1], rel=1e-6)


@pytest.mark.auto_budget
def test_vcm_leaves_merging_off_where_it_adds_only_a_point_lights_faint_sds_caustic():
    """SmallVCM's point-light box (benchmarks/smallvcm.py, bs_p): merging alone reaches
    the glass sphere's caustic seen in the mirror, a faint part of the image (its
    missing mean: missed_bias), and BDPT renders the rest at a third of merging's cost.
    Before, those few merge samples gave every candidate without merging an infinite
    moment and vcm merged (2.8x the default's time per sample for 0.94x its error)."""
    from benchmarks.smallvcm import build_scene
    scene = build_scene("bs_p", res=32)
    for seed in (1, 3):                                 # seed 3 merged before
        res = bdpt_drjit.render(scene, spp=64, seed=seed, max_depth=10, merging=True)
        assert "merging=off" in res.stats["budget"], res.stats["decision"]
