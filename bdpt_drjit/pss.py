"""Primary sample space (Kelemen et al. 2002): the engine's random numbers read from a
stored vector per Markov chain instead of drawn by an ``mi.Sampler``.

A path sample of the walks is a deterministic function of the numbers its samplers
hand out, in the order they are asked for (camera.py, walk.DepthSamples, media.py).
``PSSSampler`` hands out coordinate ``dim`` of its lane's vector, so a chain's state
is its vector u in [0,1)^D per stream, as in pbrt-v3's MLTSampler (one stream for
the camera subpath, one for the light subpath: each subpath keeps its coordinates
whatever the other's length).

* Fixed dimension budget, eager mutation: each stream stores D coordinates per chain
  (``values``: a flat Float of chains x D, row per chain), and every proposal mutates
  all D of them (``propose``).  Coordinates past D (deep paths) are fresh numbers on
  every evaluation, hashed from (key, identity, dim): an independence proposal on
  those coordinates, which is symmetric too, so the Metropolis-Hastings acceptance
  min(1, f(y)/f(x)) stays exact (Veach 1997, eq. 11.4 with T(x->y) = T(y->x)); it
  only mixes less well where paths are longer than the budget.  Lazy mutation
  (pbrt-v3's per-coordinate ``lastModificationIteration``) is not done.
* A sampler without ``values`` (the bootstrap) hashes every coordinate: sample
  ``identity`` of key k has u_d = hash(k, identity, d), so a chosen bootstrap
  sample's vector is rebuilt exactly by ``hashed_vectors``.

The sampler is loop state of the walks' ``dr.while_loop``: a dataclass whose array
field, the per-lane counter ``dim`` (UInt32), Dr.Jit traverses as loop state.  Dr.Jit
rebuilds the dataclass inside the loop from its fields, so attributes set on an
instance are lost there (seen: AttributeError in the body); the stored vector and
keys travel in a plain Python object (``_Source``) in the other field, which Dr.Jit
passes by reference, and are read by gathers inside the loop.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

# Kelemen et al. 2002, sec. 3.1 (and Mitsuba 0.6's pssmlt): a small step moves a
# coordinate by s2 exp(-log(s2/s1) v), v uniform, in a random direction, wrapped
# around [0,1): an exponential distribution of step sizes between s1 and s2.
S1, S2 = 1.0 / 1024.0, 1.0 / 64.0
# The film position (a camera stream's first two coordinates) takes wider steps, from
# FILM_S1_PIXELS pixels to FILM_S2 of the image's side, log-uniform as Kelemen's (the
# range of Veach's lens perturbation, 1997 sec. 11.4.3, starts at 0.1 pixel too): a
# chain then moves over the image, where the pixel is a weak constraint on the path
# (a connection from the first camera vertex usually survives a move of a few
# pixels).  MMLT on door-ajar.xml 64x64 (16384 chains, 1M bootstrap samples, seeds
# 1-3, median relMSE at a fixed number of iterations, the same cost): 0.01 gap 0.243
# -> 0.185, 0.05 gap 0.0485 -> 0.032; the diffuse box 0.0098 -> 0.0071; PSSMLT 0.01
# gap 0.331 -> 0.247 (benchmarks/RESULTS.md).  s2 of 0.025 / 0.1 / 0.178 of the side
# gave 0.204 / 0.198 / 0.217 on the 0.01 gap, s1 of 0.01 / 1 pixel 0.226 / 0.268.
FILM_S1_PIXELS, FILM_S2 = 0.1, 0.05
# Finer small steps where Kelemen's are mostly rejected: s1 = FINE_S1 instead of S1
# (s2 kept) when Kelemen's steps from the chains' start states are accepted less than
# FINE_BELOW, the acceptance that is optimal for random-walk Metropolis in many
# dimensions (Roberts, Gelman and Gilks 1997).  MMLT, fixed iterations, relMSE, fine
# steps on the camera and light numbers (benchmarks/RESULTS.md): door-ajar.xml's 0.01
# gap (16384 chains, 600 iterations; Kelemen's accepted 6.5%) 0.120 -> 0.100, s1 of
# 1/65536 and 1/262144 no better; the diffuse box (65536 chains, 20 iterations;
# accepted 79%) 0.0072 -> 0.0076, hence the switch.
FINE_S1, FINE_BELOW = 1.0 / 16384.0, 0.234
_ONE_MINUS_EPS = 0.99999994
_GOLDEN = 0x9E3779B9


def _mix(x: mi.UInt32) -> mi.UInt32:
    """A 32-bit integer hash with full avalanche (Wellons' lowbias32)."""
    x = x ^ (x >> 16)
    x = x * 0x7FEB352D
    x = x ^ (x >> 15)
    x = x * 0x846CA68B
    return x ^ (x >> 16)


def hash_bits(key, identity, dim) -> mi.UInt32:
    """32 random bits from (key, identity, dim): two rounds of lowbias32.  TEA with 8
    rounds (Zafar et al. 2010) was the first choice; it made proposing 16384 chains x
    157 numbers take 30 ms, half of an iteration on the door scene (2 cores)."""
    return _mix(_mix(mi.UInt32(key) ^ (mi.UInt32(dim) * _GOLDEN)) ^ mi.UInt32(identity))


def hash_uniform(key, identity, dim) -> mi.Float:
    """A number in [0,1) (24 bits) from (key, identity, dim)."""
    return mi.Float(hash_bits(key, identity, dim) >> 8) * (1.0 / (1 << 24))


def wrap(x: mi.Float) -> mi.Float:
    """x mod 1, in [0,1) (a step moves less than 1/2, so one correction suffices)."""
    x = dr.select(x < 0.0, x + 1.0, x)
    x = dr.select(x >= 1.0, x - 1.0, x)
    return dr.clip(x, 0.0, _ONE_MINUS_EPS)


def small_step(x: mi.Float, u_size: mi.Float, u_sign: mi.Float, s1=S1, s2=S2) -> mi.Float:
    """Kelemen's small step of one coordinate (symmetric: T(x->y) = T(y->x))."""
    return _step(x, u_size, u_sign, s2, dr.log(s2 / s1))


def _step(x: mi.Float, u_size: mi.Float, u_sign: mi.Float, s2, log_ratio) -> mi.Float:
    """``small_step`` with log(s2 / s1) given: where s1 and s2 are the same for all
    lanes the logarithm is one per kernel, not one per coordinate (exp alone remains,
    in a kernel over chains x dims numbers)."""
    dv = s2 * dr.exp(-log_ratio * u_size)
    return wrap(dr.select(u_sign < 0.5, x + dv, x - dv))


def propose(x: mi.Float, dims: int, large: mi.Bool, key, film=None, s1=S1) -> mi.Float:
    """The proposal y of every chain's vector (``x``: chains x dims, row per chain):
    a large step (``large``, per chain) redraws every coordinate uniformly, a small
    step moves each (eager: all ``dims`` of them).  ``key`` (opaque UInt32) keys this
    iteration's numbers.  ``film`` (s1, s2), opaque Floats: the step sizes of each
    row's first two coordinates, the film position (``film_steps``).  ``s1``: the
    other coordinates' smallest step (S1, or FINE_S1: ``fine_steps``)."""
    n = dr.width(x)
    element = dr.arange(mi.UInt32, n)
    # dims a literal (fixed by max_depth, not per seed): LLVM divides by a constant
    # with a multiply and shift; an opaque divisor was a per-lane division (the
    # proposals and acceptances over chains x dims numbers were a third of an iteration)
    chain_large = dr.gather(mi.Bool, large, element // dims)
    bits = hash_bits(key, element, 0)
    u = mi.Float(bits >> 8) * (1.0 / (1 << 24))
    u_sign = dr.select((bits & 1) == 0, 0.0, 1.0)      # a bit apart from u's 24
    # log(s2 / s1) of the two kinds of coordinate, each of width 1, chosen per
    # coordinate: a per-coordinate log was a third of the proposal kernel's time
    log_ratio = dr.log(S2 / mi.Float(s1))
    dr.make_opaque(log_ratio)
    if film is None:
        return dr.select(chain_large, u, _step(x, u, u_sign, S2, log_ratio))
    on_film = (element % dims) < 2
    s2 = dr.select(on_film, film[1], S2)
    log_film = dr.log(film[1] / film[0])
    dr.make_opaque(log_film)
    log_ratio = dr.select(on_film, log_film, log_ratio)
    return dr.select(chain_large, u, _step(x, u, u_sign, s2, log_ratio))


def fine_steps(acceptance: float) -> float:
    """s1 of the coordinates off the film for chains whose Kelemen small steps are
    accepted at the rate ``acceptance`` (FINE_S1, FINE_BELOW)."""
    return FINE_S1 if acceptance < FINE_BELOW else S1


def film_steps(resolution: int) -> tuple:
    """(s1, s2) of the film position's small steps on a film of ``resolution`` pixels
    on its longer side (FILM_S1_PIXELS, FILM_S2), opaque: a resolution compiles no
    kernel of its own."""
    s1 = min(FILM_S1_PIXELS / max(resolution, 1), 0.5 * FILM_S2)
    return dr.opaque(mi.Float, s1), dr.opaque(mi.Float, FILM_S2)


def hashed_vectors(key, identity: mi.UInt32, dims: int) -> mi.Float:
    """The first ``dims`` coordinates that a hashing sampler (no ``values``) of key
    ``key`` gives lane ``identity``: chains x dims, row per entry of ``identity``."""
    n = dr.width(identity) * dims
    element = dr.arange(mi.UInt32, n)
    return hash_uniform(key, dr.gather(mi.UInt32, identity, element // dims), element % dims)


class _Source:
    """What a sampler reads, outside the loop state (a plain object: Dr.Jit copies the
    reference when it rebuilds the dataclass inside a loop)."""

    def __init__(self, lanes, key, identity, values, dims):
        self.key, self.identity, self.values, self.dims = key, identity, values, dims
        self.opaque_dims = dr.opaque(mi.UInt32, dims)
        self.row = dr.arange(mi.UInt32, lanes) * self.opaque_dims
        if values is not None:
            dr.eval(values)


@dataclass
class PSSSampler:
    """A stand-in for ``mi.Sampler`` reading primary samples (see the module).  Only
    ``dim`` is loop state."""
    dim: mi.UInt32
    source: _Source

    @staticmethod
    def make(lanes: int, key, identity: mi.UInt32, values: mi.Float | None = None,
             dims: int = 0) -> "PSSSampler":
        """Lane i reads row i of ``values`` (chains x ``dims``) for its first
        ``dims`` coordinates and hash(key, identity[i], dim) past them."""
        return PSSSampler(dim=dr.zeros(mi.UInt32, lanes),
                          source=_Source(lanes, key, identity, values, dims))

    def next_1d(self, active=True) -> mi.Float:
        src, d = self.source, self.dim
        fresh = hash_uniform(src.key, src.identity, d)
        if src.values is not None and src.dims > 0:
            stored_dim = d < src.opaque_dims
            stored = dr.gather(mi.Float, src.values, src.row + d, stored_dim)
            fresh = dr.select(stored_dim, stored, fresh)
        self.dim = d + 1
        return fresh

    def next_2d(self, active=True) -> mi.Point2f:
        u = self.next_1d(active)
        return mi.Point2f(u, self.next_1d(active))

    def schedule_state(self) -> None:
        """mi.Sampler's call before an evaluation: nothing to schedule here."""


# -- Metropolis-Hastings on primary samples ----------------------------------------------
def acceptance(fx: mi.Float, fy: mi.Float) -> mi.Float:
    """a(x -> y) = min(1, f(y) / f(x)) for a symmetric proposal (Veach 1997, eq. 11.4;
    Kelemen 2002, eq. 6); a state of f(x) = 0 (none after the bootstrap's resampling,
    unless the image is black) accepts anything."""
    a = dr.select(fx > 0.0, dr.minimum(fy / fx, 1.0), 1.0)
    return dr.select(fy > 0.0, a, 0.0)


def expected_value_weights(fx: mi.Float, fy: mi.Float, a: mi.Float, b, large=False,
                           p_large=0.0, b_large=None):
    """The record weights of both states, b included: Veach's expected-value splatting
    (1997, sec. 11.3.3) records the proposal with a b / f(y) and the current state
    with (1 - a) b / f(x).  With ``p_large`` > 0, Kelemen's multiple importance
    sampling of large steps (2002, sec. 4): a large-step proposal is also an
    independent uniform sample, so each record is weighted by the balance heuristic
    over the chain's density f / b and the large steps' density p_large: the proposal
    with (a + [large]) / (f(y) / b + p_large), the state with (1 - a) / (f(x) / b +
    p_large); dark regions then get the large steps' samples at their own rate.

    MMLT (mmlt.py) passes per chain b = c_k = b_k N / n_k, the scale of a chain of
    path length k (n_k of the N chains), and ``b_large`` = b_k: there the chains'
    density is f / c_k and the large steps' p_large b_k / c_k (both per chain and
    iteration, in the space of (k, u)), so the balance heuristic's denominator
    becomes f + p_large b_k."""
    pb = (b if b_large is None else b_large) * p_large
    on = dr.select(mi.Bool(large) & (mi.Float(p_large) > 0.0), 1.0, 0.0)
    dy, dx = fy + pb, fx + pb
    wy = dr.select(dy > 0.0, b * (a + on) / dr.maximum(dy, 1e-30), 0.0)
    wx = dr.select(dx > 0.0, b * (1.0 - a) / dr.maximum(dx, 1e-30), 0.0)
    return wy, wx
