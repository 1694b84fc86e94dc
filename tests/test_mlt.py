"""PSSMLT over the wavefront BDPT (bdpt_drjit/mlt.py).

* The image agrees with BDPT's: independent MLT runs against independent BDPT
  renders, by Welch's t-test on the whole image and 4 x 4 blocks (stats.py); the
  error of each side is measured across its runs, never within one run (a run's
  chains are correlated).  A block test sees where the chains spend their time, not
  only the bootstrap's normalization.
* The normalization: the image's luminance sum is b N at every iteration (expected
  values add a + (1 - a) = 1 per chain), b the bootstrap's mean, itself an unbiased
  BDPT estimate.
* No kernel is compiled per iteration or per seed.
* Stability: finite images on every stress scene.
* Refusals: what cannot work is refused with a message."""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit
from bdpt_drjit import mlt, mmlt, pss
from conftest import SCENES
from stats import assert_statistically_equal

RUNS = 8


def _box(res=16, filt="box"):
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=res, height=res, rfilter={"type": filt})
    return mi.load_dict(d)


# pssmlt (mlt.py) and multiplexed MLT (mmlt.py, the "mlt" integrator): (render, renderer)
KINDS = {"pssmlt": (mlt.render, mlt.MLTRenderer), "mlt": (mmlt.render, mmlt.MMLTRenderer)}


def _mlt(scene, seed, kind="pssmlt", **kw):
    params = dict(mutations_per_pixel=32, bootstrap_samples=16384, chains=1024, max_depth=5)
    params.update(kw)
    return KINDS[kind][0](scene, seed=seed, **params)


def test_image_matches_bdpt():
    """8 runs of 32 mutations per pixel against 8 BDPT renders of 32 spp."""
    scene = _box()
    runs = [_mlt(scene, seed).image for seed in range(RUNS)]
    refs = [bdpt_drjit.render(scene, spp=32, seed=100 + s, max_depth=5, light_paths=1,
                              connections="all").image for s in range(RUNS)]
    assert_statistically_equal(runs, refs, blocks=4, what="pssmlt vs bdpt")


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("p_large, mis", [(0.0, True), (1.0, True), (0.3, False)])
def test_other_steps_match_bdpt(p_large, mis, kind):
    """Small steps only (the chains move by Kelemen's steps from the bootstrap's
    states), large steps only (an independence sampler), and the default steps
    without Kelemen's MIS of large steps agree too."""
    scene = _box()
    runs = [_mlt(scene, seed, kind, large_step_probability=p_large, large_step_mis=mis).image
            for seed in range(6)]
    refs = [bdpt_drjit.render(scene, spp=32, seed=200 + s, max_depth=5, light_paths=1,
                              connections="all").image for s in range(6)]
    assert_statistically_equal(runs, refs, blocks=4, what="p_large %g, mis %s" % (p_large, mis))


@pytest.mark.parametrize("kind", list(KINDS))
def test_fine_steps_match_bdpt(kind, monkeypatch):
    """The box's chains accept Kelemen's steps often (their pilot keeps them); with
    the finer steps forced (pss.fine_steps at any acceptance) the image agrees too."""
    scene = _box()
    stats = _mlt(scene, 0, kind).stats
    assert stats["pilot_acceptance"] > pss.FINE_BELOW and stats["small_step_s1"] == pss.S1
    monkeypatch.setattr(pss, "FINE_BELOW", 1.01)
    results = [_mlt(scene, seed, kind) for seed in range(6)]
    assert all(r.stats["small_step_s1"] == pss.FINE_S1 for r in results)
    refs = [bdpt_drjit.render(scene, spp=32, seed=400 + s, max_depth=5, light_paths=1,
                              connections="all").image for s in range(6)]
    assert_statistically_equal([r.image for r in results], refs, blocks=4,
                               what="%s, fine steps" % kind)


