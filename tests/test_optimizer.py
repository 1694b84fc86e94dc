"""Efficiency-aware budgets (optimizer.py): the decision, and the images it leads to.

The decision rests on the pilot's counts priced by unit costs (the tests' fixed ones,
tests/calibration.json), so it is deterministic for a seed; still these tests check
choices with wide margins (another machine's units may move close calls), and images
statistically (every budget is unbiased, so any choice must agree with the reference)."""
import sys
import time

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
import bdpt_drjit
from bdpt_drjit import optimizer
from bdpt_drjit.budgets import Budget
from bdpt_drjit.units import UnitCosts
from bdpt_drjit.optimizer import (DARK, Costs, MomentSample, MomentSamples, Pilot, PilotMeans,
                                  candidates, decide)
from conftest import ROOT, external, mitsuba_render, scene_path
from stats import assert_statistically_equal

pytestmark = pytest.mark.auto_budget


def test_decide_trades_cost_against_second_moments():
    cands = [Budget(0.0, 0), Budget(1.0, "all")]
    costs = Costs(camera_rays=1.0, light_rays=1.0, stored_per_path=0.0, connection_rays=2.0)
    # BDPT costs 4x path tracing: it wins only with less than a quarter of the moment.
    assert decide(cands, np.array([1.0, 0.3]), costs).budget == cands[0]
    assert decide(cands, np.array([1.0, 0.2]), costs).budget == cands[1]
    # A path only light subpaths sample makes path tracing's moment huge (optimizer.py).
    assert decide(cands, np.array([1e9, 1.0]), costs).budget == cands[1]


def test_candidates_respect_spectral_variants():
    assert {b.light_ratio for b in candidates(True)} == {0.0, 1.0}
    assert {b.light_ratio for b in candidates(False)} == {0.0, 0.25, 0.5, 1.0, 2.0, 4.0}
    # 4 light subpaths per camera sample only to light-trace smooth first hits
    assert {b for b in candidates(False) if b.light_ratio == 4} == {Budget(4.0, 0, True)}


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


@pytest.mark.parametrize("hide_emitters", [False, True])
def test_mitsuba_path_renders_what_the_pilot_path_traces(hide_emitters):
    """Where the pilot chooses path tracing, the passes after it run Mitsuba's path on
    the engine's camera rays: the image still agrees with Mitsuba's path (emitters
    hidden or not), and the decision says who rendered it."""
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=16, resy=16)
    res = [bdpt_drjit.render(scene, spp=64, seed=s, max_depth=6, hide_emitters=hide_emitters)
           for s in range(8)]
    assert all(r.stats["budget"] == "light_paths=0 connections=0" for r in res)
    assert res[0].stats["path_tracer_spp"] > 32 and "Mitsuba's path" in res[0].stats["decision"]
    ref = [mitsuba_render(scene, "path", 256, seed=400 + s, max_depth=6, hide_emitters=hide_emitters)
           for s in range(8)]
    assert_statistically_equal([r.image for r in res], ref, what="delegated path tracing")


def test_a_path_traced_pass_is_rendered_when_it_is_counted():
    """Mitsuba's path passes launch their kernel without reading anything back: on the
    LLVM backend it ran asynchronously, so passes were counted (time, spp, progress)
    long before they were rendered, and a 1 s time budget queued thousands of them
    (a CLI render with --time 5 took 29 s).  The render time counts a pass once its
    work is done: after it, nothing is left to wait for, so a sync right after a pass
    returns at once, where it used to wait for the whole pass (a comparison of two
    durations of the same run, not a time limit: the machine's load scales both)."""
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=64, resy=64)
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=10 ** 6, seed=1, max_depth=8,
                                                  samples_per_pass=256)
    r.run_pass()                                    # the pilot
    passes, waits = [], []
    for _ in range(3):
        before = r.time
        r.run_pass()
        start = time.perf_counter()
        dr.sync_thread()
        waits.append(time.perf_counter() - start)
        passes.append(r.time - before)
    assert r.budget.light_ratio == 0, r.budget
    assert r.path_tracer_spp > 0, "the premise: Mitsuba's path renders the passes"
    assert max(waits) < 0.2 * min(passes), (waits, passes)


