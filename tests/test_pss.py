"""Primary sample space (bdpt_drjit/pss.py): the samplers' numbers and the
Metropolis-Hastings kernel on them, on 1D toy targets (pure Dr.Jit, fast).

Detailed balance of the small step: chains started exactly in the target density
pi must stay in it after many Kelemen small steps accepted with min(1, f(y)/f(x)):
a chi-square test of the final histogram (independent chains: a multinomial).  A
deliberately asymmetric proposal (every step upward) fails the same test, so the
test can see a wrong kernel."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

import bdpt_drjit  # noqa: F401  (sets the variant)
from bdpt_drjit import pss

BINS = 32


def _target(x):
    """A 1D target with a deep valley and a peak near the wrap-around point."""
    return 0.05 + dr.square(dr.sin(3.0 * dr.pi * x)) + 2.0 * dr.exp(-dr.square((x - 0.97) / 0.03))


def _target_np(x):
    return 0.05 + np.sin(3 * np.pi * x) ** 2 + 2.0 * np.exp(-((x - 0.97) / 0.03) ** 2)


def _start_in_target(n, rng):
    """n exact draws from pi (inverse CDF on a fine grid, then uniform within a cell)."""
    grid = np.linspace(0.0, 1.0, 200001)
    cdf = np.concatenate([[0.0], np.cumsum(_target_np(0.5 * (grid[1:] + grid[:-1])))])
    cdf /= cdf[-1]
    return np.interp(rng.random(n), cdf, grid)


def _bin_probabilities():
    edges = np.linspace(0.0, 1.0, BINS + 1)
    fine = np.linspace(0.0, 1.0, 320001)
    mid = 0.5 * (fine[1:] + fine[:-1])
    w = _target_np(mid)
    p = np.array([w[(mid >= a) & (mid < b)].sum() for a, b in zip(edges[:-1], edges[1:])])
    return p / p.sum()


def _run_chains(x0, steps, p_large, asymmetric=False, seed=3, film=None, s1=pss.S1):
    x = mi.Float(x0)
    n = dr.width(x)
    fx = _target(x)
    chain = dr.arange(mi.UInt32, n)
    for it in range(steps):
        key = dr.opaque(mi.UInt32, (seed * 1000003 + it * 7919) & 0xFFFFFFFF)
        large = pss.hash_uniform(key, chain, 1 << 20) < dr.opaque(mi.Float, p_large)
        if asymmetric:
            y = pss.wrap(x + pss.S2 * dr.exp(-dr.log(pss.S2 / pss.S1)
                                             * pss.hash_uniform(key, chain, 0)))
        else:
            y = pss.propose(x, 1, large, key, film, s1)
        fy = _target(y)
        a = pss.acceptance(fx, fy)
        accept = pss.hash_uniform(key, chain, 1 << 21) < a
        x = dr.select(accept, y, x)
        fx = dr.select(accept, fy, fx)
        dr.eval(x, fx)
    return x.numpy()


def _chi2_p(samples):
    counts, _ = np.histogram(samples, bins=BINS, range=(0.0, 1.0))
    return stats.chisquare(counts, _bin_probabilities() * len(samples)).pvalue


def test_small_steps_keep_the_target():
    """Detailed balance of the small step (with wrap-around): pi stays pi."""
    x0 = _start_in_target(20000, np.random.default_rng(1))
    assert _chi2_p(_run_chains(x0, 200, 0.0)) > 1e-3


def test_mixed_steps_reach_the_target_from_uniform():
    """Large steps (p = 0.3) and small steps from a uniform start converge to pi."""
    x0 = np.random.default_rng(2).random(20000)
    assert _chi2_p(_run_chains(x0, 60, 0.3)) > 1e-3


def test_an_asymmetric_proposal_is_seen():
    """Control: steps that always go up are not symmetric; the same test rejects them."""
    x0 = _start_in_target(20000, np.random.default_rng(1))
    assert _chi2_p(_run_chains(x0, 200, 0.0, asymmetric=True)) < 1e-6


def test_small_step_sizes_are_kelemens():
    """|y - x| (on the circle) lies in [s1, s2] with log|y - x| uniform."""
    n = 100000
    x = mi.Float(np.random.default_rng(4).random(n))
    y = pss.propose(x, 1, dr.zeros(mi.Bool, n), dr.opaque(mi.UInt32, 77))
    d = np.abs(y.numpy() - x.numpy())
    d = np.minimum(d, 1.0 - d)
    assert d.min() >= pss.S1 * (1 - 1e-3) and d.max() <= pss.S2 * (1 + 1e-3)
    u = np.log(d / pss.S1) / np.log(pss.S2 / pss.S1)
    assert stats.kstest(np.clip(u, 0, 1), "uniform").pvalue > 1e-3


def test_fine_steps_keep_the_target():
    """Detailed balance of the finer small steps (s1 = FINE_S1, pss.fine_steps)."""
    x0 = _start_in_target(20000, np.random.default_rng(1))
    assert _chi2_p(_run_chains(x0, 200, 0.0, s1=pss.FINE_S1)) > 1e-3


def test_fine_step_sizes():
    """|y - x| lies in [FINE_S1, S2] with log|y - x| uniform (x in [1/4, 1/2), where
    float rounding is below 1e-3 of FINE_S1 and no step wraps)."""
    n = 100000
    x = mi.Float(0.25 + 0.25 * np.random.default_rng(6).random(n))
    y = pss.propose(x, 1, dr.zeros(mi.Bool, n), dr.opaque(mi.UInt32, 79), None,
                    dr.opaque(mi.Float, pss.FINE_S1))
    d = np.abs(y.numpy() - x.numpy())
    assert d.min() >= pss.FINE_S1 * (1 - 1e-3) and d.max() <= pss.S2 * (1 + 1e-3)
    u = np.log(d / pss.FINE_S1) / np.log(pss.S2 / pss.FINE_S1)
    assert stats.kstest(np.clip(u, 0, 1), "uniform").pvalue > 1e-3


def test_fine_steps_where_kelemens_are_rejected():
    """Finer steps only where Kelemen's are accepted less than FINE_BELOW."""
    assert pss.fine_steps(0.05) == pss.FINE_S1 < pss.S1
    assert pss.fine_steps(pss.FINE_BELOW) == pss.fine_steps(0.8) == pss.S1


