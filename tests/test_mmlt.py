"""Multiplexed MLT over the wavefront BDPT (bdpt_drjit/mmlt.py, the ``mlt`` integrator).

* A chain's sample is one strategy of the full BDPT sample: its target is k + 1 times
  that strategy's MIS-weighted luminance in the full sample of the same numbers (the
  walks stop early and connect once, and nothing else changes).
* b_k, per path length, agrees with BDPT's image of that length.
* The image agrees with BDPT's (Welch's t-test over independent runs, whole image and
  4 x 4 blocks, as tests/test_mlt.py, which also runs its other steps and its image sum,
  b N at every iteration, for both kinds).
* The strategy stream keeps its target: chains over u_c on a piecewise constant target
  with zero strategies (a 1D toy of the multiplexed space).
* No kernel is compiled per iteration or per seed; the stress scenes render finite; fog,
  a thin lens with a crop and an orthographic camera agree with BDPT (tests/test_mlt.py,
  for both kinds).
* multiplex="auto" takes a length per chain (and large steps of 0.3) on the box, a
  strategy (and 0.1) on the door; the first stage's blocks shrink with its effective
  sample size.
* The plugin, the API and the CLI; refusals."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

import bdpt_drjit
from bdpt_drjit import mmlt, pss
from conftest import SCENES
from stats import assert_statistically_equal
from test_mlt import _box

RUNS = 8


def _mmlt(scene, seed, **kw):
    params = dict(mutations_per_pixel=32, bootstrap_samples=16384, chains=1024, max_depth=5)
    params.update(kw)
    return mmlt.render(scene, seed=seed, **params)


@pytest.mark.parametrize("multiplex", ["strategy", "length"])
def test_chain_target_is_its_strategy_of_the_full_sample(multiplex):
    """``length``: the target is every strategy of the chain's length."""
    scene = _box()
    r = mmlt.MMLTRenderer(scene, seed=2, mutations_per_pixel=4, bootstrap_samples=8192,
                          chains=512, max_depth=5, multiplex=multiplex)
    x = r.state
    keys = r._stream_keys(0xB0)
    r.strategies.set_lanes(None, None)
    r.images = mmlt.StrategyLuminance(r.chains, 5)
    pick = dr.arange(mi.UInt32, r.chains)           # the chains' vectors, any tails
    full = r._evaluate_vectors(r.chains, keys, pick, x.vectors())
    cells = r.images.values.numpy().reshape(r.chains, -1)
    r.images = None
    chain = r._evaluate_chains(keys, pick, x.vectors(), x.depth)
    k, u = x.depth.numpy(), x.tech_u.numpy()
    s = np.minimum((u * (k + 1)).astype(int), k)
    index = (k * (k + 1) - 2) // 2 + s
    expected = (k + 1) * cells[np.arange(r.chains), index]
    if multiplex == "length":
        k_of, _ = mmlt.cell_table(5)
        expected = np.stack([cells[:, k_of == j].sum(axis=1) for j in range(1, 6)], 1)[
            np.arange(r.chains), k - 1]
    assert (expected > 0).mean() > 0.95      # chains start on strategies that carry light
    assert np.allclose(chain.f.numpy(), expected, rtol=1e-3, atol=1e-6)
    assert np.allclose(full.f.numpy(), cells.sum(axis=1), rtol=1e-3, atol=1e-6)
    assert (np.diff(k) >= 0).all()           # lanes sorted by path length


def test_b_per_path_length_matches_bdpt():
    scene = _box()
    # The chains over every length (direct_samples=-1: no lengths rendered apart).
    r = mmlt.MMLTRenderer(scene, seed=5, mutations_per_pixel=16, bootstrap_samples=1 << 18,
                          chains=4096, max_depth=4, direct_samples=-1)
    ref = bdpt_drjit.render(scene, spp=512, seed=7, max_depth=4, strategy_images=True)
    per_k = [ref.length_images[k][..., :3].mean() if k in ref.length_images else
             sum(v[..., :3].mean() for (s, t), v in ref.strategy_images.items()
                 if s + t - 1 == k) for k in range(1, 5)]
    assert np.allclose(r.b_plain, per_k, rtol=0.03), (r.b_plain, per_k)
    assert r.b == pytest.approx(r.b_plain.sum())
    assert r.chains_per_depth.sum() == r.chains == 4096
    # chains over lengths in proportion to the target's b_k (stratified resampling)
    share, target = r.chains_per_depth / r.chains, r.b_depths / r.b_depths.sum()
    assert np.allclose(share, target, atol=0.02), (share, target)