def test_path_tracing_runs_in_as_few_passes_as_its_lanes_allow():
    """Where the pilot chooses path tracing, the passes after its round are sized for
    Mitsuba's path (backend.path_pass_lanes), not for BDPT's wavefront: a pass's fixed
    cost made the default 13x path's time on a GPU at 1 spp per pass.  The film still
    gets every sample asked for; a fixed budget keeps its plan, sized for the
    engine's own walk."""
    from bdpt_drjit import backend
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=64, resy=64)
    budget = 64 << 20        # BDPT's plan: 9 spp per pass; path's: 256
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=1024, seed=1, max_depth=6,
                                                  memory_budget=budget)
    bdpt_passes = len(r.plan)
    while not r.done:
        r.run_pass()
    assert r.budget.light_ratio == 0, r.budget
    rest = r.plan[r._pilot_round:]
    per_pass = backend.path_pass_lanes(budget) // r.pixels
    assert all(spp <= per_pass for _, _, spp in rest)
    assert len(rest) == -(-sum(spp for _, _, spp in rest) // per_pass) < bdpt_passes // 8
    assert r.spp_done == 1024 and r.path_tracer_spp == sum(spp for _, _, spp in rest)
    fixed = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=1024, seed=1, max_depth=6,
                                                      memory_budget=budget, light_paths=0,
                                                      connections=0)
    own = fixed._lanes_for(fixed.budget) // fixed.pixels
    assert len(fixed.plan) == -(-1024 // own) > len(rest)


def test_media_keep_the_engine_path_tracer():
    """Mitsuba's path ignores media: with a medium the engine's own walk path-traces."""
    scene = mi.load_file(str(ROOT / "scenes" / "media" / "fog-cube.xml"), resx=16, resy=16)
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=32, seed=1)
    assert r.pilot is not None and r._path_tracer is None


def test_light_subpaths_for_a_point_caustic():
    """Path tracing cannot render a point-light caustic: its moment is infinite."""
    scene = mi.load_file(scene_path("point-caustic.xml"), resx=48, resy=48)
    budget, _ = _decision(scene, max_depth=8)
    assert budget.light_ratio > 0, budget


def test_light_tracing_of_smooth_first_hits_for_a_point_caustic():
    """The light image's noise in the caustic's dim spread over the ball's shadow
    dominates the error, and only more light subpaths reduce it; the camera walk past
    z_1 adds nothing there.  The most light subpaths, then, with the light image alone
    at smooth first hits: at 2 per camera sample 1.23x more efficient than with path
    tracing beside it, at 4 another 1.11x (benchmarks/RESULTS.md).  It chose 1 light subpath where dark pixels decided
    (a floor of 1e-4 x mean^2) and where light subpaths were timed in the BDPT
    pilot's walk; and path tracing beside the light image while each sample was
    part of its own pixel's mean (PilotMeans), which made the spread's noise 27x
    too small against the direct light that path tracing helps with."""
    scene = mi.load_file(scene_path("point-caustic.xml"), resx=128, resy=128)
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=64, seed=1, max_depth=8)
    for _ in range(Pilot.PASSES):
        r.run_pass()
    assert r.pilot.decision.budget == Budget(4.0, 0, True), r.pilot.decision.describe()


def test_a_pixel_that_outweighs_all_others_is_left_out():
    """A firefly: one pixel whose pilot moment exceeds every other pixel's together
    weighs nothing in the decision; pixels of ordinary weight all count."""
    n = 64
    samples = MomentSamples(n + 1)
    pixel = list(range(n)) + [7]
    samples.items = MomentSample(pixel=mi.UInt32(pixel), f2=mi.Float([1.0] * n + [1e6]),
                                 u_pt=mi.Float([0.2] * n + [1.0]), u_lt=mi.Float([0.8] * n + [0.0]),
                                 u_vm=mi.Float([0.0] * (n + 1)), f2_pairs=mi.Float([0.0] * (n + 1)), query=mi.Float([0.0] * (n + 1)))
    samples.count = mi.UInt32([1] * (n + 1))
    samples.SLOTS = 1
    means = PilotMeans(mi.Float([1.0] * n), mi.Float([0.0] * n), 0.0)
    rates = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    path_tracing, light_tracing = samples.relative_moments(rates, means)
    # pixel 7 is left out with its firefly; the others' samples count in full
    assert path_tracing == pytest.approx((n - 1) / 0.2)
    assert light_tracing == pytest.approx(n - 1)
    ordinary = MomentSamples(n)
    ordinary.items = MomentSample(pixel=mi.UInt32(list(range(n))), f2=mi.Float([1.0] * n),
                                  u_pt=mi.Float([1.0] * n), u_lt=mi.Float([0.0] * n), u_vm=mi.Float([0.0] * n),
                                  f2_pairs=mi.Float([0.0] * n), query=mi.Float([0.0] * n))
    ordinary.count, ordinary.SLOTS = mi.UInt32([1] * n), 1
    assert ordinary.relative_moments(rates[:1], means)[0] == pytest.approx(n)