@pytest.mark.parametrize("kind", list(KINDS))
def test_image_sum_is_b_at_every_iteration(kind):
    """mlt: sum over chains of c_k = sum_k n_k b_k N / n_k = b N (without Kelemen's MIS;
    without the separate direct samples: test_direct_samples; without two-stage, whose
    target is not the luminance: test_mmlt.py)."""
    scene = _box()
    two = {"two_stage": False} if kind == "mlt" else {}
    r = KINDS[kind][1](scene, seed=3, mutations_per_pixel=8, bootstrap_samples=8192,
                       chains=512, max_depth=5, large_step_mis=False, direct_samples=-1, **two)
    assert r.b > 0
    while not r.done:
        r.run_iteration()
        img = r.tensor().numpy()
        assert abs(img.mean() / r.b - 1.0) < 1e-4, (img.mean(), r.b)
    if kind == "pssmlt":
        assert 0.5 < r.result().stats["acceptance"] < 1.0


@pytest.mark.parametrize("kind", list(KINDS))
def test_direct_samples(kind):
    """The separate direct samples (mlt.MLTRenderer._separate_direct): on the box, where
    paths of 1 and 2 edges carry most of the light, the chains' target lacks them (mlt:
    its chains start on longer paths only), the chains' image's sum is (b - b_direct)
    N at every iteration, the direct samples' image is the rest, and the sum of both
    agrees with BDPT (test_other_steps_match_bdpt and the others render with them
    too); -1 turns them off, N > 0 takes N per pixel per iteration; on the door,
    whose direct light is a sliver, the automatic plan takes none."""
    scene = _box()
    renderer = KINDS[kind][1]
    kw = dict(mutations_per_pixel=8, bootstrap_samples=8192, chains=512, max_depth=5,
              large_step_mis=False)
    two = {"two_stage": False} if kind == "mlt" else {}     # the luminance's sums
    r = renderer(scene, seed=3, **kw, **two)
    assert r.direct_lanes == mlt.MIN_DIRECT_LANES and r.b_direct > mlt.DIRECT_SHARE * r.b
    assert abs(r.b_chains / (r.b - r.b_direct) - 1.0) < 1e-4
    if kind == "mlt":
        assert r.chains_per_depth[:mlt.DIRECT_LENGTH].sum() == 0
        assert r.chains_per_depth.sum() == 512
    while not r.done:
        r.run_iteration()
        chains = r.chains_tensor().numpy()
        assert abs(chains.mean() / (r.b - r.b_direct) - 1.0) < 1e-4
        assert r.tensor().numpy().mean() > chains.mean()
    # automatic chains (the effective sample size of the chains' cells sets them): the
    # direct samples stay (mlt's chains started on paths of 3 edges up and no direct
    # samples were taken before: the door's image lacked 6% of its light)
    auto = renderer(scene, seed=3, mutations_per_pixel=64, max_depth=5)
    assert auto.direct_lanes >= mlt.MIN_DIRECT_LANES and auto.b_direct > 0
    if kind == "mlt":
        assert auto.chains_per_depth[:mlt.DIRECT_LENGTH].sum() == 0
    assert renderer(scene, seed=3, direct_samples=-1, **kw).direct_lanes == 0
    assert renderer(scene, seed=3, direct_samples=2, **kw).direct_lanes == 2 * 256
    with pytest.raises(ValueError, match="direct_samples"):
        renderer(scene, direct_samples=-2)
    door = mi.load_file(str(SCENES / "door-ajar.xml"), resx=16, resy=16, gap_start=0.49)
    r = renderer(door, seed=1, **kw)
    assert r.direct_lanes == 0 and r.b_direct < mlt.DIRECT_SHARE * r.b