@pytest.mark.parametrize("multiplex", ["strategy", "length"])
def test_image_matches_bdpt(multiplex):
    """8 runs of 32 mutations per pixel against 8 BDPT renders of 32 spp."""
    scene = _box()
    runs = [_mmlt(scene, seed, multiplex=multiplex).image for seed in range(RUNS)]
    refs = [bdpt_drjit.render(scene, spp=32, seed=100 + s, max_depth=5, light_paths=1,
                              connections="all").image for s in range(RUNS)]
    assert_statistically_equal(runs, refs, blocks=4, what="mlt (%s) vs bdpt" % multiplex)


def test_automatic_chains_follow_the_cells_effective_size():
    """Automatic chains: at most 2x the effective sample size of the bootstrap's cells
    (k, s) of samples (mlt.chains_for_ess), which is at least that of the samples' f
    (pssmlt's cap): door with a 0.02 gap, 16x16."""
    from bdpt_drjit import mlt
    scene = mi.load_file(str(SCENES / "door-ajar.xml"), resx=16, resy=16, gap_start=0.48)
    a = mmlt.MMLTRenderer(scene, seed=1, mutations_per_pixel=4096, max_depth=6)
    b = mlt.MLTRenderer(scene, seed=1, mutations_per_pixel=4096, max_depth=6)
    assert a.bootstrap_samples == b.bootstrap_samples and a.b == pytest.approx(b.b, rel=1e-5)
    assert b.chains <= a.chains < mlt.automatic_plan(4096 * 256)[0]
    assert a.chains & (a.chains - 1) == 0


def test_automatic_bootstrap_stops_at_the_chains_effective_size():
    """An automatic bootstrap stops after the batch where its cells' effective sample
    size reaches ESS_STOP x the planned chains (the box: after 131072 of 262144
    planned samples), and the render is then the one of that many samples given
    explicitly (b, the direct image's normalization and the chains' start alike)."""
    from bdpt_drjit import mlt
    scene = _box()
    kw = dict(seed=3, mutations_per_pixel=256, chains=32768, max_depth=5)
    auto = mmlt.MMLTRenderer(scene, **kw)
    assert mlt.automatic_plan(256 * 256, 32768)[1] == 262144
    assert auto.bootstrap_samples == 131072
    fixed = mmlt.MMLTRenderer(scene, bootstrap_samples=131072, **kw)
    for r in (auto, fixed):
        r.run_iteration()
    assert auto.b == fixed.b and auto.direct_lanes == fixed.direct_lanes > 0
    assert np.allclose(auto.result().image, fixed.result().image, rtol=1e-5, atol=1e-8)
    assert auto.result().stats["bootstrap_samples"] == 131072


def test_automatic_multiplex_follows_the_bootstraps_spread():
    """multiplex="auto" (the default) takes "length", with large steps of probability
    0.3, where the effective sample size of the bootstrap's strategy cells of the
    chains' lengths is at least mmlt.EASY_ESS x its samples (the box: most samples
    light several strategies), else "strategy" with 0.1 (the door with a narrow gap:
    few samples carry light); the render is then the one of that choice given
    explicitly."""
    from bdpt_drjit import mlt
    kw = dict(seed=2, mutations_per_pixel=8, bootstrap_samples=16384, chains=512, max_depth=5)
    box = _box()
    auto = mmlt.MMLTRenderer(box, **kw)
    fixed = mmlt.MMLTRenderer(box, multiplex="length", large_step_probability=0.3, **kw)
    assert auto.multiplex == "length" and auto.p_large == mlt.MMLT_LARGE_STEP["length"] == 0.3
    assert auto.multiplex_ess >= mmlt.EASY_ESS
    for r in (auto, fixed):
        r.run_iteration()
    assert np.allclose(auto.result().image, fixed.result().image, rtol=1e-5, atol=1e-8)
    stats = auto.result().stats
    assert stats["multiplex"] == "length" and stats["large_step_probability"] == 0.3
    door = mi.load_file(str(SCENES / "door-ajar.xml"), resx=16, resy=16, gap_start=0.49)
    hard = mmlt.MMLTRenderer(door, **kw)
    assert hard.multiplex == "strategy" and hard.p_large == 0.1
    assert hard.multiplex_ess < mmlt.EASY_ESS
    given = mmlt.MMLTRenderer(box, large_step_probability=0.2, **kw)   # kept where given
    assert given.multiplex == "length" and given.p_large == 0.2


def test_stage_blocks_shrink_with_the_stages_effective_size():
    """mlt.stage_block: the first stage's blocks are the smallest power of two up to
    STAGE_BLOCK pixels whose blocks hold at least STAGE_PER_BLOCK effective samples on
    average; pixel_weights of blocks of 1 pixel are per pixel."""
    from bdpt_drjit import mlt
    px = 64 * 64
    assert mlt.STAGE_BLOCK == 8 and mlt.STAGE_PER_BLOCK == 32
    assert [mlt.stage_block(e, px) for e in (0.0, 2048, 8191, 8192, 32768, 131072, 1e9)] \
        == [8, 8, 8, 4, 2, 1, 1]
    lum = np.arange(1.0, 13.0).reshape(3, 4)
    assert np.allclose(mlt.pixel_weights(lum, 1), lum.mean() / lum)