def test_a_firefly_does_not_choose_path_tracing_in_veachs_mis_scene():
    """One pixel held 97-100% of the pilot's moment in 5 of 12 pilots (this seed among
    them): every candidate's moment was that sample's, and the cheapest, path tracing,
    won (4x less efficient here than light_paths 0.25 at equal time)."""
    external("veach-mis", "scene.xml")
    from benchmarks.scenes import SCENES
    spec = SCENES["veach-mis"]
    scene = spec.load(*spec.resolution(128)[:2])
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=64, seed=201, max_depth=3)
    for _ in range(Pilot.PASSES):
        r.run_pass()
    assert r.pilot.decision.budget.light_ratio > 0, r.pilot.decision.describe()


def pilot_round(scene, seed):
    """The image of an "auto" render's pilot round alone (luminance)."""
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=256, seed=seed, max_depth=8)
    r.run_pass()
    while not r.at_round_end:
        r.run_pass()
    return r.tensor().numpy()[..., :3]


# A crop window of a film that samples a filter border: the pilot's pixel grid (and
# so the parity of its passes) is the crop plus the border, not the crop.
CROPPED = ('<rfilter type="gaussian"/><boolean name="sample_border" value="true"/>'
           '<integer name="crop_offset_x" value="5"/><integer name="crop_offset_y" value="3"/>'
           '<integer name="crop_width" value="41"/><integer name="crop_height" value="37"/>')


def _path_tracing_pilot(monkeypatch):
    """Make every pilot choose path tracing (its estimates kept), as a pilot that
    missed what path tracing renders poorly would."""
    from bdpt_drjit.budgets import PATH_TRACING
    decide = Pilot.decide

    def forced(self, *args, **kwargs):
        table = decide(self, *args, **kwargs).table
        self.decision = self.first = optimizer.Decision(budget=PATH_TRACING, table=table)
        return self.decision
    monkeypatch.setattr(Pilot, "decide", forced)


@pytest.mark.parametrize("film", ["box", "cropped", "large", "second look"])
def test_the_pilot_round_is_unbiased_on_each_part_of_the_pixels(film, monkeypatch):
    """The pilot pass and each pass that completes its round are complete MIS
    estimators of their pixels: the light image keeps the splats in the pass's own
    pixels (film.py).  (With the first of two pilot passes path-tracing the even
    pixels and both passes' light images covering every pixel at half their rate, a
    point-light caustic, which path tracing cannot render, came out of the pilot at
    half its brightness, 3% of a 16-spp render.)  "large": a film whose pilot pass
    takes every other pixel (Pilot.stride; here by fewer pilot lanes), and a second
    pass the odd ones with the budget chosen; "second look": the same where the pilot
    chose path tracing, the odd pixels rendered as the pilot's
    (Renderer._plan_second_look; path-traced, they miss the caustic)."""
    if film == "second look":
        _path_tracing_pilot(monkeypatch)
        monkeypatch.setattr(sys.modules["bdpt_drjit.render"], "SECOND_LOOK_SHARE", 1.0)
    if film in ("large", "second look"):
        monkeypatch.setitem(optimizer.PILOT_LANES, "llvm", 512)
        monkeypatch.setitem(optimizer.PILOT_LANES, "cuda", 512)
    text = open(scene_path("point-caustic.xml")).read()
    if film == "cropped":
        text = text.replace('<rfilter type="box"/>', CROPPED)
    scene = mi.load_string(text, resx=64, resy=64)
    ours = [pilot_round(scene, seed) for seed in range(8)]
    ref = [mitsuba_render(scene, "ptracer", 64, seed=400 + s, max_depth=8) for s in range(8)]
    f = scene.sensors()[0].film()
    border = f.rfilter().border_size() if f.sample_border() else 0
    (w, h), b = f.crop_size(), border
    y, x = np.mgrid[0:h, 0:w]
    grid = (y + b) * (w + 2 * b) + x + b                     # the pilot's pixel index
    stride = 1 if film in ("box", "cropped") else 2
    for part in range(stride):
        assert_statistically_equal(ours, ref, blocks=2, mask=grid % stride == part,
                                   what="pilot, pixels %d of every %d" % (part, stride))