def test_automatic_plan():
    """Automatic chains: short chains (CHAIN_MUTATIONS mutations each) between 4096 and
    MAX_CHAINS lanes, never more chains than mutations; the bootstrap has
    BOOTSTRAP_PER_CHAIN samples per chain (at least MIN_BOOTSTRAP); given values stay."""
    for mutations in (100, 5000, 4096 * 64, 4096 * 256, 512 * 512 * 64, 1 << 40):
        chains, boot = mlt.automatic_plan(mutations)
        assert chains <= mutations and chains <= mlt.MAX_CHAINS
        assert chains == mutations or chains >= 4096
        if 4096 * mlt.CHAIN_MUTATIONS <= mutations <= mlt.MAX_CHAINS * mlt.CHAIN_MUTATIONS:
            assert chains == mutations // mlt.CHAIN_MUTATIONS
        assert boot == max(mlt.MIN_BOOTSTRAP, mlt.BOOTSTRAP_PER_CHAIN * chains)
    assert mlt.automatic_plan(1 << 40) == (mlt.MAX_CHAINS, 8 * mlt.MAX_CHAINS)
    assert mlt.automatic_plan(10 ** 6, 1000, 5000) == (1000, 5000)
    r = mlt.MLTRenderer(_box(), seed=1, mutations_per_pixel=64, max_depth=5)
    # the box's f is nearly flat: the bootstrap's effective sample size caps nothing
    assert (r.chains, r.bootstrap_samples) == mlt.automatic_plan(64 * 256)
    assert r.iterations == 4


def test_chains_capped_by_the_bootstrap():
    """Automatic chains are at most ESS_CHAINS x the bootstrap's effective sample size
    (sum f)^2 / sum f^2 rounded down to a power of two, and at least MIN_CHAINS (or the
    plan, where smaller)."""
    assert mlt.ESS_CHAINS == 2.0
    flat = np.ones(100000)
    assert mlt.chains_for_bootstrap(262144, flat) == 131072       # 200000 rounded down
    assert mlt.chains_for_bootstrap(100000, flat) == 100000
    assert mlt.chains_for_bootstrap(1000, flat) == 1000
    sparse = np.zeros(100000)
    sparse[:20000] = 3.0                                  # 20000 equal nonzero samples
    assert mlt.chains_for_bootstrap(262144, sparse) == 32768      # 40000 rounded down
    sparse[:1000] = 0.0
    sparse[:10] = 1e4                                     # a heavy tail: ESS ~ 10.4
    assert mlt.chains_for_bootstrap(262144, sparse) == mlt.MIN_CHAINS
    assert mlt.chains_for_bootstrap(262144, np.zeros(10)) == mlt.MIN_CHAINS
    # the door with a narrow gap: few of the bootstrap's samples carry light, so the
    # renderer runs fewer, longer chains than planned; given chains stay as they are
    scene = mi.load_file(str(SCENES / "door-ajar.xml"), resx=32, resy=32, gap_start=0.49)
    r = mlt.MLTRenderer(scene, seed=1, mutations_per_pixel=1024, max_depth=8)
    planned, boot = mlt.automatic_plan(1024 * 1024)
    assert r.bootstrap_samples == boot and mlt.MIN_CHAINS <= r.chains < planned // 4
    assert r.iterations == round(1024 * 1024 / r.chains)
    r = mlt.MLTRenderer(scene, seed=1, mutations_per_pixel=1024, chains=planned,
                        bootstrap_samples=65536, max_depth=8)
    assert r.chains == planned


def test_start_states_are_drawn_in_proportion_beside_a_large_weight():
    """The chains' start states are bootstrap samples drawn in proportion to their
    weights, by a float64 cumulative sum on the host: 4096 weights of 1 after one of
    2^25 get their share of 2^16 chains, 8 (a float32 scan, Mitsuba's
    DiscreteDistribution's, dropped them all; under CUDA its order of additions also
    varied between runs of one seed), and the same key draws the same states."""
    from types import SimpleNamespace
    weights = np.ones(4097)
    weights[0] = 2.0 ** 25
    mock = SimpleNamespace(chains=1 << 16, _key=lambda *v: dr.opaque(mi.UInt32, 7))
    pick = mlt.MLTRenderer._resample(mock, weights).numpy()
    assert np.all(np.diff(pick.astype(np.int64)) >= 0)
    assert 7 <= np.count_nonzero(pick) <= 9 and mock.start_states == np.count_nonzero(pick) + 1
    np.testing.assert_array_equal(mlt.MLTRenderer._resample(mock, weights).numpy(), pick)