def test_pixel_weights_are_first_stage_block_means_floored():
    """mlt.pixel_weights: 1 / L over blocks of STAGE_BLOCK^2 pixels (partial blocks at
    the edges), floored at STAGE_FLOOR x the mean, over their mean; 1 where black."""
    from bdpt_drjit import mlt
    k = mlt.STAGE_BLOCK
    lum = np.zeros((2 * k, 3 * k - 2))
    lum[:k, :k], lum[:k, k:2 * k], lum[k:, :k] = 4.0, 1.0, 0.5
    lum[0, 0] = np.nan                       # a non-finite pixel counts as black
    w = mlt.pixel_weights(lum)
    level = np.maximum(np.array([[4.0 - 4.0 / k ** 2, 1.0, 0.0], [0.5, 0.0, 0.0]]),
                       mlt.STAGE_FLOOR * (4 - 4 / k ** 2 + 1.5) * k * k / lum.size)
    per_pixel = np.repeat(np.repeat(level, k, 0), k, 1)[:, :3 * k - 2]
    assert np.allclose(w, per_pixel.mean() / per_pixel, rtol=1e-5)
    assert (mlt.pixel_weights(np.zeros((5, 7))) == 1.0).all()


def test_two_stage_target_is_luminance_over_the_first_stage():
    """two_stage: a lane's target is the sum over its records of Y(value) times 1 / L
    of the record's pixel (the first stage's mlt.pixel_weights), in the bootstrap's
    cells and the chains alike; b and the chains' plan are the luminance's, as
    without it (the same bootstrap samples).  The same seed gives the same weights
    (the light image's records come in the order of atomic slots)."""
    from bdpt_drjit import mlt
    scene = _box()
    kw = dict(seed=2, mutations_per_pixel=4, bootstrap_samples=8192, chains=512,
              max_depth=5, direct_samples=-1)
    a = mmlt.MMLTRenderer(scene, two_stage=True, **kw)
    plain = mmlt.MMLTRenderer(scene, two_stage=False, **kw)
    again = mmlt.MMLTRenderer(scene, two_stage=True, **kw)
    assert (a.pixel_weight.numpy() == again.pixel_weight.numpy()).all()
    assert (a.state.f.numpy() == again.state.f.numpy()).all()
    assert plain.pixel_weight is None and a.stage_samples == mlt.STAGE_LANES
    assert a.b == pytest.approx(plain.b, rel=1e-5) and a.chains == plain.chains
    assert np.allclose(a.b_plain, plain.b_depths, rtol=1e-5)
    w = a.pixel_weight.numpy().reshape(16, 16)
    assert w.min() > 0 and w.max() / w.min() > 2            # the lamp's pixels weigh less
    a.strategies.set_lanes(None, None)
    a.images = mmlt.StrategyLuminance(a.chains, 5)
    keys = a._stream_keys(0xB0)
    ev = a._evaluate_vectors(a.chains, keys, dr.arange(mi.UInt32, a.chains),
                             a.state.vectors())
    cells = a.images.values.numpy().reshape(a.chains, -1)
    a.images = None

    def weighted(records):
        pos = np.minimum(np.floor(records.pos.numpy()).astype(int), 15)
        return records.value.numpy().mean(axis=0) * w[pos[1], pos[0]]
    f = weighted(ev.camera)
    np.add.at(f, ev.splats.lane.numpy(), weighted(ev.splats))
    assert np.allclose(ev.f.numpy(), f, rtol=1e-4, atol=1e-7)
    assert np.allclose(cells.sum(axis=1), f, rtol=1e-3, atol=1e-6)