@pytest.mark.parametrize("name, light", [("glass-pane.xml", False), ("point-caustic.xml", True)])
def test_a_large_film_pilots_on_half_its_pixels(name, light):
    """Past 2 x optimizer.PILOT_LANES pixels the pilot pass takes the even pixels and
    a second pass of the round the odd ones with the budget chosen: the round ends
    after it, not before, and the decision is the one smaller films make
    (test_path_tracing_behind_a_glass_pane, test_light_subpaths_for_a_point_caustic)."""
    res = int(np.ceil(np.sqrt(8 * optimizer._pilot_lanes())))     # 1M pixels on a GPU
    scene = mi.load_file(scene_path(name), resx=res, resy=res)
    # A film of more pixels than a pass's memory holds lanes renders in pixel ranges,
    # without a pilot; the budget covers the pilot round here (the GPU's film).
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=64, seed=1, max_depth=8,
                                                  memory_budget=8 << 30)
    assert [p[0] for p in r.plan[:2]] == [0, 1] and [r._stride[i] for i in range(2)] == [2, 2]
    r.run_pass()
    assert not r.at_round_end
    r.run_pass()
    assert r.at_round_end and r.spp_done == 1
    assert (r.budget.light_ratio > 0) == light, r.pilot.decision.describe()


def test_a_path_tracing_pilot_looks_again_where_the_render_is_long(monkeypatch):
    """Where the pilot chose path tracing on a large film, the pass that completes its
    round renders as the pilot did, BDPT with moments, and decides again with the
    pilot's samples: a point-light caustic, which path tracing cannot render, leaves
    path tracing for light subpaths.  Only where that pass costs at most
    SECOND_LOOK_SHARE of the render, priced by the pilot's counts: a shorter render
    path-traces the odd pixels and commits."""
    _path_tracing_pilot(monkeypatch)
    render_module = sys.modules["bdpt_drjit.render"]
    res = int(np.ceil(np.sqrt(2 * optimizer._pilot_lanes())))
    scene = mi.load_file(scene_path("point-caustic.xml"), resx=res, resy=res)
    long = render_module.Renderer(scene, spp=4096, seed=1, max_depth=8, memory_budget=8 << 30)
    assert long._pilot_round == 2
    long.run_pass()
    assert long.budget.light_ratio == 0 and long._second_look
    long.run_pass()
    assert long.at_round_end and long.budget.light_ratio > 0
    assert long.pilot.rounds == [(1.0, long.budget)]
    assert "; after 1 spp light_paths=" in long.decision_text()
    short = render_module.Renderer(scene, spp=32, seed=1, max_depth=8, memory_budget=8 << 30)
    short.run_pass()
    short.run_pass()
    assert not short._second_look and short.budget.light_ratio == 0
    assert short.pilot.rounds == [] and short.path_tracer_spp == 0.5


def test_a_small_render_pilots_on_a_few_pixels_and_drops_its_samples():
    """Under PILOT_SHARE spp on a film of fewer than 2 x PILOT_LANES pixels, the pilot
    takes one pixel in several, at most 1 / 128 of the render's samples and PILOT_LANES
    / 4 lanes at least (Pilot.stride: 2048 lanes of 4096 pixels on the CPU, all of them
    under CUDA), and its samples leave the image: the round has not ended after it,
    and every sample of the render comes after it.  The decision is the one larger
    films make (test_light_subpaths_for_a_point_caustic)."""
    scene = mi.load_file(scene_path("point-caustic.xml"), resx=64, resy=64)
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=32, seed=1, max_depth=8)
    stride = 1 if mi.variant().startswith("cuda") else 2   # PILOT_LANES / 4: 2^15, 2^11
    assert r.plan[0] == (0, 4096 // stride, 1) and r._stride.get(0, 1) == stride
    assert r.plan[1][1] == 4096 and not r._pilot_kept
    r.run_pass()
    assert r.spp_done == 0 and not r.at_round_end and r.film.camera_samples == 0
    assert not np.any(r.tensor().numpy())
    assert r.pilot.decision.budget == Budget(4.0, 0, True), r.pilot.decision.describe()
    while not r.done:
        r.run_pass()
    assert r.at_round_end and r.spp_done == 32 and r.result().spp == 32
    assert r.film.camera_samples == 32 * 4096
    # Path tracing chosen: the engine's rays are the pilot's, per pilot sample.
    glass = mi.load_file(scene_path("glass-pane.xml"), resx=64, resy=64)
    r = sys.modules["bdpt_drjit.render"].Renderer(glass, spp=32, seed=1, max_depth=8)
    while not r.done:
        r.run_pass()
    assert r.path_tracer_spp == 32 and 1 <= r.result().stats["rays_per_sample"] < 40
    # Where merging is a candidate the pilot takes the whole film (Pilot.stride).
    vcm = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=32, seed=1, max_depth=8,
                                                    merging=True)
    assert vcm.plan[0] == (0, 4096, 1) and vcm._pilot_kept


