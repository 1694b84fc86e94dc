"""Multiplexed Metropolis light transport (MMLT, Hachisuka, Kaplanyan and Dachsbacher
2014) over the wavefront BDPT: the ``mlt`` integrator.  PSSMLT (mlt.py) is its base.

A chain of MMLT has a path length k (edges, k = s + t - 1 in Veach's notation), fixed
for the chain's life, and its state is three primary sample streams (pbrt-v3's
MLTIntegrator): the camera subpath's, the light subpath's, and one number u_c that
picks the strategy among the k + 1 of length k,

    s = min(floor(u_c (k + 1)), k),  t = k + 1 - s.

The path sample evaluates that one strategy, with its MIS weight over all the
strategies of the path (mis.py, the same weights as a BDPT sample), and divides by
its selection probability 1 / (k + 1):

    f_k(u) = (k + 1) Y(w_{s,t} C_{s,t}(u))        (Hachisuka 2014, eq. 5)

Its records are the camera value (t >= 2) or the light image's splat (t = 1), times
k + 1.  The sum over s of the MIS-weighted strategies is the path's contribution, so
E_u[records of f_k] is the image of paths of length k, and the sum over k the image.
The walks stop at z_{t-1} and y_{s-1} and evaluate one connection (ChainStrategies
masks every other strategy per lane): an evaluation costs a fraction of a full BDPT
sample, and a chain spends its mutations on the strategy whose weight carries the
path.

Normalization (pbrt-v3 bootstraps per depth): b_k = E_u[f_k], the brightness of
paths of length k, b = sum_k b_k, and n_k of the N chains have length k, about
N b_k / b.  With c_k = b_k N / n_k, a chain of length k has the density f_k / c_k
per iteration in the space of (k, u) (its share n_k / N times f_k / b_k), and its
records are splatted times c_k / f (Veach's expected values,
pss.expected_value_weights with b = c_k; the large steps' density is p_large
b_k / c_k).  The image's luminance sum per iteration is sum_k n_k c_k = b N, as in
PSSMLT.

Start-up: the bootstrap is made of full BDPT samples, not of strategy samples as
pbrt's (the strategies' luminances recorded per lane by StrategyLuminance): b_k sums
every strategy of length k of each sample (the strategy stream integrated out), and
a chain starts on a picked sample's cell (k, s) drawn in proportion to its
luminance, with u_c uniform in that strategy's interval: resampling in proportion to
the target over (k, u_c, u).  On the door (0.05 gap, 64x64, 65536 chains, 256
mutations per pixel) pbrt's way started the chains on 4704 distinct samples and gave
relMSE 0.55, this one 48337 and 0.059.  Lanes are then sorted by k and s, so a SIMD
packet's lanes walk subpaths of like lengths.  An automatic bootstrap stops after the
batch where the cells' effective sample size (sum L)^2 / sum L^2 reaches ESS_STOP x
the planned chains (mlt.py): an easy scene (the diffuse box) then spends a quarter of
its planned bootstrap, a hard one (the door's gaps) all or most of it.

Two-stage (``two_stage``, the default; Hoberock and Hart 2010; mlt.py's STAGE_*): f_k
is divided by the first stage's brightness L of the record's pixel (every f above,
b_k, c_k and the bootstrap's cells are then of that target; the image is not, its
records being weighted c_k / f).  An MMLT sample has one record, so each chain's
state sits in one pixel: the chains spend their time evenly over dark and bright
pixels.  Door, 0.01 gap, 600 iterations, seeds 1-2: relMSE 0.0595 / 0.0590 ->
0.0514 / 0.0499 (the reference's 0.017 in each; benchmarks/RESULTS.md).  b, the
direct decision and the automatic chains stay the luminance's (``b_plain``).

With separate direct samples (mlt.py), b_1 and b_2 go to them: the chains start on
cells of length 3 up only, and c_k of k <= 2 is 0.

``multiplex="length"``: a chain fixes only its length k and evaluates every strategy
of it with its MIS weight, f_k(u) = Y(sum_s w_{s,t} C_{s,t}(u)) (the narrower form of
the issue's "at least the path length"; u_c is then unused).  ``multiplex="auto"``
(the default) takes "length" where the bootstrap's cells of the chains' lengths have
an effective sample size of at least EASY_ESS x its samples, else "strategy"
(``_choose_multiplex``).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from . import pss
from .backend import device_array
from .chain_strategies import ChainStrategies  # noqa: F401  (mmlt.ChainStrategies)
from .mlt import (BOOTSTRAP_LANES, DIRECT_LENGTH, DIRECT_SHARE, ESS_STOP,  # noqa: F401
                  MIN_BOOTSTRAP, MIN_DIRECT_LANES, MMLT_LARGE_STEP, Chains,
                  DirectLuminance, Evaluation, MLTRenderer, chains_for_ess)
from .optimizer import luminance

# multiplex="auto" (``_choose_multiplex``): "length" where the effective sample size
# (sum L)^2 / sum L^2 of the bootstrap's cells (k, s) of the chains' lengths is at
# least EASY_ESS x its samples: most samples carry the chains' light in several
# strategies, and a chain that evaluates every strategy of its length renders a
# sample's whole contribution of that length; else "strategy", whose walks stop at
# its vertices (half the cost) and whose chains stay on the strategy that carries a
# rare path.  Bootstraps of 64x64 renders, seed 1 (2026-11-27): the diffuse box 1.52
# (past its direct lengths), the door ajar's 0.05 gap 0.19, its 0.01 gap 0.009.  The
# box at 60 iterations (65536 chains, seeds 1-3): relMSE 0.00325 (strategy) against
# 0.00174 (length), for 1.4x the time per iteration; the door's 0.05 gap (before the
# film steps) 0.059 against 0.052 for 2x the time per mutation (benchmarks/RESULTS.md).
EASY_ESS = 0.5


def _per_depth(values: np.ndarray) -> mi.Float:
    """Values per path length 1, 2, ..., gathered by length: 0 first (length 0)."""
    return device_array(mi.Float, np.append(0.0, values).astype(np.float32))


class StrategyLuminance(DirectLuminance):
    """A stand-in for strategies.StrategyImages (``ctx.images``): per lane, the
    luminance of each strategy's MIS-weighted contribution, in cells (k, s) for
    k = 1 .. K, s = 0 .. k (cell (k(k+1) - 2) / 2 + s; CELLS(K) in all), and the
    records of the direct lengths (DirectLuminance)."""

    def __init__(self, lanes: int, max_depth: int):
        super().__init__(lanes)
        self.cells = cells(max_depth)
        self.max_depth = max_depth
        self.values = dr.zeros(mi.Float, lanes * self.cells)     # the target's (weighted)
        self.plain = dr.zeros(mi.Float, lanes * self.cells)      # luminance alone

    def add(self, lane, s, t, value, pos=None) -> None:
        super().add(lane, s, t, value, pos)
        k = mi.UInt32(s) + t - 1
        y = luminance(value)
        active = (k >= 1) & (k <= self.max_depth) & (y != 0.0)
        index = mi.UInt32(lane) * self.cells + (k * (k + 1) - 2) // 2 + s
        dr.scatter_add(self.plain, y, index, active)
        if self.weight_at is not None:          # two-stage: the pixel's 1 / L
            y = y * (dr.gather(mi.Float, self.camera_weight, mi.UInt32(lane))
                     if pos is None else self.weight_at(pos))
        dr.scatter_add(self.values, y, index, active)


def cells(max_depth: int) -> int:
    """Strategies (k, s) of lengths 1 .. max_depth: sum of k + 1."""
    return max_depth * (max_depth + 3) // 2


def cell_table(max_depth: int) -> tuple[np.ndarray, np.ndarray]:
    """(k, s) of every cell, in StrategyLuminance's order."""
    ks = [(k, s) for k in range(1, max_depth + 1) for s in range(k + 1)]
    return np.array([k for k, _ in ks]), np.array([s for _, s in ks])