def test_acceptance_of_small_and_large_steps():
    """The tally of small and large steps: large steps only count no small ones and
    the reverse; the mean acceptance per iteration is the proposals' mean of both."""
    scene = _box()
    kw = dict(mutations_per_pixel=8, bootstrap_samples=8192, chains=512, max_depth=5)
    small = _mlt(scene, 1, large_step_probability=0.0, **kw).stats
    large = _mlt(scene, 1, large_step_probability=1.0, **kw).stats
    assert small["acceptance_large"] == 0.0 and 0.0 < small["acceptance_small"] < 1.0
    assert large["acceptance_small"] == 0.0 and 0.0 < large["acceptance_large"] < 1.0
    assert abs(small["acceptance_small"] - small["acceptance"]) < 1e-5
    assert abs(large["acceptance_large"] - large["acceptance"]) < 1e-5
    r = mlt.MLTRenderer(scene, seed=2, **kw)
    while not r.done:
        r.run_iteration()
    t = r._tally.numpy()
    assert t[1] + t[3] == 512 * r.iterations_done
    assert abs((t[0] + t[2]) / (t[1] + t[3]) - np.mean(r.acceptance)) < 1e-5
    # small steps of a diffuse box are accepted more often than independent proposals
    assert r.step_acceptance()[0] > r.step_acceptance()[1] > 0.0


def test_benchmark_renders_at_least_one_iteration():
    """benchmarks/mlt_door.py at equal time: a bootstrap that outlasts the time still
    gets one iteration, as the CLI's --time (it returned a black image before)."""
    from benchmarks import mlt_door
    img, seconds, mpp = mlt_door.timed_mlt(_box(), 0.0, 1, chains=256, bootstrap=4096)
    assert mpp == 1 and img.mean() > 0


def test_unbounded_depth_and_filters():
    """max_depth -1 (coordinates past the stored depths are fresh numbers each
    evaluation) and a gaussian filter (splatted records) agree with BDPT."""
    scene = _box(filt="gaussian")
    runs = [_mlt(scene, seed, max_depth=-1).image for seed in range(6)]
    refs = [bdpt_drjit.render(scene, spp=32, seed=300 + s, max_depth=-1, light_paths=1,
                              connections="all").image for s in range(6)]
    # The light image and MLT's records lose the footprint outside the film where BDPT's
    # camera samples are normalized (README, Films): compare the interior.
    mask = np.zeros((16, 16), bool)
    mask[2:-2, 2:-2] = True
    assert_statistically_equal(runs, refs, blocks=2, what="max_depth -1", mask=mask)


@pytest.mark.parametrize("kind", list(KINDS))
def test_no_kernel_per_iteration_or_seed(kind):
    """mlt with two-stage too: its first stage's records once went to NumPy as whole
    vectors (a kernel per width), and NumPy's arrays, read in place at their own
    alignment, compiled their readers anew when it differed (backend.device_array)."""
    scene = _box()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        _mlt(scene, 1, kind, mutations_per_pixel=8)
        dr.kernel_history()
        _mlt(scene, 2, kind, mutations_per_pixel=8)
        entries = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
    new = [e for e in entries if not e.get("cache_hit", 1) or e.get("cache_disk", 0)]
    assert entries and not new, "%d kernels compiled" % len(new)


def test_no_kernel_per_seed_with_automatic_chains():
    """Where the bootstrap's effective sample size caps the automatic chains (door, 0.02
    gap: 2x ESS is 18865 and 18973 for seeds 1 and 2), a second seed's render compiles
    nothing (it compiled 3 kernels when the cap was not a power of two)."""
    scene = mi.load_file(str(SCENES / "door-ajar.xml"), resx=16, resy=16, gap_start=0.48)

    def start(seed):
        r = mlt.MLTRenderer(scene, seed=seed, mutations_per_pixel=4096, max_depth=6)
        for _ in range(2):
            r.run_iteration()
        r.tensor()
        return r.chains

    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        first = start(1)
        dr.kernel_history()
        second = start(2)
        entries = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
    assert first == second == 16384 < mlt.automatic_plan(4096 * 256)[0]
    new = [e for e in entries if not e.get("cache_hit", 1) or e.get("cache_disk", 0)]
    assert entries and not new, "%d kernels compiled" % len(new)