@pytest.mark.parametrize("pilot_lanes", [None, 1 << 17])
def test_a_small_renders_image_is_unbiased(pilot_lanes, monkeypatch):
    """A render after a pilot whose samples were dropped: the light image is normalized
    by the camera samples after it alone (the point-light caustic, 16 spp).  With a
    GPU's PILOT_LANES the pilot takes every pixel, and drops them too (it kept them,
    and was run in every render: seen on an H100)."""
    from bdpt_drjit import optimizer
    if pilot_lanes:
        monkeypatch.setitem(optimizer.PILOT_LANES, "llvm", pilot_lanes)
    scene = mi.load_file(scene_path("point-caustic.xml"), resx=64, resy=64)
    ours = []
    for seed in range(8):
        r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=16, seed=seed, max_depth=8)
        assert not r._pilot_kept
        while not r.done:
            r.run_pass()
        ours.append(r.tensor().numpy()[..., :3])
    ref = [mitsuba_render(scene, "ptracer", 64, seed=500 + s, max_depth=8) for s in range(8)]
    assert_statistically_equal(ours, ref, blocks=2, what="a small render after its pilot")


def test_a_splat_leaves_its_own_share_out_of_its_pixels_mean():
    """A splat is value / r of a camera sample (N_C / N_L times its value), and where the
    pilot took one pixel in ``stride`` the film keeps it, scaled by ``stride``, in
    those pixels alone.  A pixel whose light is one splat has no mean left without
    it: the squared mean it divides by is the floor (it kept half the pixel's light
    with the camera sample's share, and a quarter more at r = 1 / 2)."""
    h = w = 16
    stride, r, value = 2, 0.5, 3.0
    filled = (np.arange(h * w) % stride == 0).reshape(h, w)
    image = np.zeros((h, w))
    image[5, 6] = value / r * stride                        # the film's pixel, 1 spp
    means = PilotMeans.of(image, 1, filled, stride)
    assert means.light_own.numpy().reshape(h, w)[5, 7] == 0.0  # a pixel not kept
    own = means.light_own * (1.0 / r)
    mean2 = means.squared(mi.UInt32(5 * w + 6), mi.Float(value), own)
    assert mean2.numpy()[0] == pytest.approx(means.floor, rel=1e-3, abs=1e-9)


def test_the_pixels_of_a_half_film_pilot_in_a_cropped_film(monkeypatch):
    """The means of a half-film pilot average the crop pixels its pass sampled: every
    camera ray of the pilot pass that lands in the crop window lands on one, and every
    ray of the pass after it on another.  The sampled grid has a filter border of
    1 pixel around a crop window of even width, so the grid's parity is not the crop
    window's (which it took at first)."""
    monkeypatch.setitem(optimizer.PILOT_LANES, "llvm", 64)
    monkeypatch.setitem(optimizer.PILOT_LANES, "cuda", 64)
    cropped = CROPPED.replace("gaussian", "tent").replace('"41"', '"40"')
    text = open(scene_path("point-caustic.xml")).read().replace('<rfilter type="box"/>', cropped)
    scene = mi.load_string(text, resx=64, resy=64)
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=64, seed=1, max_depth=8)
    assert r._pilot_round == 2
    (w, h) = scene.sensors()[0].film().crop_size()
    filled = np.array(r._pilot_pixels((h, w), 2))
    for index, expect in ((0, True), (1, False)):
        offset, n, spp = r.plan[index]
        rays = r.camera.sample_rays(r._sampler(index, 0, n * spp, spp), offset, n, spp,
                                    r._stride[index])
        pos = np.array(rays.pos)
        inside = (pos[0] >= 5) & (pos[0] < 5 + w) & (pos[1] >= 3) & (pos[1] < 3 + h)
        pixel = np.array(rays.pixel)[inside]
        assert len(pixel) > 100 and np.all(filled[pixel] == expect), index


