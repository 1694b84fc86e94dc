"""Primary sample space Metropolis light transport (PSSMLT) over the wavefront BDPT:
thousands of Markov chains, one per lane.

    first stage      (``mlt``, two-stage) the image's brightness L per 8x8 block
                     (smaller where its samples allow: stage_block) from samples
                     of their own: the chains' target is f / L
    bootstrap        B independent BDPT samples (hashed primary samples, pss.py):
                     b = mean f, the image's normalization; chains start at
                     samples drawn in proportion to f (resampling)
    pilot            one small step of PILOT_CHAINS chains from their start states,
                     discarded: where Kelemen's sizes are accepted less than 0.234,
                     the small steps reach down to 1/16384 (pss.fine_steps)
    each iteration   propose y for every chain (large step with probability
                     p_large, else Kelemen small steps: pss.propose)
                     evaluate y: camera ray, light subpath, camera subpath with every
                     (s,t) strategy and its MIS weight: records (camera value, splats)
                     accept with a = min(1, f(y)/f(x)) per lane (masks)
                     splat y's records times a/f(y), x's times (1-a)/f(x) (Veach's
                     expected values, 1997 sec. 11.3.3)

The path sample of a primary sample u is a full BDPT sample (Mitsuba 0.6's
``pssmlt`` with its bidirectional option): the camera ray through the film position
u_0,u_1, the light subpath from the light stream, and every strategy of the pair with
its MIS weight.  Its records are the camera value at its film position and each
light-image splat at its own; the target is f(u) = Y(camera value) + sum of Y(splat
values) (Y the mean of the colour channels, optimizer.luminance).  With I_j the
image of pixel j and N the film's pixels, I_j = N E_u[sum of records in j], and
E_u[g] = b E_pi[g / f] with b = E_u[f] (Veach 1997, eq. 11.8; Kelemen 2002, eq. 9),
so each record is splatted times b N / (chains x iterations) over its state's f.
Every iteration adds weights a + (1 - a) = 1 per chain: the image's luminance sum is
b N at every iteration, the bootstrap's estimate.  With ``large_step_mis`` (the
default) large-step proposals also count as independent samples, weighted with the
chain's states by the balance heuristic (Kelemen 2002, sec. 4; pss.py): dark regions
get their noise from the large steps' rate instead of from rare chain visits, and the
sum is b N in expectation only.

Direct light apart (``direct_samples``, Mitsuba 0.6's ``directSamples``): where paths
of 1 and 2 edges carry at least DIRECT_SHARE of b, each iteration also renders
independent BDPT samples of only those lengths (ChainStrategies.set_lengths with
``up_to``) onto a film of their own, which also holds the bootstrap's records of those
lengths, and the chains' target f lacks them (``set_past``): the image is the sum of
the two estimates, whose expectations are the two parts of the image.

Chain state stays in Dr.Jit arrays (``Chains``): the two streams' vectors, f(x), the
camera record and the current state's splats (a list compacted each iteration).
Every per-iteration value (keys, the large-step probability) is opaque: an iteration
compiles nothing after the first (tests/test_mlt.py).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, fields, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from . import camera as camera_stage
from . import frozen, pss, support
from .backend import device_array
from .budgets import BDPT
from .chain_strategies import ChainStrategies
from .emitters import Emitters
from .film import FilmAccumulator
from .media import Media
from .mis import Weights
from .optimizer import luminance
from .render import (PassContext, Renderer, RenderResult, _mix_seed, _recorded_camera_walk,
                     _recorded_light_walk, check_variant)
from .settings import Settings
from .strategies import StrategySet
from .vertices import LightVertexStore, gather

# An rgba film's alpha: the chains' records carry no coverage, so alpha is what the
# default bdpt's film holds (film.py: 1 where a camera ray reached an opaque surface),
# from this many path-traced samples per pixel of this engine (MLTRenderer._alpha).
ALPHA_SPP = 16
ALPHA_STREAM = 0xA1F4            # the alpha render's seed: _mix_seed(seed, ALPHA_STREAM)
ALPHA_CHANNEL = 3                # R, G, B, A (the RGB variants; others are refused)

# Depths whose numbers a chain stores (the dimension budget); deeper vertices draw
# fresh numbers each evaluation (pss.py).
STORED_DEPTHS = 12
# Numbers per depth of a walk (walk.DepthSamples), and before the first depth:
# camera: film position, aperture, time, wavelength (at most: the sensor's own count
# is CameraModel.film_ray_numbers); light: emitter, position, direction, lens sample
# of (1,1) (walk._light_start).  A walk of max_depth D runs at most D depths of the
# camera subpath and D - 1 of the light subpath (seen per chain as the samplers'
# counters: 2 + 6 D and 7 + 6 (D - 1) on a pinhole camera, full BDPT samples and
# MMLT chains alike), so the stored vectors end there: numbers never read cost a
# proposal and an acceptance each (54 + 55 per chain at D = 8 against 50 + 49).
PER_DEPTH, LIGHT_START = 6, 7
# mutations_per_pixel 0: the sensor's sample count; chains and bootstrap_samples 0:
# automatic.
MLT_PARAMS = {"mutations_per_pixel": 0, "large_step_probability": 0.3,
              "bootstrap_samples": 0, "chains": 0, "large_step_mis": True,
              "direct_samples": 0}
# MMLT's own (mmlt.py): what a chain fixes besides its path length: "strategy" (its
# (s, t) from a stream of its own, Hachisuka 2014, pbrt), "length" (every strategy
# of its length) or "auto" (mmlt.EASY_ESS: "length" where the bootstrap finds the
# chains' light spread over many strategies of most samples, the diffuse box; else
# "strategy"); and its default large-step probability, -1: automatic, by the
# multiplex (MMLT_LARGE_STEP).  With "strategy" 0.1 (pbrt's is 0.3): an MMLT large
# step is rarely accepted (door, 0.05 gap: 0.6%, PSSMLT's 10%), and at equal time 0.1
# gave 0.97x the default bdpt's relMSE on the door's 0.05 gap against 0.3's 1.20x,
# 0.82x against 0.96x on its 0.01 gap (2 runs each), the box 23.9x against 22.3x.
# With "length" 0.3 (Kelemen's, pbrt's): a chain's large step is a BDPT sample of its
# length, accepted 31% of the time on the diffuse box (strategy: 11%), where 0.3
# against 0.1 gave relMSE 0.00143 against 0.00158 (seeds 1-3) and 0.00141 against
# 0.00152 (seeds 4-6) at 60 iterations of 65536 chains (benchmarks/RESULTS.md).
MMLT_PARAMS = {"multiplex": "auto", "large_step_probability": -1.0, "two_stage": True}
MULTIPLEX = ("strategy", "length", "auto")
MMLT_LARGE_STEP = {"strategy": 0.1, "length": 0.3}
# Automatic chains and bootstrap (automatic_plan).  The image's error is mostly the
# chains' start: a chain forgets its bootstrap state only through accepted large steps
# (door-ajar.xml: large steps accepted 10%, small steps 51%; about one large step
# accepted in 32 iterations), so independent chains and distinct start states count
# more than a chain's length.  door-ajar.xml 64x64, 256 mutations per pixel (1M),
# relMSE: 16384 chains from 512K bootstrap samples 0.051; 65536 from 512K 0.040, from
# 2M 0.031; 262144 from 1M 0.030, from 2M 0.019, from 4M 0.015 (benchmarks/RESULTS.md).
# Hence short chains (CHAIN_MUTATIONS iterations when the mutations allow) and a
# bootstrap of BOOTSTRAP_PER_CHAIN samples per chain, a third of the evaluations of a
# render of the planned mutations.  Too few bootstrap samples per chain start chains on
# the same states where f is heavy-tailed (door-ajar.xml with a 0.01 gap: 16384 chains
# from 100000 samples started on 1225 distinct states).
# Where f is heavy-tailed, more chains than the bootstrap has distinct states to start
# on only repeat them: automatic chains are also at most ESS_CHAINS x the bootstrap's
# effective sample size (chains_for_bootstrap).  door-ajar.xml with a 0.01 gap (1.3% of
# samples nonzero, E[f^2] / E[f]^2 = 199: 10.5K effective of 2M), 1024 mutations per
# pixel from 2M bootstrap samples, relMSE 0.35 / 0.23 / 0.18 with 262144 / 65536 / 16384
# chains; with the 0.05 gap (E[f^2] / E[f]^2 = 11.7: 179K of 2M) 524288 / 262144 /
# 131072 chains gave 0.018 / 0.019 / 0.024 at 256 mutations per pixel.
CHAIN_MUTATIONS = 16
BOOTSTRAP_PER_CHAIN = 8
MAX_CHAINS = 1 << 18
MIN_BOOTSTRAP = 100000
MIN_CHAINS = 4096
ESS_CHAINS = 2.0
# MMLT's automatic bootstrap stops after the batch where its cells' effective sample
# size reaches ESS_STOP x the planned chains (at least MIN_BOOTSTRAP samples; mmlt.py,
# MMLTRenderer._bootstrap_targets): every chain can start on a state of its own, and
# an easy scene does not pay for samples it does not need.  Diffuse box 64x64, 5 s,
# 65536 chains (the plan of 256 mutations per pixel), 3 interleaved runs: 524288
# samples (8 per chain) 4.18x the default bdpt's relMSE, 262144 3.07x, 131072 2.90x
# (benchmarks/RESULTS.md); the door's gaps never reach it.
ESS_STOP = 1.0
# The chains whose start states price Kelemen's small steps (MLTRenderer._pilot_steps;
# pss.fine_steps): a mean acceptance to about 0.01, at the cost of a few ms.
PILOT_CHAINS = 4096
BOOTSTRAP_LANES = 1 << 16       # lanes of a bootstrap batch (at least the chains)
# Two-stage MLT (``two_stage``, MMLT's default; Mitsuba 0.6's twoStage; Hoberock and
# Hart 2010, "Arbitrary importance functions for Metropolis light transport"): a first
# stage of independent samples (keys of their own), in batches of STAGE_LANES (then
# doubling: the stop is tested at STAGE_LANES x 1, 2, 4, ...) until
# their effective sample size (sum f)^2 / sum f^2 reaches STAGE_ESS or they number the
# planned chains (at least BOOTSTRAP_LANES; an eighth of an automatic bootstrap's
# plan), estimates the image's luminance L on blocks of STAGE_BLOCK x STAGE_BLOCK pixels,
# floored at STAGE_FLOOR x its mean, and the chains' target is f / L(record's pixel)
# (``_target``).  Any positive target gives the same image in expectation (records are
# weighted b / f); this one spends the chains' states evenly over the pixels instead of
# in proportion to their brightness, which is what a relative error asks for (MLT's
# relative variance in pixel j goes as 1 / L_j).  Where L_j spans a wide range (the
# door's 0.01 gap: mean(L) mean(1/L) = 1.6 on the reference) the dark pixels' error
# dominated (relMSE by brightness quartile, dark to bright, 0.121 / 0.057 / 0.051 /
# 0.018; with two-stage 0.099 / 0.049 / 0.050 / 0.028; benchmarks/RESULTS.md).
# The door's 0.01 gap (600 iterations, seeds 1-2) needs the planned chains' 262144
# (ESS ~1.4K): 65536 gave relMSE 0.064, 16384 0.078, 262144 0.055, 524288 0.055
# (without two-stage 0.065); the diffuse box stops after 16384 (ESS ~15K), where a
# stage of its 65536 planned chains cost a fifth of its iterations in 5 s.
# The blocks are smaller where the stage has the samples for them (``stage_block``):
# the smallest of STAGE_BLOCK, STAGE_BLOCK / 2, ..., 1 pixels whose blocks hold at
# least STAGE_PER_BLOCK effective samples on average (ESS x block^2 / pixels; 8x8
# blocks of a 64x64 film at STAGE_ESS).  The diffuse box's stage (16384 samples, ESS
# ~15K at 64x64) then has 4x4 blocks: relMSE at 60 iterations (65536 chains, seeds
# 1-3) 0.00180 -> 0.00158, where 4x4 blocks on the door's 0.01 gap (ESS ~1.4K) gave
# 0.0621 / 0.0627 against 8x8's 0.0562 / 0.0546; the door's stages keep 8x8.
STAGE_BLOCK, STAGE_FLOOR, STAGE_LANES, STAGE_ESS = 8, 0.1, 1 << 14, 2048
STAGE_PER_BLOCK = 32
BDPT_PARAMS = ("max_depth", "rr_depth", "mis", "light_image", "hide_emitters")
# Separate direct samples (``direct_samples``, MLTRenderer._separate_direct): paths of up to
# DIRECT_LENGTH edges (emitters seen directly, direct illumination) are rendered by
# independent BDPT samples of those lengths where they carry at least DIRECT_SHARE of
# the bootstrap's brightness, at least MIN_DIRECT_LANES per iteration (Mitsuba 0.6's
# pssmlt renders them apart by default too).  On the diffuse box 77% of the
# brightness is there (54% the lamp seen directly), which the chains spent their
# states on (an MMLT chain carries one strategy); on the door (0.05 gap: 5.6%, seen
# through the gap) separating them gave 1.07x the default bdpt's relMSE against 0.93x
# (benchmarks/RESULTS.md).
DIRECT_LENGTH = 2
DIRECT_SHARE = 0.25
MIN_DIRECT_LANES = 1024


@dataclass
class Records:
    """Image records of path samples: film position (crop pixels), value, chain."""
    pos: mi.Vector2f
    value: mi.Spectrum
    lane: mi.UInt32


@dataclass
class Evaluation:
    f: mi.Float          # the target of each lane's sample
    camera: Records      # one per lane
    splats: Records      # the light image's records
    rays: mi.Float64     # rays traced (one number, on the device: no host sync)


def _concat(a: Records, b: Records) -> Records:
    na, nb = dr.width(a.lane), dr.width(b.lane)
    out = Records(pos=dr.empty(mi.Vector2f, na + nb), value=dr.empty(mi.Spectrum, na + nb),
                  lane=dr.empty(mi.UInt32, na + nb))
    for part, offset in ((a, 0), (b, na)):
        if dr.width(part.lane):
            idx = dr.arange(mi.UInt32, dr.width(part.lane)) + dr.opaque(mi.UInt32, offset)
            dr.scatter(out.pos, part.pos, idx)
            dr.scatter(out.value, part.value, idx)
            dr.scatter(out.lane, part.lane, idx)
    return out


def _select_records(records: Records, keep: mi.Bool) -> Records:
    """The records where ``keep`` (compacted)."""
    if not dr.width(records.lane):
        return records
    idx = dr.compress(keep)
    return gather(records, idx) if dr.width(idx) else Records(
        pos=dr.zeros(mi.Vector2f, 0), value=dr.zeros(mi.Spectrum, 0), lane=dr.zeros(mi.UInt32, 0))


def _copy_rows(x: mi.Float, y: mi.Float, rows: mi.UInt32, dims: int) -> mi.Float:
    """x with its rows ``rows`` (``dims`` numbers each, row per chain) taken from y.
    ``dims`` is a literal (fixed by max_depth): the row and column of an element
    are a multiply and shift, as in pss.propose.  Dr.Jit copies x first where it is
    referenced elsewhere (a scatter writes in place, but keeps value semantics)."""
    if not dr.width(rows):
        return x
    element = dr.arange(mi.UInt32, dr.width(rows) * dims)
    index = dr.gather(mi.UInt32, rows, element // dims) * dims + element % dims
    dr.scatter(x, dr.gather(mi.Float, y, index), index)
    return x


class DirectLuminance:
    """A stand-in for strategies.StrategyImages (``ctx.images``) in the bootstrap: per
    lane, the luminance of the strategies of paths of 1 .. DIRECT_LENGTH edges
    (``y``), and their records: ``direct`` per lane (camera strategies, at the lane's
    film position) and ``direct_splats`` (the light image's, ``pos`` given), the
    bootstrap's samples of the direct image."""

    def __init__(self, lanes: int):
        self.y = dr.zeros(mi.Float, lanes)
        self.direct = dr.zeros(mi.Spectrum, lanes)
        self.direct_splats = None
        self.weight_at, self.camera_weight = None, 1.0

    def weigh(self, weight_at, camera_pos) -> None:
        """The target's pixel weights (MLTRenderer.weight_at): of the camera
        strategies' records at the lanes' film positions ``camera_pos``, of the light
        image's at theirs (StrategyLuminance)."""
        self.weight_at, self.camera_weight = weight_at, weight_at(camera_pos)

    def add(self, lane, s, t, value, pos=None) -> None:
        k = mi.UInt32(s) + t - 1
        direct = (k >= 1) & (k <= DIRECT_LENGTH)
        dr.scatter_add(self.y, luminance(value), mi.UInt32(lane), direct)
        if pos is None:                         # a camera strategy (t >= 2)
            dr.scatter_add(self.direct, value, mi.UInt32(lane), direct)
        else:                                   # the light image's records (t = 1)
            self.direct_splats = Records(pos=pos, value=dr.select(direct, value, 0.0),
                                         lane=mi.UInt32(lane))

    def add_layer(self, *args) -> None:
        raise NotImplementedError("mlt: no merging")


@dataclass
class Chains:
    """Every chain's current state x: its two primary sample vectors (chains x D), f(x)
    and its records."""
    camera_u: mi.Float
    light_u: mi.Float
    f: mi.Float
    camera: Records
    splats: Records

    def vectors(self) -> dict:
        """The chain's primary sample vectors by field name (chains x D each)."""
        return {"camera_u": self.camera_u, "light_u": self.light_u}

    def rows(self, rows: mi.UInt32, dims: dict) -> "Chains":
        """The chains ``rows``: their vectors (``dims`` coordinates each), f and other
        per-chain fields, without records (a pilot's states)."""
        out = {}
        for field in fields(self):
            v, d = getattr(self, field.name), dims.get(field.name)
            if d is not None:
                e = dr.arange(mi.UInt32, dr.width(rows) * d)
                v = dr.gather(type(v), v, dr.gather(mi.UInt32, rows, e // d) * d + e % d)
            elif isinstance(v, (mi.Float, mi.UInt32)):
                v = dr.gather(type(v), v, rows)
            else:
                v = None
            out[field.name] = v
        return replace(self, **out)

    def accept(self, accepted: mi.Bool, y: dict, ev: Evaluation, dims: dict) -> None:
        """x <- y where ``accepted`` (per chain; masks, no per-lane branches): ``y`` the
        proposal's vectors (as ``vectors()``), ``dims`` their coordinates per chain.
        The vectors are copied row by row for the accepted chains only: a select over
        every chain's coordinates cost as much as a proposal, and on hard scenes few
        proposals are accepted (the door's 0.01 gap: small steps 6.5-10%)."""
        rows = dr.compress(accepted)
        for name, vector in y.items():
            x = getattr(self, name)
            setattr(self, name, None)      # x's only reference: the scatter writes in place
            setattr(self, name, _copy_rows(x, vector, rows, dims[name]))
            del x
        self.f = dr.select(accepted, ev.f, self.f)
        self.camera = Records(pos=dr.select(accepted, ev.camera.pos, self.camera.pos),
                              value=dr.select(accepted, ev.camera.value, self.camera.value),
                              lane=self.camera.lane)
        kept = _select_records(self.splats, ~dr.gather(mi.Bool, accepted, self.splats.lane))
        taken = _select_records(ev.splats, dr.gather(mi.Bool, accepted, ev.splats.lane))
        self.splats = _concat(kept, taken)
        dr.eval(self.vectors(), self.f, self.camera, self.splats)


def automatic_plan(mutations: int, chains: int = 0, bootstrap: int = 0) -> tuple[int, int]:
    """(chains, bootstrap samples) for a render of ``mutations`` mutations; 0 is
    automatic: min(MAX_CHAINS, max(4096, mutations / CHAIN_MUTATIONS)) chains (fewer
    lanes cost more per mutation: 16.7 against 7.8 us at 4096 and 16384 chains), never
    more than the mutations, and max(MIN_BOOTSTRAP, BOOTSTRAP_PER_CHAIN x chains)
    bootstrap samples (see the constants)."""
    chains = min(chains or min(MAX_CHAINS, max(MIN_CHAINS, mutations // CHAIN_MUTATIONS)),
                 mutations)
    return chains, bootstrap or max(MIN_BOOTSTRAP, BOOTSTRAP_PER_CHAIN * chains)


def chains_for_bootstrap(planned: int, f: np.ndarray) -> int:
    """Automatic chains once the bootstrap's targets ``f`` are known: at most ESS_CHAINS
    x their effective sample size (sum f)^2 / sum f^2 (Kish's, of resampling in
    proportion to f), rounded down to a power of two, at least MIN_CHAINS (or
    ``planned`` where fewer).  The power of two: Dr.Jit's LLVM scatter-add into an
    array of the chains' width holds that width as a literal (a per-thread copy's
    offset), so that every count would compile its own kernels; seeds of one scene
    then share theirs."""
    f = f.astype(np.float64)
    square = float(np.dot(f, f))
    return chains_for_ess(planned, float(f.sum()) ** 2 / square if square > 0.0 else 0.0)


def chains_for_ess(planned: int, ess: float) -> int:
    """``chains_for_bootstrap`` of an effective sample size ``ess``."""
    cap = int(ESS_CHAINS * ess)
    cap = 1 << (cap.bit_length() - 1) if cap > 0 else 0
    return min(planned, max(MIN_CHAINS, cap))


def mlt_settings(values: dict, name: str = "pssmlt") -> tuple[dict, dict]:
    """(MLT parameters, BDPT settings) from keyword values; refuses the BDPT
    parameters that have no meaning for a chain's sample (budgets, techniques).
    ``name`` "mlt" (mmlt.py) also knows MMLT_PARAMS."""
    known = dict(MLT_PARAMS, **(MMLT_PARAMS if name == "mlt" else {}))
    mlt, bdpt = dict(known), {}
    for key, value in values.items():
        if key in known and isinstance(known[key], bool) and isinstance(value, str):
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError("%s: %s must be true or false, got %r" % (name, key, value))
            mlt[key] = value.lower() in ("true", "1")
        elif key in known:
            mlt[key] = type(known[key])(value)
        elif key in ("maxDepth", "rrDepth", "hideEmitters", "lightImage") or key in BDPT_PARAMS:
            bdpt[key] = value
        else:
            raise ValueError("%s: unknown or unsupported parameter '%s' (known: %s)"
                             % (name, key, ", ".join(list(known) + list(BDPT_PARAMS))))
    if mlt.get("multiplex", "strategy") not in MULTIPLEX:
        raise ValueError("%s: multiplex must be one of %s, got %r"
                         % (name, ", ".join(MULTIPLEX), mlt["multiplex"]))
    if mlt.get("direct_samples", 0) < -1:
        raise ValueError("%s: direct_samples must be >= -1 (-1: none, 0: automatic), got %d"
                         % (name, mlt["direct_samples"]))
    if min(mlt["mutations_per_pixel"], mlt["bootstrap_samples"], mlt["chains"]) < 0:
        raise ValueError("%s: mutations_per_pixel, bootstrap_samples and chains must be "
                         ">= 0 (0: the sample count; automatic)" % name)
    p_large = mlt["large_step_probability"]
    if not (0.0 <= p_large <= 1.0 or (name == "mlt" and p_large == -1.0)):
        raise ValueError("%s: large_step_probability must lie in [0, 1]%s, got %g"
                         % (name, " (-1: automatic)" if name == "mlt" else "", p_large))
    return mlt, bdpt


def _refuse(scene: mi.Scene, media: Media, settings: Settings, name: str) -> None:
    """What PSSMLT cannot render here, refused before anything is rendered."""
    if mi.is_spectral or mi.is_monochromatic:
        raise RuntimeError("%s: RGB variants only (got %s): a chain's records carry no "
                           "wavelengths" % (name, mi.variant()))
    if settings.mis == "lafortune":
        raise ValueError("%s: mis='lafortune' is refused: its weights have no light "
                         "image, use power or balance" % name)
    if media.present and any(not m.is_homogeneous() for m in media.all):
        raise support.UnsupportedPluginError(
            "%s: heterogeneous media are refused: ratio tracking's transmittance is "
            "keyed per pass, not by the primary sample, so f(u) would not be a function "
            "of u; render them with bdpt" % name)


class MLTRenderer:
    """PSSMLT of one sensor (see the module): ``bootstrap`` happens on construction,
    then call ``run_iteration`` until ``done``; ``result()`` develops the image."""

    def __init__(self, scene: mi.Scene, sensor=0, seed: int = 0, **params):
        check_variant()
        mlt, bdpt = mlt_settings(params, self.name)
        self.multiplex = mlt.get("multiplex")
        self.direct_samples = mlt["direct_samples"]
        self.sensor = camera_stage.select_sensor(scene, sensor)
        self.camera = camera_stage.make_camera(self.sensor)
        self.scene, self.seed = scene, int(seed)
        self.settings = Settings.from_dict({**bdpt, "light_paths": 1, "connections": "all"})
        support.check(scene, self.sensor)
        self.emitters = Emitters(scene)
        self.media = Media(scene, self.sensor)
        _refuse(scene, self.media, self.settings, self.name)
        base = StrategySet(self.settings, self.emitters.count > 0, BDPT,
                           self.camera.light_image_possible)
        self.weights = Weights(self.settings.mis, base)     # every strategy's weight
        self.strategies = ChainStrategies(base)             # per evaluation: which records
        self.weights.set_rates(1.0, 1.0)
        film = self.sensor.film()
        self.pixels = int(dr.prod(film.crop_size()))
        self.film = FilmAccumulator(film, coalesce=False)
        self.p_large = mlt["large_step_probability"]
        self.large_step_mis = mlt["large_step_mis"]
        mpp = mlt["mutations_per_pixel"] or self.sensor.sampler().sample_count()
        self.mutations = mpp * self.pixels
        self.chains, self.bootstrap_samples = automatic_plan(
            self.mutations, mlt["chains"], mlt["bootstrap_samples"])
        self.automatic_chains = mlt["chains"] == 0     # capped by the bootstrap's ESS
        self.automatic_bootstrap = mlt["bootstrap_samples"] == 0  # mmlt.py: may stop early
        self.iterations = max(1, round(self.mutations / self.chains))
        depths = STORED_DEPTHS if self.settings.max_depth < 0 else min(
            self.settings.max_depth, STORED_DEPTHS)
        self.dims = {"camera_u": self.camera.film_ray_numbers() + PER_DEPTH * depths,
                     "light_u": LIGHT_START + PER_DEPTH * max(depths - 1, 0)}
        self._capacity = [4, 5]          # pool records per light subpath, raised on overflow
        self.iterations_done, self.time = 0, 0.0
        self._iterating = False          # in run_iteration: the walks replay (``_walk``)
        self._rays = dr.zeros(mi.Float64, 1)     # rays traced (read by ``rays``)
        # mean acceptance per iteration, on the device (read by ``acceptance``)
        self._acceptance = dr.zeros(mi.Float, 64)
        # sums of a and counts of proposals: small steps, large steps (no host sync)
        self._tally = dr.zeros(mi.Float, 4)
        self.start_states = 0            # distinct bootstrap samples the chains start on
        self.images = None               # strategy records of an evaluation (mmlt.py)
        self._alpha_image = None         # an rgba film's alpha (``_alpha``)
        # the direct image (direct_samples): the bootstrap's records of those lengths,
        # then _direct's; b_chains the chains' brightness (b less b_direct if apart)
        self.b_direct, self.b_chains, self.direct_lanes = 0.0, 0.0, 0
        self.direct_film = FilmAccumulator(film, coalesce=False)
        # two-stage: 1 / L per pixel (``_first_stage``), and the first stage's samples
        self.two_stage, self.pixel_weight, self.stage_samples = mlt.get("two_stage", False), None, 0
        self.stage_block = 0             # the first stage's blocks (a side, pixels)
        self.film_steps = pss.film_steps(int(max(film.crop_size())))
        frozen.settle(self.scene, self.sensor)     # before any walk (frozen.settle)
        self._configure()
        start = time.perf_counter()
        self.b, self.state = self.bootstrap()
        self.s1, self.pilot_acceptance = pss.S1, 0.0
        if self.state is not None:
            self.s1 = self._pilot_steps()
        self.bootstrap_time = time.perf_counter() - start
        self.time += self.bootstrap_time

    name = "pssmlt"

    def _configure(self) -> None:
        """Subclasses' settings before the bootstrap (mmlt.py)."""

    def _key(self, *values) -> mi.UInt32:
        return dr.opaque(mi.UInt32, _mix_seed(self.seed, *values))

    @property
    def rays(self) -> int:
        """Rays traced so far (bootstrap included)."""
        return int(self._rays.numpy()[0])

    @property
    def acceptance(self) -> list:
        """The mean acceptance of each iteration's proposals (kept on the device until
        read: the iterations make no host sync for it)."""
        done = self.iterations_done if self.state is not None else 0
        return [float(v) for v in self._acceptance.numpy()[:done]]

    def last_acceptance(self) -> float:
        """The last iteration's mean acceptance (0 before the first)."""
        done = self.iterations_done if self.state is not None else 0
        return float(self._acceptance[done - 1]) if done else 0.0

    @property
    def done(self) -> bool:
        return self.iterations_done >= self.iterations

    # -- one evaluation: a BDPT sample per lane --------------------------------------
    def _context(self, rays, camera_sampler, light_sampler, lanes: int, key) -> PassContext:
        return PassContext(
            scene=self.scene, camera=self.camera, settings=self.settings,
            strategies=self.strategies, weights=self.weights, emitters=self.emitters,
            media=self.media, camera_sampler=camera_sampler, light_sampler=light_sampler,
            budget=BDPT, lane=dr.arange(mi.UInt32, lanes), time=rays.ray.time,
            wavelengths=rays.ray.wavelengths, camera_weight=rays.weight, light_count=lanes,
            pick_offset=dr.opaque(mi.Float, 0.0), noise_key=key, pixel=rays.pixel,
            connection_scale=dr.opaque(mi.Float, 1.0), images=self.images)

    def evaluate(self, lanes: int, samplers) -> Evaluation:
        """The BDPT sample of each lane's primary samples: ``samplers()`` makes a
        fresh (camera, light) pair (a light walk whose pools overflowed runs again on
        the same numbers).  A walk that Dr.Jit could not record (frozen.py) has run,
        but its samplers moved on: the evaluation runs again, that walk traced."""
        try:
            return self._evaluate(lanes, samplers)
        except frozen.RecordingFailed:
            return self._evaluate(lanes, samplers)

    def _evaluate(self, lanes: int, samplers) -> Evaluation:
        camera_sampler, light_sampler = samplers()
        rays = self.camera.sample_film_rays(camera_sampler, lanes)
        dr.eval(rays)
        if self.images is not None and self.pixel_weight is not None:   # two-stage
            self.images.weigh(self.weight_at, rays.pos)
        ctx = self._context(rays, camera_sampler, light_sampler, lanes, self._key(0x4E01))
        while True:
            store = LightVertexStore(lanes, lanes * self._capacity[0], lanes * self._capacity[1],
                                     allocate=False)
            light_rays, buffers = self._walk(_recorded_light_walk, ctx, store)
            store.adopt(buffers)
            dr.eval(light_rays, store.vertices.items, store.splats.items, store.first)
            if not store.overflowed():
                break
            self._capacity[0] = max(self._capacity[0], -(-store.vertices.size() * 5 // (4 * lanes)))
            self._capacity[1] = max(self._capacity[1], -(-store.splats.size() * 5 // (4 * lanes)))
            ctx.light_sampler = samplers()[1]
        ctx.stored = dr.opaque(mi.UInt32, max(store.vertices.size(), 1))
        cam = self._walk(_recorded_camera_walk, ctx, rays, store)[0]
        dr.eval(cam.radiance, cam.rays)
        count = min(store.splats.size(), store.splats.capacity)
        if count:
            s = gather(store.splats.items, dr.arange(mi.UInt32, count))
            splats = Records(pos=mi.Vector2f(s.pos), value=mi.Spectrum(s.value), lane=s.lane)
            if self.images is not None:
                self.images.add(s.lane, s.s, 1, splats.value, pos=splats.pos)
        else:
            splats = Records(pos=dr.zeros(mi.Vector2f, 0), value=dr.zeros(mi.Spectrum, 0),
                             lane=dr.zeros(mi.UInt32, 0))
        camera = Records(pos=rays.pos, value=mi.Spectrum(cam.radiance),
                         lane=dr.arange(mi.UInt32, lanes))
        f = self._target(camera, splats)
        totals = mi.Float64(dr.sum(cam.rays) + dr.sum(light_rays))
        dr.eval(f, camera, splats, totals)
        return Evaluation(f=f, camera=camera, splats=splats, rays=totals)

    def _walk(self, fn, *args):
        """A walk of ``evaluate`` in an iteration, replayed where recorded
        (frozen.py): tracing the walks cost more than their kernels at the chains'
        lane counts (door ajar 64x64, 8192 chains: an iteration 15.3 ms, its kernels
        5.6; replayed 16-17 ms against 34 traced, 32768 chains 48 against 62-82, under
        load; benchmarks/RESULTS.md).  The bootstrap's walks, which write every
        strategy's luminance (``images``), the first stage's, the start states' and the
        pilot's run once or a few times a render and are traced."""
        if self.images is not None or not self._iterating:
            return fn(*args)
        return frozen.call(fn, *args)

    def weight_at(self, pos: mi.Vector2f):
        """1 / L of the pixels at film positions ``pos`` (two-stage), or 1."""
        if self.pixel_weight is None:
            return 1.0
        size = self.sensor.film().crop_size()
        px = dr.clip(mi.Int32(dr.floor(pos.x)), 0, int(size.x) - 1)
        py = dr.clip(mi.Int32(dr.floor(pos.y)), 0, int(size.y) - 1)
        return dr.gather(mi.Float, self.pixel_weight, mi.UInt32(py * int(size.x) + px))

    def _target(self, camera: Records, splats: Records) -> mi.Float:
        """f of each lane's sample: the sum over its records of Y(value), each times
        ``weight_at`` its position (two-stage: 1 / L of its pixel)."""
        f = luminance(camera.value) * self.weight_at(camera.pos)
        if dr.width(splats.lane):
            dr.scatter_add(f, luminance(splats.value) * self.weight_at(splats.pos), splats.lane)
        return f

    def _first_stage(self) -> mi.Float:
        """1 / L per pixel up to a constant (two-stage; STAGE_*): the image of BDPT
        samples on keys of their own (the target must not depend on the samples that
        estimate b and pick the start states), in batches until their effective sample
        size reaches STAGE_ESS or max(planned chains, BOOTSTRAP_LANES) are drawn, on
        blocks of ``stage_block`` pixels (a side).  Their records of the direct lengths
        also go on the direct film, as the bootstrap's (``stage_samples`` counts
        them)."""
        keys = self._stream_keys(0xB3)
        total = max(self.chains, BOOTSTRAP_LANES)
        size = [int(v) for v in self.sensor.film().crop_size()]
        lum, sums, done = np.zeros(size[0] * size[1]), np.zeros(2), 0
        self.strategies.set_past(0)
        while done < total and not (sums[1] > 0 and sums[0] ** 2 >= STAGE_ESS * sums[1]):
            # batches of STAGE_LANES, then as many as are done (the stop is tested at
            # STAGE_LANES x 1, 2, 4, ...): a batch's walks are traced anew, some 50-75
            # ms each on 2 cores whatever its lanes, and the door's 0.01 gap's stage
            # took 16 batches of 16384 (1.8 s of a 30-s render; 5 batches now)
            n = min(max(STAGE_LANES, done), total - done)
            ident = dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, done)
            self.images = DirectLuminance(n)
            ev = self._evaluate_vectors(n, keys, ident, {name: None for name in self.dims})
            self._put_direct(ev)
            f = np.zeros(n)
            for records in (ev.camera, ev.splats):
                per_pixel, per_lane = _pixel_sums(records, size, n)
                lum, f = lum + per_pixel, f + per_lane
            sums += (f.sum(), np.dot(f, f))
            done += n
        self.images = None
        self.stage_samples = done
        self.stage_block = stage_block(sums[0] ** 2 / sums[1] if sums[1] > 0 else 0.0,
                                       size[0] * size[1])
        return device_array(mi.Float, pixel_weights(lum.reshape(size[1], size[0]),
                                                    self.stage_block).ravel())

    # -- start-up ---------------------------------------------------------------------
    def bootstrap(self):
        """b = the mean of f over ``bootstrap_samples`` independent samples (hashed
        primary samples, in batches of BOOTSTRAP_LANES lanes), and the chains' first states:
        bootstrap samples drawn in proportion to f (stratified resampling), rebuilt
        from their keys (pss.hashed_vectors), so that the chains start in the target
        distribution and the image's mean is b from the first iteration (Veach 1997,
        sec. 11.3.1's start-up bias)."""
        if self.emitters.count == 0:            # black (support.check warned)
            return 0.0, None
        keys = self._stream_keys(0xB0)
        f_np, f_direct = self._bootstrap_targets(keys, self.bootstrap_samples)
        b = float(f_np.mean())
        if b <= 0.0:
            return 0.0, None
        self.b_direct = float(f_direct.mean())
        separate = self._separate_direct(b)
        if separate:                            # the chains' target: longer paths only
            f_np = np.maximum(f_np - f_direct, 0.0)
        self.b_chains = float(f_np.mean())
        if self.automatic_chains:
            self.chains = chains_for_bootstrap(self.chains, f_np)
            self.iterations = max(1, round(self.mutations / self.chains))
        self.direct_lanes = self._direct_lanes(b) if separate else 0
        if self.b_chains <= 0.0:                # direct light only
            return b, None
        pick = self._resample(f_np)
        x = {name: pss.hashed_vectors(key, pick, self.dims[name])
             for name, key in zip(self.dims, keys)}
        dr.eval(x)
        self.strategies.set_past(DIRECT_LENGTH if self.direct_lanes else 0)
        ev = self._evaluate_vectors(self.chains, keys, pick, x)
        return b, Chains(f=ev.f, camera=ev.camera, splats=ev.splats, **x)

    def _separate_direct(self, b: float) -> bool:
        """Whether paths of lengths 1 .. DIRECT_LENGTH are rendered by independent
        samples instead of the chains (Mitsuba 0.6's ``directSamples``): where
        ``direct_samples`` > 0, or (0) where they carry at least DIRECT_SHARE of the
        brightness b (else the chains render every length).  Either way the image's
        expectation is the same: the chains' target then lacks those lengths."""
        if self.direct_samples < 0 or 0 <= self.settings.max_depth <= DIRECT_LENGTH:
            return False
        return self.direct_samples > 0 or self.b_direct >= DIRECT_SHARE * b

    def _direct_lanes(self, b: float) -> int:
        """Direct samples per iteration: ``direct_samples`` per pixel, or (0) chains x
        their share b_direct / b rounded down to a power of two, at least
        MIN_DIRECT_LANES."""
        if self.direct_samples > 0:
            return self.direct_samples * self.pixels
        lanes = max(MIN_DIRECT_LANES, int(self.chains * self.b_direct / b))
        return 1 << (lanes.bit_length() - 1)

    def _put_direct(self, ev: Evaluation) -> None:
        """A bootstrap batch's records of the direct lengths (``self.images``, a
        DirectLuminance) on the direct film."""
        self.direct_film.put_light(ev.camera.pos, self.images.direct)
        if self.images.direct_splats is not None:
            self.direct_film.put_light(self.images.direct_splats.pos,
                                       self.images.direct_splats.value)

    def _stream_keys(self, *values) -> tuple:
        """One opaque key per stream (``dims``'s order)."""
        return tuple(self._key(*values, i) for i in range(len(self.dims)))

    def _bootstrap_targets(self, keys, count: int) -> tuple[np.ndarray, np.ndarray]:
        """f of bootstrap samples 0 .. count - 1 (every coordinate hashed from its
        stream's key and the sample's number), in batches of BOOTSTRAP_LANES lanes, and
        its part on paths of 1 .. DIRECT_LENGTH edges (their records on the direct
        film)."""
        f_all, direct_all = [], []
        batch = max(self.chains, BOOTSTRAP_LANES)
        self.strategies.set_past(0)
        for start in range(0, count, batch):
            n = min(batch, count - start)
            ident = dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, start)
            self.images = DirectLuminance(n)
            ev = self._evaluate_vectors(n, keys, ident, {name: None for name in self.dims})
            self._put_direct(ev)
            f_all.append(ev.f.numpy())
            direct_all.append(self.images.y.numpy())
        self.images = None
        out = [np.concatenate(v).astype(np.float64) for v in (f_all, direct_all)]
        for v in out:
            v[~np.isfinite(v)] = 0.0
        return out[0], np.minimum(out[1], out[0])

    def _resample(self, weights: np.ndarray) -> mi.UInt32:
        """``chains`` bootstrap samples drawn in proportion to ``weights``, stratified
        (chain c takes the quantile (c + u_c) / chains: the picks ascend with c).  The
        cumulative sum is the host's, in float64: a device scan of float32 (Mitsuba's
        DiscreteDistribution) adds in an order that varies between runs under CUDA
        (two renders of one seed started other chains, seen on an H100), and drops a
        weight 2^-24 of those before it."""
        cdf = np.cumsum(weights, dtype=np.float64)
        chain = dr.arange(mi.UInt32, self.chains)
        u = pss.hash_uniform(self._key(0xB1), chain, 0).numpy().astype(np.float64)
        quantile = (np.arange(self.chains) + u) / self.chains * cdf[-1]
        pick = np.minimum(np.searchsorted(cdf, quantile, side="right"), len(cdf) - 1)
        self.start_states = len(np.unique(pick))
        return device_array(mi.UInt32, pick.astype(np.uint32))

    def _evaluate_vectors(self, lanes: int, keys, identity: mi.UInt32, x: dict) -> Evaluation:
        """The BDPT sample of each lane's vectors ``x`` (None: hashed from ``keys``
        and ``identity``); past a vector's coordinates, numbers hashed likewise.
        ``identity`` is evaluated first: an unevaluated ``dr.arange`` of the lanes'
        width is the same variable as the pass context's ``lane`` (Dr.Jit merges equal
        expressions), and a frozen walk whose inputs alias differently from its
        recording's records again (a second seed compiled 2 kernels)."""
        identity = mi.UInt32(identity)
        dr.make_opaque(identity)
        ev = self.evaluate(lanes, lambda: tuple(
            pss.PSSSampler.make(lanes, key, identity, x[name], self.dims[name])
            for name, key in zip(("camera_u", "light_u"), keys)))
        self._rays = self._rays + ev.rays
        dr.eval(self._rays)
        return ev

    # -- the chains ---------------------------------------------------------------------
    def run_iteration(self) -> None:
        """One mutation of every chain: propose, evaluate, splat both states by their
        expected values, accept or reject (Veach 1997, fig. 11.3; Kelemen 2002, sec. 4)."""
        if self.done:
            return
        start = time.perf_counter()
        with dr.suspend_grad():
            self._iterating = True
            try:
                self._iterate(self.iterations_done)
            finally:
                self._iterating = False
            dr.sync_thread()
        self.iterations_done += 1
        self.time += time.perf_counter() - start

    def _iterate(self, i: int) -> None:
        if self.state is not None:
            self._step_chains(i)
        if self.direct_lanes:
            self._direct(i)

    def _direct(self, i: int) -> None:
        """Iteration i's independent samples of the paths of lengths 1 .. DIRECT_LENGTH
        (every strategy of them with its MIS weight, hashed primary samples, as the
        bootstrap's samples' records of those lengths), on their own film: the image of
        those lengths is their records' mean (``tensor``)."""
        n = self.direct_lanes
        self.strategies.set_lengths(dr.full(mi.UInt32, DIRECT_LENGTH, n), up_to=True)
        ev = self._evaluate_vectors(n, self._stream_keys(0xD1, i), dr.arange(mi.UInt32, n),
                                    {name: None for name in self.dims})
        for records in (ev.camera, ev.splats):
            if dr.width(records.lane):
                self.direct_film.put_light(records.pos, records.value)

    def _proposals(self, key: tuple, large: mi.Bool, s1) -> dict:
        """Every chain's proposal y, keyed by ``key`` (pss.propose per stream; the film
        steps on the camera stream's film position, ``s1`` the other coordinates'
        smallest step)."""
        y = {name: pss.propose(vector, self.dims[name], large, self._key(*key, k),
                               self.film_steps if name == "camera_u" else None, s1)
             for k, (name, vector) in enumerate(self.state.vectors().items())}
        dr.eval(y)
        return y

    def _pilot_steps(self) -> float:
        """The small steps' s1 (pss.fine_steps), from the mean acceptance of one small
        step with Kelemen's sizes from the start states of PILOT_CHAINS chains (every
        chains / PILOT_CHAINS-th: MMLT's are sorted by length), on numbers of its own
        and discarded: the kernel is fixed from the bootstrap's states before the
        chains' first iteration (detailed balance holds for it), and a seed decides."""
        full, n = self.state, self.chains
        m = min(n, PILOT_CHAINS)
        self.state = full.rows(dr.arange(mi.UInt32, m) * (n // m), self.dims)
        self.chains = m
        try:
            y = self._proposals((0x5C, 1), dr.zeros(mi.Bool, m), dr.opaque(mi.Float, pss.S1))
            keys = self._stream_keys(0x5C, 2)
            ev = self._evaluate_proposal(keys, dr.arange(mi.UInt32, m), y)
            a = dr.mean(pss.acceptance(self.state.f, ev.f))
        finally:
            self.state, self.chains = full, n
        self.pilot_acceptance = float(a.numpy()[0])
        return pss.fine_steps(self.pilot_acceptance)

    def _step_chains(self, i: int) -> None:
        x, n = self.state, self.chains
        chain = dr.arange(mi.UInt32, n)
        step_key = self._key(0x17, i)
        large = pss.hash_uniform(step_key, chain, 0) < dr.opaque(mi.Float, self.p_large)
        y = self._proposals((0x17, i), large, dr.opaque(mi.Float, self.s1))
        ev = self._evaluate_proposal(self._stream_keys(0x7A, i), chain, y)
        a = pss.acceptance(x.f, ev.f)
        wy, wx = self._record_weights(x, ev, a, large)
        for records, w in ((ev.camera, wy), (ev.splats, wy), (x.camera, wx), (x.splats, wx)):
            self._put(records, w)
        accepted = pss.hash_uniform(step_key, chain, 1) < a
        mean_a = dr.mean(a)
        self._count(a, large)
        x.accept(accepted, y, ev, self.dims)
        if i >= dr.width(self._acceptance):      # grown by doubling (rarely)
            grown = np.zeros(2 * dr.width(self._acceptance), dtype=np.float32)
            grown[:i] = self._acceptance.numpy()[:i]
            self._acceptance = device_array(mi.Float, grown)
        dr.scatter(self._acceptance, mean_a, dr.opaque(mi.UInt32, i))
        dr.eval(self._acceptance)

    def _evaluate_proposal(self, keys, identity: mi.UInt32, y: dict) -> Evaluation:
        """The path samples of the chains' proposals ``y`` (of the lengths past the
        direct samples' where those are apart)."""
        self.strategies.set_past(DIRECT_LENGTH if self.direct_lanes else 0)
        return self._evaluate_vectors(self.chains, keys, identity, y)

    def _record_weights(self, x: Chains, ev: Evaluation, a: mi.Float, large: mi.Bool):
        """The weights of the proposal's and the state's records (pss.py)."""
        p_mis = self.p_large if self.large_step_mis else 0.0
        return pss.expected_value_weights(x.f, ev.f, a, dr.opaque(mi.Float, self.b_chains), large,
                                          dr.opaque(mi.Float, p_mis))

    def _count(self, a: mi.Float, large: mi.Bool) -> None:
        """Adds the iteration's acceptance sums and proposal counts of small and large
        steps to the tally (evaluated, no host sync)."""
        one = dr.select(large, 1.0, 0.0)
        sums = [dr.sum(a * (1.0 - one)), dr.sum(1.0 - one), dr.sum(a * one), dr.sum(one)]
        idx = dr.arange(mi.UInt32, 4)
        add = dr.select(idx == 0, sums[0], dr.select(idx == 1, sums[1],
                        dr.select(idx == 2, sums[2], sums[3])))
        self._tally = self._tally + add
        dr.eval(self._tally)

    def step_acceptance(self) -> tuple[float, float]:
        """The mean acceptance of small and of large steps so far (0 where none)."""
        t = self._tally.numpy()
        return (float(t[0] / t[1]) if t[1] else 0.0, float(t[2] / t[3]) if t[3] else 0.0)

    def _put(self, records: Records, w: mi.Float) -> None:
        """Records on the film, each times its chain's weight (the film's scale is
        applied once, in ``tensor``)."""
        if not dr.width(records.lane):
            return
        weight = dr.gather(mi.Float, w, records.lane)
        self.film.put_light(records.pos, records.value * weight, weight > 0.0)

    # -- results ------------------------------------------------------------------------
    def chains_tensor(self) -> mi.TensorXf:
        """The chains' image so far: the film's weighted records times N / (chains x
        iterations)."""
        samples = max(self.chains * self.iterations_done, 1)
        return self.film.develop_light(self.pixels / samples)

    def tensor(self) -> mi.TensorXf:
        """The image so far: the chains', plus the direct samples' where apart, and the
        film's alpha where it has one."""
        image = self.chains_tensor()
        if self.direct_lanes:       # the bootstrap's and _direct's (the same estimator)
            samples = (self.bootstrap_samples + self.stage_samples
                       + self.direct_lanes * self.iterations_done)
            image += self.direct_film.develop_light(self.pixels / samples)
        alpha = self._alpha()
        return image if alpha is None else image + alpha

    def _alpha(self) -> mi.TensorXf | None:
        """The film's alpha channel with its other channels 0, or None for a film
        without alpha: ALPHA_SPP samples per pixel of path tracing by this engine
        (its camera walk's coverage), rendered at the first call and counted in the
        render's time.  (The records alone left alpha 0: a transparent image.)"""
        if not mi.has_flag(self.sensor.film().flags(), mi.FilmFlags.Alpha):
            return None
        if self._alpha_image is None:
            start = time.perf_counter()
            r = Renderer(self.scene, sensor=self.sensor, spp=ALPHA_SPP,
                         seed=_mix_seed(self.seed, ALPHA_STREAM), light_paths=0, connections=0,
                         max_depth=self.settings.max_depth, rr_depth=self.settings.rr_depth,
                         hide_emitters=self.settings.hide_emitters)
            while not r.done:
                r.run_pass()
            image = r.tensor().numpy()
            alpha = np.zeros_like(image)
            alpha[..., ALPHA_CHANNEL] = image[..., ALPHA_CHANNEL]
            self._alpha_image = device_array(mi.TensorXf, alpha)
            self.time += time.perf_counter() - start
        return self._alpha_image

    def result(self) -> RenderResult:
        tensor = self.tensor()
        mpp = self.chains * self.iterations_done / self.pixels
        return RenderResult(image=tensor.numpy(), tensor=tensor, spp=int(mpp + 1e-9),
                            passes=self.iterations_done, time=self.time, rays=self.rays,
                            stats={"pixels": self.pixels, "integrator": self.name,
                                   "b": self.b, "chains": self.chains,
                                   "iterations": self.iterations_done,
                                   "mutations_per_pixel": mpp,
                                   "large_step_probability": self.p_large,
                                   "large_step_mis": self.large_step_mis,
                                   "two_stage": self.two_stage,
                                   "stage_block": self.stage_block,
                                   "bootstrap_samples": self.bootstrap_samples,
                                   "bootstrap_time": self.bootstrap_time,
                                   "start_states": self.start_states,
                                   "b_direct": self.b_direct,
                                   "direct_samples_per_iteration": self.direct_lanes,
                                   "acceptance": float(np.mean(self.acceptance))
                                   if self.acceptance else 0.0,
                                   "acceptance_small": self.step_acceptance()[0],
                                   "pilot_acceptance": self.pilot_acceptance,
                                   "small_step_s1": self.s1,
                                   "acceptance_large": self.step_acceptance()[1],
                                   "budget": self.name,
                                   "decision": "%s (BDPT samples)" % self.name})


def _pixel_sums(records: Records, size, lanes: int) -> tuple[np.ndarray, np.ndarray]:
    """The records' luminance summed per pixel (row-major, ``size`` = (width,
    height)) and per lane, in float64 and in an order fixed by the records' lanes,
    pixels and values: the light image's records come in the order of atomic slots,
    and a float sum (an image block's scatter-add among them) depends on it, so that
    the same seed would not give the same weights (or stage)."""
    if not dr.width(records.lane):
        return np.zeros(size[0] * size[1]), np.zeros(lanes)
    # Component by component: a whole Vector2f's or Spectrum's numpy() packs its
    # components in a kernel with their width as a literal, one kernel per width.
    x = np.clip(np.floor(records.pos.x.numpy()).astype(np.int64), 0, size[0] - 1)
    y = np.clip(np.floor(records.pos.y.numpy()).astype(np.int64), 0, size[1] - 1)
    value = np.nan_to_num(np.mean([records.value[c].numpy().astype(np.float64)
                                   for c in range(len(records.value))], axis=0))
    pixel, lane = y * size[0] + x, records.lane.numpy()
    order = np.lexsort((value, pixel, lane))
    return (np.bincount(pixel[order], weights=value[order], minlength=size[0] * size[1]),
            np.bincount(lane[order], weights=value[order], minlength=lanes))


def stage_block(ess: float, pixels: int) -> int:
    """The side of the first stage's blocks for a stage of effective sample size
    ``ess`` on a film of ``pixels``: the smallest power of two up to STAGE_BLOCK whose
    blocks hold at least STAGE_PER_BLOCK effective samples on average, else
    STAGE_BLOCK."""
    block = STAGE_BLOCK
    while block > 1 and ess * (block // 2) ** 2 >= STAGE_PER_BLOCK * pixels:
        block //= 2
    return block


def pixel_weights(lum: np.ndarray, block: int = STAGE_BLOCK) -> np.ndarray:
    """1 / L for a first-stage luminance image (``_first_stage``): means over blocks of
    ``block`` x ``block`` pixels (``stage_block``), floored at STAGE_FLOOR x their mean,
    over their mean (a black image: 1 everywhere)."""
    h, w = lum.shape
    k = block
    hb, wb = -(-h // k), -(-w // k)
    pad = ((0, hb * k - h), (0, wb * k - w))
    sums = np.pad(np.nan_to_num(lum.astype(np.float64)), pad)
    sums = sums.reshape(hb, k, wb, k).sum(axis=(1, 3))
    counts = np.pad(np.ones((h, w)), pad).reshape(hb, k, wb, k).sum(axis=(1, 3))
    level = np.repeat(np.repeat(sums / counts, k, axis=0), k, axis=1)[:h, :w]
    mean = level.mean()
    if not mean > 0.0:
        return np.ones((h, w), dtype=np.float32)
    level = np.maximum(level, STAGE_FLOOR * mean)
    return (level.mean() / level).astype(np.float32)


def render(scene, seed: int = 0, sensor=0, **params) -> RenderResult:
    """Render ``scene`` with PSSMLT (``params``: MLT_PARAMS and max_depth, rr_depth,
    mis, light_image, hide_emitters)."""
    r = MLTRenderer(scene, sensor=sensor, seed=seed, **params)
    while not r.done:
        r.run_iteration()
    return r.result()