def test_film_steps_keep_the_target():
    """Detailed balance of the film position's wider small steps (pss.film_steps of a
    64-pixel film; with one coordinate per row every coordinate takes them)."""
    x0 = _start_in_target(20000, np.random.default_rng(1))
    assert _chi2_p(_run_chains(x0, 200, 0.0, film=pss.film_steps(64))) > 1e-3


def test_film_steps_move_only_the_film_position():
    """A row's first two coordinates step from FILM_S1_PIXELS pixels to FILM_S2 of the
    side (log-uniform), the others by Kelemen's sizes."""
    rows, dims, res = 50000, 4, 64
    x = mi.Float(np.random.default_rng(5).random(rows * dims))
    y = pss.propose(x, dims, dr.zeros(mi.Bool, rows), dr.opaque(mi.UInt32, 78),
                    pss.film_steps(res))
    d = np.abs(y.numpy() - x.numpy()).reshape(rows, dims)
    d = np.minimum(d, 1.0 - d)
    for cols, s1, s2 in (((0, 1), pss.FILM_S1_PIXELS / res, pss.FILM_S2),
                         ((2, 3), pss.S1, pss.S2)):
        dc = d[:, cols].ravel()
        assert dc.min() >= s1 * (1 - 1e-3) and dc.max() <= s2 * (1 + 1e-3)
        u = np.log(dc / s1) / np.log(s2 / s1)
        assert stats.kstest(np.clip(u, 0, 1), "uniform").pvalue > 1e-3


def test_sampler_reads_its_vector_then_hashes():
    """Lane i reads row i for dims < D, then hash(key, identity, dim), the same numbers
    a hashing sampler gives; hashed_vectors rebuilds a hashing sampler's vector."""
    lanes, dims = 5, 3
    key = dr.opaque(mi.UInt32, 12345)
    ident = mi.UInt32([7, 8, 9, 10, 11])
    values = pss.hashed_vectors(key, ident, dims)
    hashing = pss.PSSSampler.make(lanes, key, ident)
    stored = pss.PSSSampler.make(lanes, key, ident, values + 0.0, dims)
    for _ in range(dims + 2):
        a, b = hashing.next_1d().numpy(), stored.next_1d().numpy()
        assert np.array_equal(a, b)
    other = pss.PSSSampler.make(lanes, key, ident, dr.full(mi.Float, 0.25, lanes * dims), dims)
    assert np.all(other.next_2d().x.numpy() == 0.25)


def test_sampler_as_loop_state():
    """The sampler's counter advances inside dr.while_loop, per lane."""
    lanes = 4
    s = pss.PSSSampler.make(lanes, dr.opaque(mi.UInt32, 5), dr.arange(mi.UInt32, lanes),
                            dr.arange(mi.Float, lanes * 8) / 64.0, 8)
    i = mi.UInt32([0, 1, 2, 3])
    acc = dr.zeros(mi.Float, lanes)

    def body(i, acc, s):
        acc += s.next_1d()
        return i + 1, acc, s

    i, acc, s = dr.while_loop((i, acc, s), lambda i, acc, s: i < 3, body)
    rows = np.arange(32).reshape(4, 8) / 64.0
    expect = [rows[k, :3 - k].sum() for k in range(lanes)]
    assert np.allclose(acc.numpy(), expect) and list(s.dim.numpy()) == [3, 2, 1, 0]