def test_means_of_a_pilot_on_half_the_pixels():
    """Where the pilot's passes left pixels without samples, its means average the
    pixels that have them: an even image is its own mean, and a lone sample is still
    not its own mean (test_a_sample_is_not_its_own_mean)."""
    filled = (np.arange(17 * 17) % 2 == 0).reshape(17, 17)
    image = np.where(filled, 0.5, 0.0)
    means = PilotMeans.of(image, spp=1, filled=filled)
    assert np.array(means.blurred) == pytest.approx(0.5)
    image = np.zeros((17, 17))
    image[8, 8] = 4.0
    means = PilotMeans.of(image, spp=2, filled=filled)
    index = mi.UInt32([8 * 17 + 8])
    assert np.array(means.squared(index, mi.Float([8.0]))) == pytest.approx([means.floor])


def test_dark_pixels_weigh_as_a_tenth_of_the_mean():
    image = np.full((16, 16), 0.4)
    image[:, :8] = 0.003
    floor = DARK * float(np.mean(image)) ** 2
    squared = PilotMeans.of(image, spp=1).squared(mi.UInt32([0, 15]), mi.Float([0.0, 0.0]))
    assert np.array(squared) == pytest.approx([floor, 0.16])


@pytest.mark.parametrize("pixel", [(8, 8), (0, 0), (16, 3)])
def test_a_sample_is_not_its_own_mean(pixel):
    """Leave one out: a lone sample in a dark region is divided by the floor, not by
    the blurred mean it makes itself (with it, F^2 / mean^2 is smallest exactly for
    the largest F; the point-light caustic's summed moment came out 27x too small).
    Its share of its own blurred pixel is larger at the film's edges."""
    image = np.zeros((17, 17))
    image[pixel] = 4.0                                  # one sample, spp = 2: F = 8
    means = PilotMeans.of(image, spp=2)
    index = mi.UInt32([pixel[0] * 17 + pixel[1]])
    assert np.array(means.squared(index, mi.Float([8.0]))) == pytest.approx([means.floor])
    # any other sample there divides by the blurred mean, here 4 x (its share)
    other = np.array(means.squared(index, mi.Float([0.0])))[0]
    assert other == pytest.approx((4.0 * np.array(means.own)[index[0]] * 2) ** 2)


def test_costs_are_the_pilots_counts_priced_by_unit_costs():
    """Per camera sample: the pilot's camera-walk rays and its connections' rays; per
    light subpath its light rays and its stored vertices; each priced by its unit
    cost (units.UnitCosts), path tracing by Mitsuba's path where that renders it."""
    units = UnitCosts(camera_ray=1.0, light_ray=10.0, stored_vertex=100.0, connection=1000.0,
                      path_ray=0.5)
    pilot = Pilot(False, units=units)
    pilot.record(lanes=2, walk_rays=4, connection_rays=6, light_subpaths=2, light_rays=6,
                 stored=6, first_hit_share=0.5)
    c = pilot.costs
    assert (c.camera_rays, c.light_rays, c.connection_rays, c.stored_per_path) == (2, 3, 3, 3)
    assert c.of(Budget(0.0, 0)) == 2.0
    assert c.of(Budget(1.0, 0)) == 2.0 + 30.0
    assert c.of(Budget(0.5, "all")) == 2.0 + 15.0 + 150.0 + 3000.0
    assert c.of(Budget(1.0, 1)) == 2.0 + 30.0 + 300.0 + 1000.0     # 1 of 3 stored vertices
    assert c.of(Budget(1.0, 0, True)) == 1.0 + 30.0
    c.path_tracer = True
    assert c.of(Budget(0.0, 0)) == 1.0


def test_the_decision_reads_no_clock(box, monkeypatch):
    """The same seed gives the same decision whatever the kernels' timings: the pilot's
    counts are the same with the kernel history's times made random."""
    real = dr.kernel_history
    rng = np.random.default_rng(0)

    def noisy(*args):
        return [dict(e, execution_time=float(rng.uniform(0, 100))) for e in real(*args)]

    runs = []
    for patch in (False, True):
        if patch:
            monkeypatch.setattr(dr, "kernel_history", noisy)
        r = sys.modules["bdpt_drjit.render"].Renderer(box, spp=32, seed=4, max_depth=5)
        for _ in range(Pilot.PASSES):
            r.run_pass()
        runs.append((str(r.budget), r.cost_stats(), r.pilot.decision.describe()))
    assert runs[0] == runs[1]