@pytest.mark.parametrize("kind", list(KINDS))
def test_replayed_walks_give_the_traced_image(kind):
    """The chains' walks replay recordings (frozen.py) from the second iteration on:
    the same seed gives the traced walks' image (within the film's float atomics, as
    tests/test_frozen.py), with two-stage and direct samples apart (the box)."""
    from bdpt_drjit import frozen
    scene = _box()
    old, images = frozen.ENABLED, []
    try:
        for on in (True, False):
            frozen.ENABLED = on
            images.append(_mlt(scene, 3, kind, mutations_per_pixel=16).image)
    finally:
        frozen.ENABLED = old
    np.testing.assert_allclose(images[0], images[1], rtol=1e-5, atol=1e-6)
    assert images[0].mean() > 0


def test_a_walk_that_cannot_be_recorded_is_traced(monkeypatch):
    """Where Dr.Jit cannot record a walk (frozen.RecordingFailed, raised after the walk
    ran: Mitsuba's various-emitters scene with bdpt, tests/test_frozen.py), the
    evaluation runs again with its walks traced: the image is the traced one."""
    from bdpt_drjit import frozen
    scene = _box()
    traced = frozen.call

    def fails_once(fn, *args):
        out = fn(*args)
        if not failed and fn.__name__.endswith("_walk"):
            failed.append(fn)
            raise frozen.RecordingFailed("a walk Dr.Jit could not record")
        return out
    failed, images = [], []
    old = frozen.ENABLED
    try:
        for on in (True, False):
            frozen.ENABLED = on
            monkeypatch.setattr(frozen, "call", fails_once if on else traced)
            images.append(_mlt(scene, 3, "mlt", mutations_per_pixel=16).image)
    finally:
        frozen.ENABLED = old
    assert failed
    np.testing.assert_allclose(images[0], images[1], rtol=1e-5, atol=1e-6)
    assert images[0].mean() > 0


STRESS = sorted(p.name for p in (SCENES / "stress").glob("*.xml"))


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("name", STRESS)
def test_stress_scenes_finite(name, kind):
    scene = mi.load_file(str(SCENES / "stress" / name), resx=16, resy=16)
    res = KINDS[kind][0](scene, seed=1, mutations_per_pixel=4, bootstrap_samples=4096,
                         chains=256, max_depth=8)
    assert np.isfinite(res.image).all() and (res.image >= 0).all()
    assert np.isfinite(res.stats["b"])


def test_refusals():
    scene = _box()
    with pytest.raises(ValueError, match="large_step_probability"):
        mlt.MLTRenderer(scene, large_step_probability=1.5)
    with pytest.raises(ValueError, match="unknown or unsupported parameter 'light_paths'"):
        mlt.MLTRenderer(scene, light_paths=1)
    with pytest.raises(ValueError, match="lafortune"):
        mlt.MLTRenderer(scene, mis="lafortune")
    cloud = mi.load_file(str(SCENES / "media" / "cloud.xml"), resx=8, resy=8)
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="heterogeneous"):
        mlt.MLTRenderer(cloud)


def test_black_scene():
    """No light reaches the camera: b = 0 and a black image, not NaNs."""
    scene = mi.load_file(str(SCENES / "no-emitters.xml"), resx=8, resy=8)
    with pytest.warns(UserWarning):
        res = mlt.render(scene, seed=1, mutations_per_pixel=4, bootstrap_samples=1024, chains=64)
    assert res.stats["b"] == 0 and not res.image.any()


def test_plugin_and_api_give_the_same_image():
    """``mi.render`` with the ``pssmlt`` plugin (spp = mutations per pixel, Mitsuba
    0.6's names) and ``bdpt_drjit.render(integrator="pssmlt")`` are the same render."""
    scene = _box()
    integ = mi.load_dict({"type": "pssmlt", "max_depth": 5, "pLarge": 0.3,
                          "luminanceSamples": 4096, "chains": 256})
    a = mi.render(scene, integrator=integ, spp=8, seed=4).numpy()
    b = bdpt_drjit.render(scene, spp=8, seed=4, integrator="pssmlt", max_depth=5,
                          bootstrap_samples=4096, chains=256).image
    assert np.allclose(a, b, rtol=1e-4, atol=1e-6)
    assert mi.load_dict({"type": "pssmlt", "directSamples": 4}).settings["direct_samples"] == 4
    with pytest.raises(ValueError, match="cluster"):
        bdpt_drjit.render(scene, spp=8, integrator="pssmlt", cluster="local:2")