def techniques(k: mi.UInt32, u: mi.Float):
    """(s, t, k + 1) of the strategy that ``u`` picks among the k + 1 of length k."""
    count = k + 1
    s = dr.minimum(mi.UInt32(u * mi.Float(count)), k)
    return s, count - s, count


@dataclass
class MultiplexedChains(Chains):
    """Chains with their path length, strategy number and scale c_k (see the module)."""
    tech_u: mi.Float = None     # the strategy stream (one number per chain)
    depth: mi.UInt32 = None     # k
    scale: mi.Float = None      # c_k = b_k N / n_k
    b_depth: mi.Float = None    # b_k

    def vectors(self) -> dict:
        return {"camera_u": self.camera_u, "light_u": self.light_u, "tech_u": self.tech_u}


class MMLTRenderer(MLTRenderer):
    """MMLT of one sensor (see the module; the interface is MLTRenderer's)."""

    name = "mlt"

    def __init__(self, scene: mi.Scene, sensor=0, seed: int = 0, **params):
        self.b_depths, self.b_plain, self.chains_per_depth = None, None, None
        self.multiplex_ess = 0.0        # _choose_multiplex's measure
        super().__init__(scene, sensor=sensor, seed=seed, **params)

    def _configure(self) -> None:
        if self.settings.max_depth < 1:
            raise ValueError("mlt: needs a finite max_depth >= 1 (MMLT runs its chains "
                             "per path length; pbrt's default is 5), or use pssmlt")
        self.dims["tech_u"] = 1
        # large_step_probability -1: the multiplex's (mlt.MMLT_LARGE_STEP), set with
        # the multiplex (``_choose_multiplex``); "strategy"'s until then
        self.large_step_auto = self.p_large < 0.0
        if self.large_step_auto:
            self.p_large = MMLT_LARGE_STEP.get(self.multiplex, MMLT_LARGE_STEP["strategy"])


    def _evaluate_vectors(self, lanes: int, keys, identity: mi.UInt32, x: dict) -> Evaluation:
        """With the strategies set per lane (``set_lanes``): each lane's strategy
        sample, its records and target times k + 1 (``self.count``); without: a full
        BDPT sample (the bootstrap)."""
        ev = super()._evaluate_vectors(lanes, keys, identity, x)
        if self.strategies.s is None:           # full samples, or a length per lane
            return ev
        scale = mi.Float(self.count)
        ev.camera.value *= scale
        if dr.width(ev.splats.lane):
            ev.splats.value *= dr.gather(mi.Float, scale, ev.splats.lane)
        ev.f = ev.f * scale
        dr.eval(ev.f, ev.camera.value, ev.splats.value)
        return ev

    def _evaluate_chains(self, keys, identity, x: dict, depth: mi.UInt32) -> Evaluation:
        """The strategy samples of the chains' states ``x`` of lengths ``depth`` (with
        ``multiplex="length"``: all strategies of that length, u_c unused)."""
        if self.multiplex == "length":
            self.strategies.set_lengths(depth)
        else:
            s, t, self.count = techniques(depth, x["tech_u"])
            self.strategies.set_lanes(s, t)
        return self._evaluate_vectors(self.chains, keys, identity, x)

    def bootstrap(self):
        """b_k per path length from full BDPT samples (their strategies' luminances
        summed per k: Rao-Blackwellized over the strategy stream), b = sum b_k, the
        direct samples' plan (``_separate_direct``) and the chains' first states
        (``_start``) on the lengths the chains render."""
        if self.emitters.count == 0:            # black (support.check warned)
            return 0.0, None
        if self.two_stage:
            self.pixel_weight = self._first_stage()
        keys = self._stream_keys(0xB0)
        targets, (self.b_depths, self.b_plain), self.bootstrap_samples = \
            self._bootstrap_targets(keys, self.bootstrap_samples)
        b = float(self.b_plain.sum())           # the image's luminance, and its direct part
        if b <= 0.0 or self.b_depths.sum() <= 0.0:
            return 0.0, None
        self.b_direct = float(self.b_plain[:DIRECT_LENGTH].sum())
        separate = self._separate_direct(b)
        f_np, ess = targets[separate]
        self._choose_multiplex(ess)
        if separate:
            self.b_depths[:DIRECT_LENGTH] = 0.0
        b_chains = self.b_chains = float(self.b_depths.sum())
        if self.automatic_chains:       # the effective sample size of the cells (k, s, u)
            self.chains = chains_for_ess(self.chains, ess)
            self.iterations = max(1, round(self.mutations / self.chains))
        self.direct_lanes = self._direct_lanes(b) if separate else 0
        if b_chains <= 0.0:                     # direct light only
            return b, None
        return b, self._start(keys, self._resample(f_np))

    def _choose_multiplex(self, ess: float) -> None:
        """``multiplex="auto"``: "length" where ``ess``, the effective sample size of
        the bootstrap's strategy cells of the chains' lengths, is at least EASY_ESS x
        its samples, else "strategy" (EASY_ESS); and an automatic large-step
        probability, the multiplex's (mlt.MMLT_LARGE_STEP).  Before the start states,
        whose cells are the chosen multiplex's; the seed's bootstrap decides (no
        clock)."""
        self.multiplex_ess = ess / max(self.bootstrap_samples, 1)
        if self.multiplex == "auto":
            self.multiplex = "length" if self.multiplex_ess >= EASY_ESS else "strategy"
        if self.large_step_auto:
            self.p_large = MMLT_LARGE_STEP[self.multiplex]

    def _bootstrap_targets(self, keys, count: int):
        """Per bootstrap sample 0 .. n - 1 (every coordinate hashed), with and without
        the lengths 1 .. DIRECT_LENGTH (``[separate]``): its strategies' target summed,
        f, and the effective sample size of their luminances, (sum L)^2 / sum L^2 over
        the cells (k, s) of samples (the start states are cells; it is at least that of
        f, whose cross terms it lacks; the luminance's, not the two-stage target's, as
        the automatic chains were measured with); the mean per path length of the
        target, b_k, and of the luminance; and n, the samples drawn: ``count``, or
        (automatic bootstrap) fewer where both effective sizes reach ESS_STOP x the
        planned chains first (``_enough``)."""
        self.strategies.set_lanes(None, None)
        depths = self.settings.max_depth
        f_all, sums, plain = ([], []), np.zeros(depths), np.zeros(depths)
        totals, squares = np.zeros(2), np.zeros(2)
        batch = max(self.chains, BOOTSTRAP_LANES)
        k_of, _ = self._cell_table()
        # the cells of the longer lengths: a suffix (cells ascend in k).  Sums in float64
        # over float32 views: copies of lanes x cells in float64 (and a boolean mask's
        # copies) took 0.5 s a batch of 262144 lanes, half of the bootstrap's time
        far = int(np.searchsorted(k_of, DIRECT_LENGTH, side="right"))
        done = 0
        while done < count and not (done and self._enough(done, totals, squares)):
            n = min(batch, count - done)
            ident = dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, done)
            self.images = StrategyLuminance(n, depths)
            ev = self._evaluate_vectors(n, keys, ident, {name: None for name in self.dims})
            self._put_direct(ev)
            per_cell, lum = self._cells(n), self._cells(n, "plain")
            sums += np.bincount(k_of - 1, weights=per_cell.sum(axis=0, dtype=np.float64),
                                minlength=depths)
            plain += np.bincount(k_of - 1, weights=lum.sum(axis=0, dtype=np.float64),
                                 minlength=depths)
            for j, first in enumerate((0, far)):
                part = lum[:, first:]
                totals[j] += float(part.sum(dtype=np.float64))
                squares[j] += float(np.einsum("ij,ij->", part, part, dtype=np.float64))
                f_all[j].append(per_cell[:, first:].sum(axis=1, dtype=np.float64))
            done += n
        self.images = None
        ess = [totals[j] ** 2 / squares[j] if squares[j] > 0.0 else 0.0 for j in range(2)]
        targets = [(np.concatenate(f_all[j]), ess[j]) for j in range(2)]
        return targets, (sums / done, plain / done), done

    def _enough(self, done: int, totals, squares) -> bool:
        """Whether an automatic bootstrap of ``done`` samples (at least MIN_BOOTSTRAP)
        may stop: the effective sample size of its cells, with and without the direct
        lengths (``totals`` and ``squares`` of their luminances), is at least ESS_STOP x
        the planned chains (each chain can start on a state of its own; mlt.ESS_STOP)."""
        if not self.automatic_bootstrap or done < MIN_BOOTSTRAP:
            return False
        return all(square > 0.0 and total * total / square >= ESS_STOP * self.chains
                   for total, square in zip(totals, squares))

    def _cell_table(self):
        """(k, s) of the start states' cells: a strategy each, or (``multiplex="length"``)
        a length each (s = 0); a strategy each in the bootstrap of ``"auto"``, which
        is chosen from them (``_choose_multiplex``)."""
        depths = self.settings.max_depth
        if self.multiplex == "length":
            return np.arange(1, depths + 1), np.zeros(depths, dtype=int)
        return cell_table(depths)

    def _cells(self, n: int, which: str = "values") -> np.ndarray:
        """The last evaluation's StrategyLuminance (its target's ``values`` or the
        ``plain`` luminance) as lanes x cells (``_cell_table``), float32, finite."""
        per_cell = getattr(self.images, which).numpy().reshape(n, -1)
        bad = ~np.isfinite(per_cell)
        if bad.any():
            per_cell = np.where(bad, np.float32(0.0), per_cell)
        if self.multiplex == "length":
            k_of, _ = cell_table(self.settings.max_depth)
            per_cell = np.add.reduceat(per_cell, np.flatnonzero(np.diff(k_of, prepend=0)), axis=1)
        return per_cell

    def _start(self, keys, pick: mi.UInt32) -> MultiplexedChains:
        """Each chain's first state: the picked bootstrap sample's vectors, and a
        strategy (k, s) of it drawn in proportion to its luminance, with u_c uniform
        in s's interval [s, s + 1) / (k + 1).  That is resampling in proportion to the
        target over (k, u_c, u) (the cell (k, s) of u has mass Y(w C_{s,t}(u))).
        Chains are then sorted by k, then s (SIMD packets of like lengths)."""
        depths, n = self.settings.max_depth, self.chains
        x = {name: pss.hashed_vectors(key, pick, self.dims[name])
             for name, key in zip(("camera_u", "light_u"), keys)}
        dr.eval(x)
        self.strategies.set_lanes(None, None)
        self.images = StrategyLuminance(n, depths)
        self._evaluate_vectors(n, keys, pick, x)
        per_cell = self._cells(n).astype(np.float64)
        self.images = None
        k_of, s_of = self._cell_table()
        if self.direct_lanes:                   # those lengths: the direct samples'
            per_cell[:, k_of <= DIRECT_LENGTH] = 0.0
        cum = np.cumsum(per_cell, axis=1)
        chain = dr.arange(mi.UInt32, n)
        u = pss.hash_uniform(self._key(0xB2), chain, 0).numpy() * cum[:, -1]
        cell = np.minimum((cum <= u[:, None]).sum(axis=1), per_cell.shape[1] - 1)
        order = np.lexsort((s_of[cell], k_of[cell]))
        k, s = k_of[cell][order], s_of[cell][order]
        jitter = pss.hash_uniform(self._key(0xB2), chain, 1).numpy()
        tech = np.minimum((s + jitter) / (k + 1), 0.99999994).astype(np.float32)
        order_dr = device_array(mi.UInt32, order.astype(np.uint32))
        pick = dr.gather(mi.UInt32, pick, order_dr)
        x = {name: pss.hashed_vectors(key, pick, self.dims[name])
             for name, key in zip(("camera_u", "light_u"), keys)}
        x["tech_u"] = device_array(mi.Float, tech)
        depth = device_array(mi.UInt32, k.astype(np.uint32))
        self.chains_per_depth = np.bincount(k, minlength=depths + 1)[1:]
        n_k = self.chains_per_depth
        c_k = np.where(n_k > 0, self.b_depths * n / np.maximum(n_k, 1), 0.0)
        dr.eval(x, depth)
        ev = self._evaluate_chains(keys, pick, x, depth)
        return MultiplexedChains(
            f=ev.f, camera=ev.camera, splats=ev.splats, depth=depth,
            scale=dr.gather(mi.Float, _per_depth(c_k), depth),
            b_depth=dr.gather(mi.Float, _per_depth(self.b_depths), depth), **x)

    def _evaluate_proposal(self, keys, identity, y: dict) -> Evaluation:
        return self._evaluate_chains(keys, identity, y, self.state.depth)

    def _record_weights(self, x, ev, a, large):
        p_mis = self.p_large if self.large_step_mis else 0.0
        return pss.expected_value_weights(x.f, ev.f, a, x.scale, large,
                                          dr.opaque(mi.Float, p_mis), x.b_depth)

    def result(self):
        res = super().result()
        res.stats["multiplex"] = self.multiplex
        res.stats["multiplex_ess"] = self.multiplex_ess
        if self.chains_per_depth is not None:
            res.stats["b_depths"] = [float(v) for v in self.b_depths]
            res.stats["b_luminance_depths"] = [float(v) for v in self.b_plain]
            res.stats["chains_per_depth"] = [int(v) for v in self.chains_per_depth]
        return res


def render(scene, seed: int = 0, sensor=0, **params):
    """Render ``scene`` with MMLT (``params``: mlt.MLT_PARAMS and max_depth, rr_depth,
    mis, light_image, hide_emitters; max_depth must be finite)."""
    r = MMLTRenderer(scene, sensor=sensor, seed=seed, **params)
    while not r.done:
        r.run_iteration()
    return r.result()