def test_the_decision_compiles_nothing_and_reruns_no_walk(box):
    """The decision of a second render (new seed, so a new kappa) launches only its own
    small kernels, all from the cache.  It used to read the pilot's slot counts after
    the camera walk had run, which ran the whole walk again (~1700 operations, 23 ms at
    256x256), and to bake kappa into a reduction kernel compiled anew each time.  The
    pilot is not reused (where the film is a small render's, as under CUDA, the second
    render would take the first one's decision)."""
    from bdpt_drjit import optimizer
    seen = []
    original = optimizer.MomentSamples.relative_moments

    def spy(self, *args):
        dr.sync_thread()
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            out = original(self, *args)
            seen.extend(e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT)
        return out

    for seed in (1, 2):
        seen.clear()
        optimizer.MomentSamples.relative_moments = spy
        try:
            r = sys.modules["bdpt_drjit.render"].Renderer(box, spp=32, seed=seed, max_depth=5,
                                                          reuse_pilot=False)
            for _ in range(Pilot.PASSES):
                r.run_pass()
        finally:
            optimizer.MomentSamples.relative_moments = original
    assert seen and max(e["operation_count"] for e in seen) < 500
    assert all(e["cache_hit"] for e in seen)


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


def test_a_later_moment_pass_records_every_nth_lane():
    """A moment pass after the pilot records the camera side of every ``every``-th
    lane (its memory stays the pilot's) and counts each recorded sample ``every``
    times; its splats count with the weight they come with."""
    samples = MomentSamples(4, every=2)
    lane = dr.arange(mi.UInt32, 4)
    samples.count = samples.add(mi.UInt32(0), lane, lane, mi.Spectrum(mi.Float([1.0, 5.0, 1.0, 5.0])),
                                mi.Float(1.0), mi.Float(0.0), mi.Float(0.0), mi.Bool(True))
    recorded = samples._camera_side()
    assert sorted(recorded.pixel.numpy().tolist()) == [0, 2]
    means = PilotMeans(mi.Float([1.0] * 4), mi.Float([0.0] * 4), 0.0)
    splats = (MomentSample(pixel=mi.UInt32([1]), f2=mi.Float([4.0]), u_pt=mi.Float([0.0]),
                           u_lt=mi.Float([1.0]), u_vm=mi.Float([0.0]),
                           f2_pairs=mi.Float([0.0]), query=mi.Float([0.0])), mi.Bool([True]), 0.25,
              2.0)      # r
    rates = np.array([[1.0, 0.0, 0.0]])
    # 2 x (1 + 1) from the camera side (lanes 1 and 3, F = 5, unrecorded), 0.25 x 4
    # from the splat
    assert samples.relative_moments(rates, means, splats)[0] == pytest.approx(5.0)


@pytest.mark.parametrize("budget", [Budget(1.0, 0), Budget(0.5, "all"), Budget(1.0, 2),
                                    Budget(0.25, 1), Budget(2.0, 0, True)])
def test_every_budget_estimates_the_pilots_moments(budget):
    """A re-decision's moment pass renders the chosen budget, whose balance weights
    give the candidates' balance sums through its own rates (optimizer.Pilot.redecide):
    its estimate of each candidate's moment per camera sample must be the pilot's
    (which renders Veach's BDPT at unit rates), for every candidate it covers.  With
    the rates left out of the shares, a pass without connections estimated 1.5x the
    pilot's moments; with a vertex cache, whose connections recorded no moments,
    0.72-0.9x.  (Each estimate rests on 32768 camera samples or light subpaths; over
    3-4 seeds the two agreed within 5%; at 128x128 within 10%.)"""
    from bdpt_drjit.optimizer import covers
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=256, resy=256)
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=64, seed=1, max_depth=5)
    for _ in range(r._pilot_round):
        r.run_pass()
    pilot = dict(r.pilot.moments)
    r.budget, r._moment_passes = budget, {r._pilot_round}
    r.plan.insert(r._pilot_round, (0, r.pixels, 16))
    r.run_pass()
    checked = 0
    for c, (total, n) in r.pilot.moments.items():
        if not covers(budget, c):
            assert r.pilot.moments[c] == pilot[c]
            continue
        later = (total - pilot[c][0]) / (n - pilot[c][1])
        assert later == pytest.approx(pilot[c][0] / pilot[c][1], rel=0.1), c
        checked += 1
    assert checked >= 2