def test_cli(tmp_path):
    """``bdpt mlt``: an EXR whose header says what it is; --time stops after an
    iteration with a correctly normalized image (its mean is b); bad options are one
    line, not a traceback."""
    import subprocess
    import sys
    from bdpt_drjit.exr import read_exr
    from conftest import cli_env
    out = tmp_path / "box.exr"
    cmd = [sys.executable, "-m", "bdpt_drjit", "mlt", str(SCENES / "cornell-box.xml"),
           "--res", "16x16", "--spp", "64", "--chains", "256",
           "--bootstrap-samples", "4096", "--max-depth", "5", "--no-large-step-mis",
           "--direct-samples", "-1",
           "-o", str(out)]
    p = subprocess.run(cmd + ["--time", "0.01"], capture_output=True, text=True, timeout=300,
                       env=cli_env())
    assert p.returncode == 0, p.stderr
    assert "time budget used up after 1 of 64 iterations" in p.stderr
    image, meta = read_exr(out)
    assert meta["integrator"] == "pssmlt" and int(meta["passes"]) == 1
    assert abs(image[..., :3].mean() / float(meta["b"]) - 1) < 1e-4
    assert out.with_suffix(".png").exists()
    p = subprocess.run(cmd + ["--large-step-probability", "2"], capture_output=True,
                       text=True, timeout=300, env=cli_env())
    assert p.returncode != 0 and "large_step_probability" in p.stderr
    assert "Traceback" not in p.stderr


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(KINDS))
def test_homogeneous_fog_matches_bdpt(kind):
    """Free flights draw a varying count of numbers per depth (media.py): the chains'
    coordinates shift with them, and the image still agrees with BDPT's."""
    scene = mi.load_file(str(SCENES / "media" / "fog-cube.xml"), resx=16, resy=16, g=0.5)
    runs = [_mlt(scene, seed, kind, max_depth=6).image for seed in range(6)]
    refs = [bdpt_drjit.render(scene, spp=32, seed=400 + s, max_depth=6, light_paths=1,
                              connections="all").image for s in range(6)]
    assert_statistically_equal(runs, refs, blocks=4, what="fog cube")


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("camera", ["thin lens, crop", "orthographic"])
def test_other_cameras_match_bdpt(camera, kind):
    """A thin lens (aperture numbers in the camera stream) with a crop window (film
    positions of the crop), and an orthographic camera (no light image: camera records
    only; for mlt the t = 1 strategies a chain may pick are off and weigh 0, as in
    BDPT's MIS)."""
    from test_cameras import ORTHOGRAPHIC, cornell_thin_lens, with_sensor
    if camera == "orthographic":
        scene = with_sensor("cornell-box.xml", ORTHOGRAPHIC, 16)
    else:
        scene = cornell_thin_lens(0.5, res=20, film_xml=(
            '<integer name="crop_offset_x" value="5"/><integer name="crop_offset_y" '
            'value="3"/><integer name="crop_width" value="12"/><integer '
            'name="crop_height" value="12"/>'))
    runs = [_mlt(scene, seed, kind, max_depth=6).image for seed in range(6)]
    refs = [bdpt_drjit.render(scene, spp=32, seed=500 + s, max_depth=6, light_paths=1,
                              connections="all").image for s in range(6)]
    assert_statistically_equal(runs, refs, blocks=4, what=camera)