def test_strategy_stream_keeps_its_target():
    """Chains on u_c alone, k = 4: target (k + 1) L_s with L = (1, 0, 3, 0.2, 0), started
    by the bootstrap's rule (a strategy in proportion to L, u_c uniform in its
    interval), 100 mixed steps: the strategies' histogram stays L / sum L (chi-square),
    and no chain reaches a zero strategy."""
    k, weights = 4, np.array([1.0, 0.0, 3.0, 0.2, 0.0])
    n = 20000
    rng = np.random.default_rng(4)
    s0 = rng.choice(k + 1, size=n, p=weights / weights.sum())
    u = mi.Float(((s0 + rng.random(n)) / (k + 1)).astype(np.float32))
    table = mi.Float(weights.astype(np.float32) * (k + 1))
    chain = dr.arange(mi.UInt32, n)
    depth = dr.full(mi.UInt32, k, n)

    def target(v):
        s, _, _ = mmlt.techniques(depth, v)
        return dr.gather(mi.Float, table, s)

    fu = target(u)
    for it in range(100):
        key = dr.opaque(mi.UInt32, 0x5151 + it * 7919)
        large = pss.hash_uniform(key, chain, 1 << 20) < dr.opaque(mi.Float, 0.3)
        v = pss.propose(u, 1, large, key)
        fv = target(v)
        accept = pss.hash_uniform(key, chain, 1 << 21) < pss.acceptance(fu, fv)
        u, fu = dr.select(accept, v, u), dr.select(accept, fv, fu)
        dr.eval(u, fu)
    s = np.minimum((u.numpy() * (k + 1)).astype(int), k)
    counts = np.bincount(s, minlength=k + 1)
    assert counts[1] == counts[4] == 0
    on = weights > 0
    p = stats.chisquare(counts[on], weights[on] / weights.sum() * n).pvalue
    assert p > 1e-3, (counts, p)


def test_plugin_api_and_refusals():
    """``mi.render`` with the ``mlt`` plugin and ``bdpt_drjit.render(integrator="mlt")``
    are the same render; an unbounded max_depth is refused with a message."""
    scene = _box()
    integ = mi.load_dict({"type": "mlt", "max_depth": 5, "pLarge": 0.1,
                          "luminanceSamples": 4096, "chains": 256})
    assert "MMLT" in integ.to_string() and "multiplexed" in type(integ).__doc__.lower()
    a = mi.render(scene, integrator=integ, spp=8, seed=4).numpy()
    b = bdpt_drjit.render(scene, spp=8, seed=4, integrator="mlt", max_depth=5,
                          bootstrap_samples=4096, chains=256, large_step_probability=0.1)
    assert b.stats["integrator"] == "mlt" and len(b.stats["b_depths"]) == 5
    assert b.stats["large_step_probability"] == 0.1
    assert np.allclose(a, b.image, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="finite max_depth"):
        mmlt.MMLTRenderer(scene, max_depth=-1)
    with pytest.raises(ValueError, match="mlt: unknown or unsupported parameter 'light_paths'"):
        mmlt.MMLTRenderer(scene, max_depth=5, light_paths=1)
    with pytest.raises(ValueError, match="lafortune"):
        mmlt.MMLTRenderer(scene, max_depth=5, mis="lafortune")
    with pytest.raises(ValueError, match="multiplex must be one of strategy, length, auto"):
        mmlt.MMLTRenderer(scene, max_depth=5, multiplex="technique")
    with pytest.raises(ValueError, match=r"large_step_probability must lie in \[0, 1\] \(-1"):
        mmlt.MMLTRenderer(scene, max_depth=5, large_step_probability=-0.5)
    with pytest.raises(ValueError, match="pssmlt: unknown or unsupported parameter 'multiplex'"):
        bdpt_drjit.render(scene, spp=4, integrator="pssmlt", multiplex="length")


def test_black_scene():
    scene = mi.load_file(str(SCENES / "no-emitters.xml"), resx=8, resy=8)
    with pytest.warns(UserWarning):
        res = mmlt.render(scene, seed=1, mutations_per_pixel=4, bootstrap_samples=1024,
                          chains=64, max_depth=4)
    assert res.stats["b"] == 0 and not res.image.any()


def test_cli(tmp_path):
    import subprocess
    import sys
    from bdpt_drjit.exr import read_exr
    from conftest import cli_env
    out = tmp_path / "box.exr"
    cmd = [sys.executable, "-m", "bdpt_drjit", "mlt", str(SCENES / "cornell-box.xml"),
           "--integrator", "mlt", "--res", "16x16", "--spp", "64", "--chains", "256",
           "--bootstrap-samples", "4096", "--max-depth", "5", "--no-large-step-mis",
           "--direct-samples", "-1", "--no-two-stage",
           "-o", str(out)]   # the image is then b's alone
    p = subprocess.run(cmd + ["--time", "0.01"], capture_output=True, text=True, timeout=300,
                       env=cli_env())
    assert p.returncode == 0, p.stderr
    assert "bdpt: mlt cornell-box.xml" in p.stderr
    image, meta = read_exr(out)
    assert meta["integrator"] == "mlt" and int(meta["passes"]) == 1
    assert abs(image[..., :3].mean() / float(meta["b"]) - 1) < 1e-4
    unbounded = cmd[:cmd.index("--max-depth") + 1] + ["-1"] + cmd[cmd.index("--max-depth") + 2:]
    p = subprocess.run(unbounded, capture_output=True,
                       text=True, timeout=300, env=cli_env())
    assert p.returncode != 0 and "finite max_depth" in p.stderr and "Traceback" not in p.stderr