def test_re_decisions_after_4_16_and_64_times_the_pilots_samples():
    """The first pass that ends at or after 4, 16 and 64 times the pilot's spp
    records moments and re-decides, and the log says what it chose."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=64, resy=64)
    r = sys.modules["bdpt_drjit.render"].Renderer(scene, spp=300, seed=1, max_depth=5,
                                                  first_hits="light_image", samples_per_pass=4)
    while not r.done:
        r.run_pass()
    assert r.plan[0][2] == 4 and {p[2] for p in r.plan} == {4}
    # the passes end at 4, 8, 12, ..., 300 spp
    assert sorted(r._moment_passes) == [16 // 4 - 1, 64 // 4 - 1, 256 // 4 - 1]
    assert [spp for spp, _ in r.pilot.rounds] == [16, 64, 256]
    text = r.result().stats["decision"]
    assert all("after %d spp light_paths=" % spp in text for spp in (16, 64, 256)), text


def test_the_pilots_buffers_are_touched_outside_its_timed_kernels():
    """The calibration (render.calibrate) times the pilot's walks by their JIT kernels;
    there (``zeroed``: a pass with ``Renderer.timings``) the moment buffer and its
    light pools are filled by memsets first (vertices.LightVertexStore), so that the
    fresh pages' faults are not charged to connections and light subpaths (they made
    connections look 1.5-9x dearer in a process's first render)."""
    from bdpt_drjit.vertices import LightVertexStore
    def kernels(make):
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            made = make()
            dr.sync_thread()
            return made, [(e["type"], e["size"]) for e in dr.kernel_history()]

    lanes = 4096
    llvm = mi.variant().startswith("llvm")     # CUDA's history lists no memsets
    moments, launched = kernels(lambda: MomentSamples(lanes, zeroed=True))
    slots = lanes * MomentSamples.SLOTS
    assert not llvm or (dr.KernelType.Memset, slots * 4) in launched   # 4 bytes a field
    assert all(size < slots for kind, size in launched if kind == dr.KernelType.JIT)
    store, launched = kernels(lambda: LightVertexStore(lanes, 4 * lanes, 5 * lanes, zeroed=True))
    assert dr.KernelType.JIT not in {kind for kind, _ in launched}  # the light lap's own
    assert not llvm or (dr.KernelType.Memset, 4 * lanes * 4) in launched
    assert not np.any(np.array(moments.items.f2)) and not np.any(np.array(store.vertices.items.head))


def test_a_moment_pass_without_splats_of_its_chosen_light_subpaths():
    """A later moment pass records the splats of one light subpath in every * r; where
    the pass's splats all came from other light subpaths, there are no splat samples
    (it crashed on the luminance of an empty array: the default on door-ajar.xml with
    a 0.01 gap, 64x64, 1024 spp)."""
    from types import SimpleNamespace as NS
    from bdpt_drjit.render import _splat_moments
    from bdpt_drjit.vertices import Splat
    n = 3
    items = Splat(pos=dr.zeros(mi.Point2f, n), value=dr.ones(mi.Spectrum, n),
                  s=dr.full(mi.UInt32, 2, n), lane=mi.UInt32([1, 2, 3]),
                  u_pt=dr.zeros(mi.Float, n), u_lt=dr.ones(mi.Float, n), u_vm=dr.zeros(mi.Float, n))
    store = NS(splats=NS(size=lambda: n, capacity=16, items=items))
    ctx = NS(mis_rates=(1.0, 1.0, 0.0), moments=NS(every=4), camera=None)
    assert _splat_moments(ctx, store) is None


def test_the_pilots_per_pixel_means_are_aligned_copies():
    """PilotMeans' per-pixel arrays and the outlier mask are copies at 64-byte alignment
    (backend.device_array): Dr.Jit's CPU backend reads a NumPy array in place, and a
    kernel that loads it is compiled for its address's alignment, so the decision
    compiled a small kernel anew in some renders with a new seed
    (test_kernels.py::test_re_decisions_with_a_new_seed_compile_nothing failed 1 run
    in 3 to 5 on its own)."""
    if not mi.variant().startswith("llvm"):
        pytest.skip("the CPU backend reads NumPy's memory in place")
    image = np.random.default_rng(0).random((64, 64))
    for filled in (None, np.indices((64, 64)).sum(axis=0) % 2 == 0):
        means = optimizer.PilotMeans.of(image, 1, filled, 2 if filled is not None else 1)
        for values in (means.blurred, means.own, means.light_own):
            assert np.from_dlpack(values).ctypes.data % 64 == 0
    moment = mi.Float64(np.random.default_rng(1).random(4096))
    pixel = dr.arange(mi.UInt32, 4096)
    dropped = optimizer.outliers([(moment, None, None, None, pixel, 0.0, None)], 4096)
    assert np.from_dlpack(dropped).ctypes.data % 64 == 0