@pytest.mark.parametrize("kind", list(KINDS))
def test_rgba_film_alpha_is_bdpts(kind):
    """An rgba film's alpha is the camera rays' coverage, as the default bdpt's: a
    sphere against nothing, half the film's pixels at alpha 0 (the chains' records
    alone had left alpha 0 everywhere: a transparent image).  RGB is the records'."""
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16,
                            "pixel_format": "rgba", "rfilter": {"type": "box"}}},
        "ball": {"type": "sphere", "radius": 1.0, "bsdf": {"type": "diffuse"}},
        "sun": {"type": "point", "position": [2, 3, 4], "intensity": 20.0}})
    image = _mlt(scene, 1, kind).image
    ref = bdpt_drjit.render(scene, spp=64, seed=1, max_depth=5).image
    assert image.shape == ref.shape == (16, 16, 4)
    alpha, ref_alpha = image[..., 3], ref[..., 3]
    assert 0.2 < ref_alpha.mean() < 0.8 and (ref_alpha == 0).any() and (ref_alpha == 1).any()
    assert np.all((alpha >= 0) & (alpha <= 1))
    # ALPHA_SPP samples per pixel against 64: the interior and the outside agree
    # exactly, the silhouette's pixels within a sample's share.
    assert np.array_equal(alpha == 0, ref_alpha == 0) or np.abs(alpha - ref_alpha).max() <= 0.5
    assert abs(alpha.mean() - ref_alpha.mean()) < 0.02
    assert np.allclose(image[..., :3].mean(), ref[..., :3].mean(), rtol=0.1)


def test_accepted_rows_are_copied_and_nothing_else():
    """Chains.accept copies the accepted chains' rows only (mlt._copy_rows): the result
    is the select over every coordinate, and another reference to the old state keeps
    its values (Dr.Jit's scatter writes in place where x has no other reference)."""
    rng = np.random.default_rng(5)
    chains, dims = 37, 11
    x_np, y_np = rng.random(chains * dims), rng.random(chains * dims)
    accepted_np = rng.random(chains) < 0.3
    x, y = mi.Float(x_np), mi.Float(y_np)
    other = mi.Float(x)
    rows = dr.compress(mi.Bool(accepted_np))
    out = mlt._copy_rows(x, y, rows, dims)
    want = np.where(np.repeat(accepted_np, dims), y_np, x_np).astype(np.float32)
    assert np.array_equal(out.numpy(), want)
    assert np.array_equal(other.numpy(), x_np.astype(np.float32))
    assert mlt._copy_rows(other, y, dr.zeros(mi.UInt32, 0), dims) is other


@pytest.mark.parametrize("kind", list(KINDS))
def test_stored_vectors_cover_what_the_walks_read(kind, monkeypatch):
    """The chains' vectors end where the walks stop reading (mlt.PER_DEPTH): the
    largest coordinate a chain's camera and light samplers read, over iterations, is
    the last stored one on the pinhole box (no stored number unread, none read past)."""
    from bdpt_drjit import frozen
    monkeypatch.setattr(frozen, "ENABLED", False)       # the samplers' reads traced
    reads, make = {}, pss.PSSSampler.make

    def counting(lanes, key, identity, values=None, dims=0):
        sampler = make(lanes, key, identity, values, dims)
        if values is not None:
            reads[id(sampler.source)] = (dims, dr.zeros(mi.UInt32, lanes))
        return sampler
    next_1d = pss.PSSSampler.next_1d

    def next_counted(self, active=True):
        if id(self.source) in reads:
            dr.scatter_reduce(dr.ReduceOp.Max, reads[id(self.source)][1], self.dim + 1,
                              dr.arange(mi.UInt32, dr.width(self.dim)), active)
        return next_1d(self, active)
    monkeypatch.setattr(pss.PSSSampler, "make", staticmethod(counting))
    monkeypatch.setattr(pss.PSSSampler, "next_1d", next_counted)
    r = KINDS[kind][1](_box(), seed=1, mutations_per_pixel=16, bootstrap_samples=16384,
                       chains=1024, max_depth=5)
    reads.clear()
    while not r.done:
        r.run_iteration()
    assert r.dims["camera_u"] == 2 + mlt.PER_DEPTH * 5
    assert r.dims["light_u"] == mlt.LIGHT_START + mlt.PER_DEPTH * 4
    most = {}
    for dims, count in reads.values():
        most[dims] = max(most.get(dims, 0), int(dr.max(count)[0]))
    assert most == {r.dims["camera_u"]: r.dims["camera_u"],
                    r.dims["light_u"]: r.dims["light_u"]}
