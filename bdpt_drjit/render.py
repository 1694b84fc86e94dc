"""The renderer: passes, each a list of named stages.

    for each pass:
        camera rays        camera.Camera.sample_rays     one lane per pixel sample
        light subpaths     walk.trace_light_subpaths     y_i stored for connections,
                                                         t = 1 splats (splat.py)
        hash grid          merge.HashGrid.build          merging only: the stored
                                                         light vertices by cell
        camera subpaths    walk.trace_camera_subpaths    s = 0, s = 1 and s, t >= 2
                                                         (connect.py)
        film               film.FilmAccumulator          camera block, then splats

Each camera sample i is paired with light subpath i (N_L = N_C), so the light image
is normalized by W*H / (total camera samples) and MIS uses N_L / N_C = 1.
Passes split the work so that a pass's state and stored light vertices stay under
a memory budget; a pass covers all pixels at ``spp_pass`` samples, or a range of
pixels at 1 sample for very large films.  Peak memory does not grow with spp.
"""
from __future__ import annotations

import copy
import functools
import math
import sys
import time
import warnings
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from . import aovs
from . import camera as camera_stage
from . import support
from .emitters import Emitters
from .film import FilmAccumulator
from .media import Media
from .mis import Weights
from .settings import Settings
from . import units
from .units import UnitCosts
from .budgets import BDPT, PATH_TRACING, Budget, fixed_budget
from .optimizer import (MIN_SPP, QUERY_STEPS, MomentSample, MomentSamples, Pilot, luminance,
                        rows_and_columns)
from .strategies import MERGE_LAYER, StrategyImages, StrategySet
from . import backend, connect, frozen, merge
from .vertices import RECORD_BYTES, SPLAT_BYTES, LightVertexStore, Pool, gather
from .walk import path_tracer_walk, trace_camera_subpaths, trace_light_subpaths

# Bytes a pass holds per camera lane besides its light subpaths' (camera rays, the
# samplers' state, the camera walk's outputs, the film's writes), and per light subpath
# besides its pools (the light walk's state and outputs).  Peak memory of a pass of
# Veach's BDPT (python -m benchmarks.memory, 256x256, 2 spp per pass, 2026-11-26): 982
# bytes per lane in the Cornell box, 1624 in Veach's bidirectional room (6 stored
# vertices of capacity per light subpath), where this model plans 1640 and 1960.
_CAMERA_LANE_BYTES = 300
_LIGHT_PATH_BYTES = 500
# Stored light vertices and splats per light subpath a pass plans for (measured: 3.0 and 3.2
# on the Cornell box, at max_depth 8 and -1 alike; 2.6 and 3.4 with its glass and
# mirror spheres).  A pass that needs more runs its light walk again with larger pools,
# and the passes after it are planned with those.
_VERTICES_PER_LANE = 4
_SPLATS_PER_LANE = 5


@dataclass
class PassContext:
    """What the stages of one pass share; the walks only read it."""
    scene: mi.Scene
    camera: camera_stage.CameraModel
    settings: Settings
    strategies: StrategySet
    weights: Weights
    emitters: Emitters
    media: Media
    camera_sampler: mi.Sampler
    light_sampler: mi.Sampler
    budget: Budget
    lane: mi.UInt32                    # each lane's own index (pools, strategy images)
    time: mi.Float                     # per lane, shared by its two subpaths
    wavelengths: mi.UnpolarizedSpectrum
    camera_weight: mi.Spectrum         # sensor sampling weight (spectral response)
    light_count: int                   # N_L light subpaths; camera lane i takes i mod N_L
    pick_offset: mi.Float              # a vertex cache's pick offset, uniform per pass
    noise_key: mi.UInt32               # per pass: keys ratio tracking's numbers (media.py)
    images: StrategyImages | None = None
    connection_scale: mi.Float = None  # 1 / kappa of the pass's stored vertices
    stored: mi.UInt32 = None           # V, the stored light vertices of the pass
    pixel: mi.UInt32 = None            # each camera lane's crop pixel (moments)
    moments: MomentSamples | None = None   # a moment pass's contributions (optimizer.py)
    mis_rates: tuple = (1.0, 1.0, 0.0)  # N_L / N_C, kappa and eta of the MIS weights
    grid: merge.HashGrid | None = None  # merging: the pass's light vertices (merge.py)
    queries: Pool | None = None        # merging: the camera walk's deferred queries
    links: Pool | None = None          # the camera walk's deferred connections (connect.py)
    merge_radius: float = 0.0          # merging: this pass's radius r_i
    scene_values: tuple = ()           # support.SceneFacts.values: key the walks' recordings

    def light_subpath(self, lane):
        """The light subpath camera lane ``lane`` connects to (i mod N_L)."""
        return lane % dr.opaque(mi.UInt32, max(self.light_count, 1))

    def for_light_subpaths(self) -> "PassContext":
        """This context with a lane per light subpath; light subpath l shares the time,
        wavelengths and sensor weight of camera lane l mod N_C."""
        lanes = dr.width(self.lane)
        if self.light_count == lanes:
            return replace(self)
        home = dr.arange(mi.UInt32, self.light_count) % dr.opaque(mi.UInt32, lanes)
        return replace(self, lane=dr.arange(mi.UInt32, self.light_count),
                       time=dr.gather(mi.Float, self.time, home),
                       wavelengths=dr.gather(type(self.wavelengths), self.wavelengths, home),
                       camera_weight=dr.gather(type(self.camera_weight), self.camera_weight, home))


@dataclass
class RenderResult:
    """What ``render`` returns.  ``image`` is an (H, W, C) float32 NumPy array.
    On request, ``strategy_images`` maps (s, t) to the MIS-weighted image of that
    strategy, for paths of up to strategies.LAYER_K edges, and ``length_images``
    maps a longer path length k to the image of all its strategies (k =
    strategies.DEEP_K + 1 holding every longer path); together they sum to ``image``."""
    image: np.ndarray
    tensor: mi.TensorXf
    strategy_images: dict = field(default_factory=dict)
    length_images: dict = field(default_factory=dict)
    kernel_history: list = field(default_factory=list)   # entries the pilot took from
                                                           # Dr.Jit's kernel history
    spp: int = 0
    passes: int = 0
    time: float = 0.0
    rays: int = 0
    stats: dict = field(default_factory=dict)
    aov_names: list = field(default_factory=list)   # the last channels' names (aovs.py)
    merge_image: np.ndarray | None = None   # merging with strategy images: every merge
    @property
    def channels(self) -> list:
        """The image's channel names: the film's (``exr.channel_names``), then AOVs'."""
        from .exr import channel_names
        return channel_names(self.image.shape[2] - len(self.aov_names)) + self.aov_names

    @property
    def strategies(self) -> dict:
        """Old name of ``strategy_images``."""
        return self.strategy_images

    @property
    def samples_per_second(self) -> float:
        return self.spp * self.stats.get("pixels", 0) / self.time if self.time > 0 else 0.0


def _mix_seed(*values: int) -> int:
    """A 32-bit seed from several integers (splitmix64 finalizer)."""
    x = 0x9E3779B97F4A7C15
    for v in values:
        x = (x ^ (int(v) & 0xFFFFFFFFFFFFFFFF)) * 0xBF58476D1CE4E5B9 & 0xFFFFFFFFFFFFFFFF
        x ^= x >> 31
        x = x * 0x94D049BB133111EB & 0xFFFFFFFFFFFFFFFF
        x ^= x >> 29
    return x & 0xFFFFFFFF


def _unit(*values: int) -> float:
    """A number in [0, 1) from integers (a pass's pick offset)."""
    return _mix_seed(*values, 0x5EED) / 2.0 ** 32


def check_variant() -> None:
    variant = mi.variant()
    if variant is None:
        from ._llvm import FIX, LLVMError
        raise LLVMError("bdpt: no Mitsuba variant could be set (llvm_ad_rgb needs libLLVM "
                        ">= 16). " + FIX)
    if not (variant.startswith("llvm_") or variant.startswith("cuda_")):
        raise RuntimeError("bdpt: needs a JIT variant of Mitsuba (llvm_* or cuda_*), but the "
                           "current variant is %r; call mi.set_variant('llvm_ad_rgb') first" % variant)
    if "polarized" in variant:
        raise RuntimeError("bdpt: polarized variants are not supported (got %r)" % variant)
    from . import _llvm
    _llvm.check(variant)


class _StageTimer:
    """Kernel seconds of each stage of a pilot pass, compilation excluded (Dr.Jit's
    kernel history, whose entries are kept in ``log`` for callers that read it too)."""

    def __init__(self, on: bool, log: list):
        self.on, self.log = on, log
        if on:
            self.log.extend(dr.kernel_history())

    def lap(self) -> float:
        """Kernel seconds since the last lap, the stage's queued scatters evaluated."""
        if not self.on:
            return 0.0
        dr.eval()
        dr.sync_thread()
        entries = dr.kernel_history()
        self.log.extend(entries)
        return sum(e.get("execution_time", 0.0) for e in entries
                   if e["type"] == dr.KernelType.JIT) / 1000.0


def _splat_moments(ctx, store):
    """A moment pass's light-image contributions as moment samples (optimizer.py),
    with their validity and weight.  A splat is value / r per camera sample (N_C / N_L
    times its value, r = N_L / N_C), so its F^2 weighs 1 / r^2.  A pass after the pilot
    takes the splats of one light subpath in every * r (at least 1; about as many
    light subpaths as camera lanes it records), chosen by subpath, not by place in the
    pool, which the walk's threads fill in no fixed order; only the lanes of its
    millions of records are read before the choice, and the choice is evaluated once
    (unevaluated, the decision's kernels read the whole pool again: 20 ms)."""
    size = 0 if store is None else min(store.splats.size(), store.splats.capacity)
    if size == 0:
        return None
    s = store.splats
    r = ctx.mis_rates[0]
    stride = max(1, int(ctx.moments.every * r))
    index = dr.arange(mi.UInt32, size)
    if stride > 1:
        chosen = dr.gather(mi.UInt32, s.items.lane, index) % dr.opaque(mi.UInt32, stride) == 0
        index = dr.compress(chosen)
        if dr.width(index) == 0:        # splats, but none of a chosen light subpath
            return None
    items = gather(s.items, index)
    value = luminance(items.value)
    if ctx.moments.shadow:          # weighted as with merging (MomentSamples)
        value = value * (1.0 - items.u_vm)
    samples = MomentSample(pixel=ctx.camera.pixel_index(items.pos), f2=dr.square(value),
                           u_pt=items.u_pt, u_lt=items.u_lt, u_vm=items.u_vm,
                           f2_pairs=dr.zeros(mi.Float, dr.width(value)),
                           query=dr.zeros(mi.Float, dr.width(value)))
    dr.eval(samples)
    return samples, None, stride / r ** 2, r


def _recorded_light_walk(ctx, store):
    """Stage 2's walk with its pools made inside it: frozen.py records it, and a buffer
    made before a recording is one of its inputs, which a replay copies before its
    first scatter (copy on write: 66 copies of the pilot's pools, 6 MB at 64x64).
    Returns the rays per lane and the pools (LightVertexStore.adopt)."""
    store.allocate()
    rays = trace_light_subpaths(ctx, store)
    return rays, store.buffers()


def _recorded_camera_walk(ctx, rays, store):
    """Stage 3's walk with the moment samples' buffers made inside it (as
    ``_recorded_light_walk``); returns its final state, those buffers
    (optimizer.MomentSamples.adopt) and the deferred connections' count."""
    if ctx.moments is not None:
        ctx.moments.allocate()
    for pool in (ctx.queries, ctx.links):
        if pool is not None:
            pool.allocate()
    cam = trace_camera_subpaths(ctx, rays, store)
    if ctx.queries is not None or ctx.links is not None:
        # The walk's kernel with all of its outputs, its sampler's state included (a
        # recording's outputs, frozen.py: one evaluated later would run the walk's loop
        # again), then the connections and merges it deferred, added to its radiance.
        ctx.camera_sampler.schedule_state()
        dr.eval(cam)
        if ctx.links is not None:
            connect.run_links(ctx, store, cam)
        if ctx.queries is not None:
            merge.run_queries(ctx, store, cam)
    return (cam, None if ctx.moments is None else ctx.moments.buffers(),
            None if ctx.links is None else ctx.links.count)


@functools.lru_cache(maxsize=8)
def _path_tracer(max_depth: int, rr_depth: int, hide_emitters: bool) -> mi.Integrator:
    """Mitsuba's ``path`` with these settings, one object for every render: the
    recorded path passes (frozen.py) name it by identity."""
    return mi.load_dict({"type": "path", "max_depth": max_depth, "rr_depth": rr_depth,
                         "hide_emitters": hide_emitters})


def _recorded_path_pass(camera, sensor, seed, integrator, scene, film, aovs, opaque: bool,
                        pixel_offset: int, n_pixels: int, spp: int, stride: int):
    """A path-traced pass whole, as frozen.py records it: its sampler seeded by an
    opaque ``seed``, its camera rays, Mitsuba's path on them and the film's put, in
    one kernel as in Mitsuba's own render (101-108 ns per sample against ``path``'s
    100, glass pane 128x128 256 spp).  Tracing the path megakernel and the put cost
    each pass what ``mi.render`` spends before its kernel runs (2 ms, 5 under load);
    a replay takes 0.5.  (Recording the walk alone saved nothing at 64x64: its values
    and the sampler's state were then written out for the film's kernel.)
    ``opaque``: alpha is 1 everywhere (``_put_camera``)."""
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(seed, n_pixels * spp)
    rays = camera.sample_rays(sampler, pixel_offset, n_pixels, spp, stride)
    walk = path_tracer_walk(integrator, scene, rays, sampler)
    _put_camera(film, aovs, opaque, rays, walk.radiance, walk.hit)


def _put_camera(film, aovs, opaque: bool, rays, radiance, hit, images=None, lanes: int = 0):
    """The camera samples' values on the film.  Alpha as Mitsuba's path: 1 where the
    camera ray hit a surface, everywhere if an environment shows (``opaque``)."""
    film.put_camera(rays, radiance, hit | opaque, images, lanes)
    if aovs is not None:
        film.put_aovs(rays, aovs.values(rays.ray))


def plan_passes(spp: int, pixels: int, max_lanes: int, explicit: int, accepted) -> list:
    """Split spp x pixels into passes (pixel offset, pixels, spp) of at most
    ``max_lanes`` lanes.  Automatic passes are equal in size: Dr.Jit keeps freed
    buffers for reuse by requests of the same size, so a smaller last pass would
    allocate a second set beside the cached first one (measured: 1.9 -> 3.0 GB at
    1920x1080).  ``accepted(n)``: the count the sampler accepts for n (orthogonal
    rounds to a prime squared), as Mitsuba's render does."""
    per_pass = min(explicit or spp, max(1, max_lanes // pixels), spp)
    if not explicit or per_pass < explicit:
        per_pass = -(-spp // -(-spp // per_pass))    # equal passes
    passes, counts = [], {}         # accepted(n) for the (two) sizes asked
    if pixels * per_pass <= max_lanes:
        done = 0
        while done < spp:
            want = min(per_pass, spp - done)
            n = counts[want] = counts.get(want) or accepted(want)
            passes.append((0, pixels, n))
            done += n
        return passes
    chunks = -(-pixels // max_lanes)                 # very large film: pixel ranges, 1 spp
    chunk = -(-pixels // chunks)
    return [(start, min(chunk, pixels - start), 1)
            for _ in range(spp) for start in range(0, pixels, chunk)]


class Renderer:
    """A progressive BDPT render of one sensor: call ``run_pass`` until ``done``.

    ``bdpt_drjit.render`` drives it to the end; the command line drives it pass by
    pass to show progress, write checkpoints and stop on a signal or time budget.
    """

    def __init__(self, scene: mi.Scene, sensor=0, spp: int | None = None, seed: int = 0,
                 strategy_images: bool = False, unit_costs: UnitCosts | None = None,
                 reuse_pilot: bool = True, **settings):
        """``unit_costs``: the prices of the pilot's counts (units.py); by default the
        machine's calibration, measured on first use.  ``reuse_pilot``: a small
        render may take its pilot's outcome from an earlier render (``_ReusedPilot``);
        a cluster's renderers do not."""
        check_variant()
        self.sensor = camera_stage.select_sensor(scene, sensor)
        # Camera samples cover the crop and any sampled filter border; so do t = 1's.
        border = camera_stage.sampled_border(self.sensor.film())
        self.camera = camera_stage.make_camera(self.sensor, border)
        self.scene = scene
        self.settings = Settings.from_dict(settings)
        camera_stage.check_settings(self.camera, self.settings)
        facts = support.facts(scene, self.sensor)
        self._facts = facts if reuse_pilot else None    # the scene's state (_ReusedPilot)
        # Refuses what bdpt would get wrong (media, unsupported plugins), warns of the rest.
        support.check(scene, self.sensor, facts.verdicts)
        support.warn_of_light_tracing_paths(scene, self.settings)
        self.emitters = Emitters(scene)
        self.media = Media(scene, self.sensor)
        self._scene_values = facts.values       # they key the frozen walks (frozen.py)
        self._path_drops_light = facts.path_drops_light
        fixed = fixed_budget(self.settings)
        if strategy_images and fixed is None:   # the layers show every BDPT strategy
            fixed = BDPT
        self.budget = fixed or BDPT
        if mi.is_spectral and self.settings.light_paths not in ("auto", 0.0, 1.0):
            raise ValueError("bdpt: light_paths must be 0 or 1 in spectral variants (a light "
                             "subpath shares its wavelengths with one camera sample), got %g"
                             % self.settings.light_paths)
        self._rules_cache = {}
        # Strategy-image layers cover every strategy of full BDPT.
        self.strategies = StrategySet(self.settings, self.emitters.count > 0,
                                      light_image_possible=self.camera.light_image_possible)
        self.seed = int(seed)
        self.strategy_images = strategy_images
        film = self.sensor.film()
        grid = camera_stage.film_grid(film)
        self.pixels = int(grid[0]) * int(grid[1])
        if self.settings.merging and mi.is_spectral:
            raise ValueError("bdpt: merging is not supported in spectral variants: a light "
                             "vertex's throughput holds its own subpath's wavelengths, which "
                             "the camera samples merging with it do not share")
        # Merging: the first pass's radius (merge.py); 0 without merging.
        self.merge_radius = (merge.first_radius(scene, self.sensor, self.settings.radius)
                             if self.settings.merging else 0.0)
        self.spp = int(spp) if spp else self.sensor.sampler().sample_count()
        if self.spp <= 0:
            raise ValueError("bdpt: spp must be positive, got %d" % self.spp)
        layers = self.strategies.layers() if strategy_images else []
        self._unit_costs = unit_costs
        self.timings = None             # calibrate(): kernel seconds of the pilot's walks
        # Pool capacities per light subpath, raised on overflow, for every pass after:
        # a light subpath's stored vertices do not depend on the pass's light subpaths
        # (kept per count, every new count overflowed again: Veach's room ran one light
        # walk twice per render: 7% of its time at 128x128, 256 spp).
        self._capacity = [_VERTICES_PER_LANE, _SPLATS_PER_LANE]
        self._links_per_lane = connect.LINKS_PER_LANE   # deferred connections' pool, raised too
        self._outgrown = False          # a light walk raised them in this pass
        self._plan(fixed, layers)
        self.redecide = True        # False: the pilot's decision and plan hold (cluster.py)
        aov_list = aovs.parse(self.settings.aovs)
        self.aovs = aovs.AOVs(scene, aov_list) if aov_list else None
        # Alpha 1 everywhere: an environment shows (``_put_camera``).
        self._opaque = self.emitters.environment is not None and not self.settings.hide_emitters
        self.film = FilmAccumulator(film, coalesce=self.spp >= 4, layers=layers,
                                    aov_names=aovs.channel_names(aov_list), border=border)
        self.passes_done = 0
        self.spp_done = 0.0           # samples per pixel rendered (fractional: pixel ranges)
        self.time = 0.0
        self.rays = 0                 # traced by this engine's walks
        self.last_counts = [0, 0]     # the last pass's: rays of its camera walk, light walk
        self.path_tracer_spp = 0.0    # samples per pixel rendered by Mitsuba's path
        self._last_lanes = 0
        self._vertices_per_path = 3.0   # stored light vertices per light subpath, last pass
        self.kernel_history = []        # kernels calibrate()'s timing took from Dr.Jit's history
        if self.pilot is not None and not self._pilot_kept:
            _ReusedPilot.restore(self)

    def _plan(self, fixed: Budget | None, layers: list) -> None:
        """The passes: equal ones that fit the memory budget, opened by a pilot round
        where the budget is "auto" (not for fewer than MIN_SPP samples, nor for a film
        rendered in pixel ranges)."""
        self.memory_budget = self.settings.memory_budget or backend.default_memory_budget()
        self._layer_bytes = len(layers) * 16
        max_lanes = self._lanes_for(fixed or BDPT)
        if self.settings.merging and not self.settings.samples_per_pass:
            # The radius shrinks per pass (merge.py): passes of a few samples per pixel.
            max_lanes = min(max_lanes, max(merge.PASS_LANES, self.pixels))
        self.plan = plan_passes(self.spp, self.pixels, max_lanes, self.settings.samples_per_pass,
                                self._accepted_count)
        self.pilot, self._stride, self._path_tracer = None, {}, None
        self._moment_passes = set()     # passes after the pilot that re-decide
        self._pending = []              # the vcm pilot pass, merged for moments only
        self._pilot_round = 0           # passes of the round the pilot opens (1 or 2)
        self._pilot_kept = True         # the pilot's samples stay in the image
        self._pilot_reused = False      # its outcome came from an earlier render
        self._second_look = False       # the round's second pass records moments too
        if fixed is None and self.spp >= MIN_SPP and self.pixels <= max_lanes:
            self._plan_pilot(max_lanes)
            if not self.media.present and not self._path_drops_light:
                # Where the pilot chooses path tracing, Mitsuba's path renders the rest
                # (elsewhere this engine's camera walk does, with s <= 1).
                self._path_tracer = _path_tracer(self.settings.max_depth,
                                                 self.settings.rr_depth,
                                                 self.settings.hide_emitters)
            self.pilot.costs.path_tracer = self._path_tracer is not None

    def _lanes_for(self, budget: Budget) -> int:
        """The camera lanes of a pass of ``budget`` that fit the memory budget: its light
        subpaths per lane (light_ratio) with their pools at the capacities in force,
        the vertex pool only where some strategy stores a vertex, and the camera walk's
        deferred connections (connect.link_bytes).  Never more than a
        pass of Veach's BDPT at the first capacities: on the CPU a larger pass is
        slower (each pass of a new size writes fresh memory, a page fault per 4 KiB:
        light_paths=0.25 in one pass of 63 spp took 1.11-1.16x the time of three, Cornell
        box 256x256)."""
        links = connect.link_bytes(self.strategies, budget, self.media.present,
                                   self._links_per_lane)

        def lanes(ratio: float, vertices: int, splats: int, stores: bool) -> int:
            pools = (vertices * RECORD_BYTES if stores else 0) + splats * SPLAT_BYTES
            lane_bytes = (_CAMERA_LANE_BYTES + self._layer_bytes + links
                          + max(ratio, 0.0) * (_LIGHT_PATH_BYTES + pools))
            return int(min(max(1024, self.memory_budget // lane_bytes), 2 ** 31))
        stores = budget.connects or (self.settings.merging and budget.merges)
        return min(lanes(budget.light_ratio, *self._capacity, stores),
                   lanes(1.0, _VERTICES_PER_LANE, _SPLATS_PER_LANE, True))

    def _plan_pilot(self, max_lanes: int) -> None:
        """An "auto" budget: the render opens with a pilot pass, BDPT with moments
        (optimizer.py), then the rest of the samples.  On a large film the pilot pass
        takes every other pixel (optimizer.Pilot.stride), and a second pass of its
        round gives the odd ones their samples with the budget chosen, so that every
        pixel has the same samples after the round.  A small render's pilot takes one
        pixel in several and its samples are dropped (``pass_spp``): all the render's
        samples come after it."""
        self.pilot = Pilot(mi.is_spectral,
                           self.camera.light_image_possible and self.settings.light_image,
                           self._unit_costs or units.load() or calibrate(),
                           merging=self.settings.merging, spp=self.spp)
        if self.settings.first_hits != "auto":
            light = self.settings.first_hits == "light_image"
            self.pilot.candidates = [b for b in self.pilot.candidates
                                     if b.light_first_hits == light]
            if not self.pilot.candidates:
                raise ValueError("bdpt: first_hits='light_image' needs a camera that a light "
                                 "vertex can be connected to (not an orthographic one)")
        spp = self._accepted_count(self.settings.samples_per_pass
                                   or Pilot.spp(self.pixels, self.spp))
        stride, self._pilot_kept = Pilot.stride(self.pixels, spp, self.spp,
                                                self.settings.merging)
        if self._pilot_kept and stride == 2:
            pilot_round = [(0, (self.pixels + 1) // 2, spp), (1, self.pixels // 2, spp)]
            self._stride = {0: 2, 1: 2}
        else:
            pilot_round = [(0, -(-self.pixels // stride), spp)]
            self._stride = {0: stride} if stride > 1 else {}
        self._pilot_round = len(pilot_round)
        self.plan = pilot_round + plan_passes(
            self.spp - (spp if self._pilot_kept else 0), self.pixels, max_lanes,
            self.settings.samples_per_pass, self._accepted_count)

    def _replan(self, after: int) -> None:
        """The passes after pass ``after``, sized anew for the budget in force and the
        pools' capacities: after the pilot's decision, a re-decision, or a light walk
        that outgrew its pools (not with an explicit samples_per_pass, a film rendered
        in pixel ranges, on a cluster, whose workers render a plan fixed before the
        pilot, nor inside the pilot's round):

        * path tracing: Mitsuba's path, whose lanes hold little, in as few passes as
          ``backend.path_pass_lanes`` allows (a GPU pass's fixed cost is 17-40 ms: at
          BDPT's 1 spp per pass the default took 13x ``path``'s time on an H100 at
          1024x1024, 16 spp);
        * otherwise as many lanes as the budget's light subpaths and pools leave room
          for (``_lanes_for``; the plan before knew neither: Veach's BDPT in Veach's
          room held 2.4x the memory budget), merging's passes kept small (their
          radius shrinks per pass)."""
        rest = self.plan[after + 1:]
        if after < self._pilot_round - 1:
            return
        if (self.redecide and not self.settings.samples_per_pass and rest
                and rest[0][1] == self.pixels):
            if self.budget == PATH_TRACING and self._path_tracer is not None:
                lanes = backend.path_pass_lanes(self.memory_budget)
            else:
                lanes = self._lanes_for(self.budget)
                if self.budget.merges and self.settings.merging:
                    lanes = min(lanes, max(merge.PASS_LANES, self.pixels))
            self.plan = self.plan[:after + 1] + plan_passes(
                sum(spp for _, _, spp in rest), self.pixels, lanes, 0, self._accepted_count)
        self._plan_rounds(after)

    def merge_eta(self, after: int) -> float:
        """Merging's rate per light subpath per camera sample over the passes after
        ``after``: the mean of pi r_i^2 N_C,i (merge.pass_radius), which a budget's
        light_ratio scales to its eta (optimizer.Costs.merge_eta).  Over the passes a
        merging budget would render (``_plan``, ``_replan``): after a choice without
        merging the plan's passes are larger, and their eta priced merging's queries
        at 3x the pilot's cost on SmallVCM's large glass sphere.  0 where no candidate
        merges (its plan took 0.1 ms of a 64x64 render's pilot pass)."""
        if not self.settings.merging:
            return 0.0
        rest = self.plan[after + 1:]
        if (not self.budget.merges and not self.settings.samples_per_pass and rest
                and rest[0][1] == self.pixels):
            lanes = min(self._lanes_for(BDPT), max(merge.PASS_LANES, self.pixels))
            rest = plan_passes(sum(spp for _, _, spp in rest), self.pixels, lanes, 0,
                               self._accepted_count)
        etas = [math.pi * merge.pass_radius(self.merge_radius, self.settings.radius_alpha, i) ** 2
                * n * spp for i, (_, n, spp) in enumerate(rest, after + 1)]
        return float(np.mean(etas)) if etas else 0.0

    def _plan_rounds(self, done: int) -> None:
        """Re-decisions (optimizer.Pilot.redecide) after pass ``done``: the first pass
        of the plan that ends at or after 4, 16 and 64 times the pilot's spp (the last
        pass excepted) records moments, on the first sample of every other pixel, with
        the balance heuristic; the decision after it holds until the next.  No pass is
        split to end exactly there: passes of other sizes cost more than they gave (each
        new size allocates its buffers anew: on Veach's bidirectional room, 128x72, 256
        spp, 8.0 s against 6.75 s), and a moment pass costs 4-20% more than a plain
        one.  Not where path tracing was chosen (its samples give no other
        candidate's moment: the pilot looks again instead, ``_plan_second_look``), nor
        on a cluster (the workers' plan is fixed)."""
        self._moment_passes = {i for i in self._moment_passes if i <= done}
        if not self.redecide or self.budget.light_ratio <= 0 or self.pilot is None:
            return
        ends = np.cumsum([self.pass_spp(i) for i in range(len(self.plan))])
        pilot_spp = sum(n * spp for _, n, spp in self.plan[:self._pilot_round]) / self.pixels
        for c in (4, 16, 64):
            if ends[done] >= c * pilot_spp - 1e-9:
                continue                                # reached by the passes done
            after = [i for i in range(done + 1, len(self.plan) - 1)
                     if ends[i] >= c * pilot_spp - 1e-9]
            if after:
                self._moment_passes.add(after[0])

    def pass_spp(self, index: int) -> float:
        """Samples per pixel that pass ``index`` of the plan adds to the image: none
        for a pilot whose samples are dropped (``_plan_pilot``)."""
        if index < self._pilot_round and not self._pilot_kept:
            return 0.0
        _, n, spp = self.plan[index]
        return n * spp / self.pixels

    def _accepted_count(self, n: int) -> int:
        sampler = self.sensor.sampler().clone()
        sampler.set_sample_count(n)
        return sampler.sample_count()

    @property
    def done(self) -> bool:
        return self.passes_done >= len(self.plan)

    @property
    def at_round_end(self) -> bool:
        return self.is_round_end(self.passes_done, self.spp_done)

    def is_round_end(self, passes: int, spp_done: float) -> bool:
        """Every pixel has had the same number of camera samples after the first
        ``passes`` passes of the plan (``spp_done`` per pixel), so the image is
        unbiased there.  Only the pilot's first pass (the even pixels) and a very large
        film split into pixel ranges are ever between rounds: a stop there would leave
        pixels with the light image alone (a time budget that ran out in the pilot's
        first pass wrote the odd pixels black); and a pilot whose samples were dropped
        has left none."""
        if 0 < passes < self._pilot_round or (passes > 0 and spp_done == 0):
            return False
        return abs(spp_done - round(spp_done)) < 1e-6

    def run_pass(self) -> None:
        """Render the next pass of the plan."""
        if not self.done:
            self.render_pass(self.passes_done)

    def render_pass(self, index: int) -> None:
        """Render pass ``index`` of the plan into the film.  A pass's samples depend
        only on the seed and its index, so passes may run in any order, or on
        different machines whose raw film sums are added (cluster.py)."""
        pixel_offset, n_pixels, spp = self.plan[index]
        lanes = n_pixels * spp
        if self._last_lanes and lanes != self._last_lanes:
            # Buffers cached for the previous size would sit beside this pass's.
            dr.flush_malloc_cache()
        self._last_lanes = lanes
        start = time.perf_counter()
        history = dr.flag(dr.JitFlag.KernelHistory) or self.timings is not None
        with dr.suspend_grad(), dr.scoped_set_flag(dr.JitFlag.KernelHistory, history):
            try:
                self._render_pass(index, pixel_offset, n_pixels, spp, lanes)
            except frozen.RecordingFailed:
                # Nothing reached the film before the walks: the pass again, traced.
                self._render_pass(index, pixel_offset, n_pixels, spp, lanes)
            if self._outgrown:
                self._outgrown = False
                self._replan(index)
            if self._is_pilot_pass(index) and not self._pilot_kept:
                _ReusedPilot.keep(self)
            # A pass counts once it is rendered: Dr.Jit launches kernels asynchronously,
            # and a pass that reads nothing back (Mitsuba's path) would only be queued.
            dr.sync_thread()
        self.time += time.perf_counter() - start
        self.passes_done += 1
        self.spp_done += self.pass_spp(index)

    # -- one pass -----------------------------------------------------------------------
    def _seed_of(self, index: int) -> int:
        """The seed of pass ``index``'s random numbers: a pilot whose samples are dropped
        draws the same ones in every render (``_ReusedPilot``)."""
        return PILOT_SEED if index < self._pilot_round and not self._pilot_kept else self.seed

    def _is_pilot_pass(self, index: int) -> bool:
        """The pilot pass (not the passes that complete its round)."""
        return self.pilot is not None and index < Pilot.PASSES

    def _looks_again(self, index: int) -> bool:
        """Pass ``index`` is the pilot round's second pass, rendered as the pilot
        (``_plan_second_look``)."""
        return self._second_look and index == Pilot.PASSES

    def _sampler(self, index: int, stream: int, lanes: int, spp: int) -> mi.Sampler:
        sampler = self.sensor.sampler().clone()
        sampler.set_sample_count(spp)
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(_mix_seed(self._seed_of(index), index, stream), lanes)
        return sampler

    def _rules(self, budget: Budget, heuristic: str, shadow: bool = False):
        """The strategies and weights of a budget (one pair per budget, reused);
        ``shadow``: its merges for the moments only (mis.Weights)."""
        key = budget, heuristic, shadow
        if key not in self._rules_cache:
            strategies = StrategySet(self.settings, self.emitters.count > 0, budget,
                                     self.camera.light_image_possible)
            self._rules_cache[key] = (strategies, Weights(heuristic, strategies, shadow))
        return self._rules_cache[key]

    def _pass_rules(self, index: int):
        """(budget, heuristic, moment samples or None) of pass ``index``."""
        if self._is_pilot_pass(index) or self._looks_again(index):
            budget, heuristic, moments = self.pilot.budget(index)
            return budget, heuristic or self.settings.mis, moments
        if index in self._moment_passes and self.budget.light_ratio > 0:
            return self.budget, "balance", True
        return self.budget, self.settings.mis, False

    def _context(self, index, rays, sampler, lanes: int, spp: int) -> PassContext:
        budget, heuristic, moments = self._pass_rules(index)
        # The vcm pilot merges for its moments only: its image stays BDPT's (unbiased,
        # and without the fireflies of merging where it does not pay).
        shadow = self._is_pilot_pass(index) and budget.merging is True
        strategies, weights = self._rules(budget, heuristic, shadow)
        record = moments
        moments = moments or weights.shadow       # (pass 0: for its correction alone)
        n_light = budget.light_subpaths(lanes) if strategies.max_light_vertices() != -1 else 0
        # MIS rates of the pass: a vertex cache's kappa from the stored vertices per light
        # subpath of the last pass (the weights need a value before the light walk).
        rates = (n_light / lanes, budget.kappa(n_light, n_light * self._vertices_per_path))
        weights.set_rates(*rates)
        radius, eta = 0.0, 0.0
        if strategies.merging and n_light > 0:      # merging at rate pi r_i^2 N_L (mis.py)
            radius = (merge.pass_radius(self.merge_radius, self.settings.radius_alpha, index)
                      * budget.radius_scale)
            eta = math.pi * radius * radius * n_light
            weights.set_merging(eta)
        rates += (eta,)
        every = 1 if index < Pilot.PASSES or self._looks_again(index) else Pilot.moment_every(
            lanes, spp, self.settings.merging and not budget.merges)
        images = StrategyImages(self.strategies, lanes) if self.strategy_images else None
        return PassContext(
            scene=self.scene, camera=self.camera, settings=self.settings, budget=budget,
            strategies=strategies, weights=weights, emitters=self.emitters, media=self.media,
            camera_sampler=sampler, light_sampler=self._sampler(index, 1, max(n_light, 1), spp),
            lane=dr.arange(mi.UInt32, lanes), time=rays.ray.time,
            wavelengths=rays.ray.wavelengths, camera_weight=rays.weight,
            light_count=n_light, pick_offset=dr.opaque(mi.Float, _unit(self._seed_of(index), index)),
            noise_key=dr.opaque(mi.UInt32, _mix_seed(self._seed_of(index), index, 2) & 0xFFFFFFFF),
            images=images, pixel=rays.pixel,
            moments=(MomentSamples(lanes, every, weights.shadow, record, allocate=False,
                                   zeroed=self.timings is not None) if moments else None),
            mis_rates=rates,
            merge_radius=radius, scene_values=self._scene_values)

    def _render_pass(self, index, pixel_offset, n_pixels, spp, lanes):
        if (self._path_tracer is not None and index >= Pilot.PASSES
                and self.budget == PATH_TRACING and not self._looks_again(index)):
            return self._path_traced_pass(index, pixel_offset, n_pixels, spp, lanes)
        timer = _StageTimer(self.timings is not None, self.kernel_history)
        # Stage 1: camera rays.
        sampler = self._sampler(index, 0, lanes, spp)
        rays = self.camera.sample_rays(sampler, pixel_offset, n_pixels, spp,
                                       self._stride.get(index, 1))
        sampler.schedule_state()
        dr.eval(rays)
        ctx = self._context(index, rays, sampler, lanes, spp)
        rays_seconds = timer.lap()

        # Stage 2: light subpaths: stored light vertices and t = 1 splats.
        store, light_rays = self._light_subpaths(ctx, index, spp)
        light_seconds = timer.lap()
        if ctx.merge_radius > 0 and store is not None:
            ctx.grid = merge.HashGrid.build(store, ctx.merge_radius, ctx.light_count,
                                            shares=ctx.moments is not None)
            ctx.queries = merge.query_pool(ctx.strategies, lanes, ctx.moments is not None,
                                           self.memory_budget)
        grid_seconds = timer.lap()

        # Stage 3: camera subpaths, with every strategy t >= 2.
        cam = self._camera_subpaths(ctx, rays, store, lanes)
        # Every output the pass reads, in the walk's one kernel: an output evaluated
        # later would run the whole walk again (the pilot's slot counts did: 23 ms).
        dr.eval(cam.radiance, cam.hit, cam.rays, cam.slot, cam.specular_z1)
        camera_seconds = timer.lap()

        # Stage 4: film.
        self._put_camera(rays, cam, None if ctx.images is None else ctx.images.values, lanes)
        film_seconds = timer.lap()
        if store is not None:
            self._put_splats(index, store, ctx, lanes, pixel_offset)
        light_seconds += timer.lap()
        self.film.camera_samples += lanes
        totals = (dr.sum(cam.rays), dr.sum(light_rays))
        pilot = self._is_pilot_pass(index)
        if pilot:                   # the pilot's counts, all read in the same sync
            totals += self._pilot_counts(cam)
        counts = [int(n) for n in backend.read_values(*totals)]   # one launch, one read
        self.last_counts = counts[:2]                   # camera walk's rays, light walk's
        self.rays += counts[0] + counts[1]
        if timer.on:
            # The camera side as Mitsuba's path's megakernel has it: its rays' making,
            # the walk and the film's put; the light side with its splats' put.
            self.timings[index] = (light_seconds, rays_seconds + camera_seconds + film_seconds,
                                   grid_seconds)
        if pilot:
            if ctx.weights.shadow:
                self._pending.append((index, rays, ctx, store, lanes, pixel_offset))
            self._pilot_pass(index, ctx, store, cam, counts, lanes)
            for pending in self._pending if self.budget.merges else ():
                self._merging_after_all(*pending)
            self._pending = []
            if not self._pilot_kept:
                self.film.clear()
        elif ctx.moments is not None:
            ctx.moments.count = cam.slot
            self.pilot.costs.merge_eta = self.merge_eta(index)
            self.budget = self.pilot.redecide(
                ctx.moments, _splat_moments(ctx, store), self._luminance(),
                self.spp_done + n_pixels * spp / self.pixels, ctx.budget, ctx.mis_rates).budget
            self._replan(index)

    def _put_splats(self, index, store, ctx, lanes: int, pixel_offset: int):
        """The pass's light image on the film: the splats written, read by a kernel as
        wide as their count (one as wide as the pool, 5 slots per light subpath, took
        80 ms of 1.76 s on the point caustic, 128x128 256 spp, for 0.06 splats per
        light subpath).  A pilot pass keeps the splats in its own pixels (film.py);
        the mask is computed for every pass, so that all passes share one film kernel."""
        count = min(store.splats.size(), store.splats.capacity)
        if count == 0:
            return
        splats = gather(store.splats.items, dr.arange(mi.UInt32, count))
        stride = self._stride.get(index, 1)
        keep = (self.camera.grid_index(splats.pos) % dr.opaque(mi.UInt32, stride)
                == dr.opaque(mi.UInt32, pixel_offset % stride))
        self.film.put_splats(splats, ctx.wavelengths, lanes / ctx.light_count * stride, keep,
                             None if ctx.images is None else ctx.images.layer_of)

    def _merging_after_all(self, index, rays, ctx, store, lanes: int, pixel_offset: int):
        """The vcm pilot's BDPT pass merged for its moments only (its image BDPT's);
        where the decision keeps merging, its samples become the estimator with
        merging: each contribution x (1 - u_vm) (balance weights) and the merges added
        (MomentSamples.correction; the splats' -u_vm x value), with no weight of their
        own on the film."""
        wavelengths = rays.ray.wavelengths
        self.film.camera.put(rays.pos, wavelengths, ctx.moments.correction, 0.0, 0.0)
        count = 0 if store is None else min(store.splats.size(), store.splats.capacity)
        if count == 0:
            return
        splats = gather(store.splats.items, dr.arange(mi.UInt32, count))
        splats.value = splats.value * -splats.u_vm
        stride = self._stride.get(index, 1)
        keep = (self.camera.grid_index(splats.pos) % dr.opaque(mi.UInt32, stride)
                == dr.opaque(mi.UInt32, pixel_offset % stride))
        self.film.put_splats(splats, ctx.wavelengths, lanes / ctx.light_count * stride, keep)

    def _put_camera(self, rays, cam, images=None, lanes: int = 0):
        _put_camera(self.film, self.aovs, self._opaque, rays, cam.radiance, cam.hit, images,
                    lanes)

    def _path_traced_pass(self, index, pixel_offset, n_pixels, spp, lanes):
        """A pass after the pilot chose path tracing: Mitsuba's ``path`` on the pass's
        camera rays, recorded whole (``_recorded_path_pass``)."""
        seed = dr.opaque(mi.UInt32, _mix_seed(self.seed, index, 0))
        frozen.call(_recorded_path_pass, self.camera, self.sensor, seed, self._path_tracer,
                    self.scene, self.film, self.aovs, self._opaque, pixel_offset, n_pixels,
                    spp, self._stride.get(index, 1))
        dr.eval(*[block.tensor() for block in self.film.blocks()])
        self.film.camera_samples += lanes
        self.path_tracer_spp += n_pixels * spp / self.pixels

    @staticmethod
    def _pilot_counts(cam) -> tuple:
        """Sums of the pilot pass's camera walk (optimizer.Pilot.record): the
        connections' rays; the rays a light_first_hits budget would still trace (z_1's,
        and every ray of a lane that went on from z_1 through a delta lobe); with
        merging, the merge queries and the grid items they visited."""
        walk = cam.rays - cam.links
        sums = (dr.sum(cam.links),
                dr.sum(dr.select(cam.specular_z1, walk, dr.minimum(walk, 1))))
        if cam.merges is not None:
            sums += (dr.sum(cam.merges), dr.sum(cam.merge_items))
        return sums

    def _pilot_pass(self, index, ctx, store, cam, counts: list, lanes: int):
        """Record the pilot pass's counts and choose the budget."""
        camera_rays, light_rays, links, kept = counts[:4]
        walk_rays = camera_rays - links
        stored = 0 if store is None else store.vertices.size()
        self.pilot.record(lanes, walk_rays, links, ctx.light_count, light_rays, stored,
                          kept / max(walk_rays, 1))
        if len(counts) > 4:
            self.pilot.record_merging(lanes, counts[4], counts[5], ctx.mis_rates[2])
        ctx.moments.count = cam.slot
        # Where the pilot took one pixel in several, its light image is normalized as
        # if the round had every pixel's samples, and the means are its pixels'.
        stride = self._stride.get(index, 1)
        mean = self._luminance(self.pixels * self.plan[index][2] if stride > 1 else None)
        filled = self._pilot_pixels(mean.shape, stride) if stride > 1 else None
        self.pilot.pilot_eta = ctx.mis_rates[2]
        self.pilot.costs.merge_eta = self.merge_eta(self._pilot_round - 1)
        self.budget = self.pilot.decide(ctx.moments, _splat_moments(ctx, store), mean,
                                         self.plan[index][2], filled, stride).budget
        self._plan_second_look()
        self._replan(self._pilot_round - 1)

    def _plan_second_look(self) -> None:
        """Where the pilot chose path tracing on a large film, the pass that completes
        its round (the odd pixels) renders as the pilot does, BDPT with moments, and
        its samples decide again with the pilot's (optimizer.Pilot.redecide): twice the
        samples of the pilot's estimate before the render commits to path tracing,
        whose passes give no other candidate's moment (``_plan_rounds``).  Its samples
        stay in the image (the round's pixels have one sample each, as after the
        pilot's own pass).  Only where it costs at most SECOND_LOOK_SHARE more than
        path tracing those pixels would, of the render's price by the pilot's counts
        (no clock): from 130 spp up behind the glass pane, where the pilot prices full
        BDPT at 2.3x path tracing, 300 at 4x, 900 at 10x; not with merging (its pilot
        merges for its moments alone), nor on a cluster (``redecide``)."""
        self._second_look = False
        if (not self.redecide or self.budget.light_ratio > 0 or self._pilot_round != 2
                or self.settings.merging):
            return
        costs = self.pilot.costs
        pilot, path = costs.of(self.pilot.budget(Pilot.PASSES)[0]), costs.of(PATH_TRACING)
        extra = (pilot - path) * self.plan[Pilot.PASSES][1] * self.plan[Pilot.PASSES][2]
        self._second_look = extra <= SECOND_LOOK_SHARE * path * self.pixels * self.spp

    def _pilot_pixels(self, shape, stride: int) -> mi.Bool:
        """The crop pixels (H, W, flat) of a pilot pass over one pixel in ``stride``:
        those whose index in the sampled grid (camera.sample_rays: the crop plus a
        sampled filter border) is a multiple of it."""
        b = dr.opaque(mi.Int32, camera_stage.sampled_border(self.sensor.film()))
        y, x = rows_and_columns(shape)
        grid = (y + b) * (dr.opaque(mi.Int32, shape[1]) + 2 * b) + x + b
        return grid % dr.opaque(mi.Int32, stride) == 0

    def _luminance(self, camera_samples: int | None = None) -> mi.TensorXf:
        """The image so far, (H, W) on the device: the mean of its colour channels; its
        light image normalized by ``camera_samples`` if given
        (film.FilmAccumulator.develop)."""
        image = self.film.develop(camera_samples)
        h, w, channels = image.shape
        first = dr.arange(mi.UInt32, h * w) * channels
        rgb = [dr.gather(mi.Float, image.array, first + c) for c in range(3)]
        return mi.TensorXf((rgb[0] + rgb[1] + rgb[2]) / 3.0, (h, w))

    def _light_subpaths(self, ctx, index: int, spp: int):
        """Stage 2; runs the light walk again with larger pools if one overflowed
        (nothing has reached the film yet, and the sampler is seeded the same)."""
        n = ctx.light_count
        if n == 0:                                      # no strategy uses light subpaths
            return None, mi.UInt32(0)
        light = ctx.for_light_subpaths()
        per_path = self._capacity
        while True:
            store = LightVertexStore(n, n * per_path[0] if ctx.strategies.stores_vertices else 1,
                                     n * per_path[1], zeroed=self.timings is not None,
                                     allocate=False)
            light_rays, buffers = frozen.call(_recorded_light_walk, light, store)
            store.adopt(buffers)
            dr.eval(light_rays, store.vertices.items, store.splats.items, store.first)
            if not store.overflowed():
                break
            per_path[0] = max(per_path[0], -(-store.vertices.size() * 5 // (4 * n)))
            per_path[1] = max(per_path[1], -(-store.splats.size() * 5 // (4 * n)))
            # The larger pools replace these, not join them (Veach's room: 1.5x the peak).
            store = light_rays = buffers = None
            dr.flush_malloc_cache()
            self._outgrown = True       # the passes after this one: planned anew
            light.light_sampler = self._sampler(index, 1, n, spp)
        stored = store.vertices.size()
        if ctx.budget.connects:     # a budget without connections stores none
            self._vertices_per_path = max(stored / n, 1e-3)
        # A vertex cache's contributions are divided by the density of their pick.
        ctx.connection_scale = dr.opaque(mi.Float, 1.0 / max(ctx.budget.kappa(n, stored), 1e-20))
        ctx.stored = dr.opaque(mi.UInt32, max(stored, 1))
        if ctx.budget.caches:
            store.order = store.ordered()
        return store, light_rays

    def _camera_subpaths(self, ctx, rays, store, lanes: int):
        """Stage 3; where the pass defers its connections (connect.link_pool) and
        their pool overflowed, runs the camera walk again with a larger one (nothing
        has reached the film yet, and the walk's sampler and strategy images start
        again as they were)."""
        def links():
            return connect.link_pool(ctx.strategies, ctx.budget, lanes, ctx.moments is not None,
                                     ctx.media.present, self.memory_budget, self._links_per_lane)
        ctx.links = None if store is None else links()
        sampler = None if ctx.links is None else ctx.camera_sampler.clone()
        while True:
            cam = self._camera_walk(ctx, rays, store)
            if ctx.links is None or not ctx.links.overflowed():
                return cam
            self._links_per_lane = ctx.links.size() * 5 / (4 * lanes)
            self._outgrown = True       # the passes after this one: planned anew
            ctx.links, ctx.camera_sampler = links(), sampler.clone()
            if ctx.images is not None:
                ctx.images = StrategyImages(self.strategies, lanes)

    @staticmethod
    def _camera_walk(ctx, rays, store):
        """Stage 3's walk, replayed where recorded (frozen.py), the moment samples'
        buffers and the deferred connections' pool made inside it (see
        ``_recorded_light_walk``).  With strategy images it is traced: their layers,
        lanes x strategies, would be copied by every replay."""
        if ctx.images is not None:
            return _recorded_camera_walk(ctx, rays, store)[0]
        cam, buffers, links = frozen.call(_recorded_camera_walk, ctx, rays, store)
        if ctx.moments is not None:
            ctx.moments.adopt(buffers)
        if ctx.links is not None:
            ctx.links.adopt_count(links)
        return cam

    # -- results -------------------------------------------------------------------
    def load_raw(self, raw: dict | None, passes: int, time: float = 0.0, rays: int = 0) -> None:
        """Make the film hold ``raw``: the film sums (``film.raw()``) of passes 0 to
        ``passes`` - 1 of this plan, rendered elsewhere and added up (cluster.py), and
        count those passes as this renderer's, with their render ``time`` and ``rays``:
        ``result()`` then develops them."""
        self.film.clear()
        if raw:
            self.film.add_raw(raw)
        self.passes_done = int(passes)
        self.spp_done = sum(self.pass_spp(i) for i in range(passes))
        self.time, self.rays = float(time), int(rays)

    def _walk_samples(self) -> float:
        """Camera samples of this engine's walks (``rays`` counts their rays): the
        image's that Mitsuba's path did not render, and a pilot's that were dropped."""
        dropped = (self._pilot_round and not self._pilot_kept and self.passes_done
                   and not self._pilot_reused)
        return ((self.spp_done - self.path_tracer_spp) * self.pixels
                + (self.plan[0][1] * self.plan[0][2] if dropped else 0))

    def tensor(self) -> mi.TensorXf:
        return self.film.develop()

    def result(self) -> RenderResult:
        tensor = self.tensor()
        layers = self.film.develop_layers() if self.strategy_images else {}
        return RenderResult(image=tensor.numpy(), tensor=tensor, aov_names=self.film.aov_names,
                            strategy_images={k: v.numpy() for k, v in layers.items()
                                             if k[0] not in ("k", "vm")},
                            merge_image=(layers[MERGE_LAYER].numpy() if MERGE_LAYER in layers
                                         else None),
                            length_images={k[1]: v.numpy() for k, v in layers.items() if k[0] == "k"},
                            spp=int(self.spp_done + 1e-9), passes=self.passes_done, time=self.time,
                            rays=self.rays, kernel_history=list(self.kernel_history),
                            stats={"pixels": self.pixels,
                                   "lanes_per_pass": max(p[1] * p[2] for p in self.plan),
                                   "rays_per_sample": self.rays / max(1, self._walk_samples()),
                                   "path_tracer_spp": self.path_tracer_spp,
                                   "budget": str(self.budget), "decision": self.decision_text(),
                                   **self.cost_stats()})

    def cost_stats(self) -> dict:
        """What the decision priced (optimizer.Costs): the pilot's counts and the unit
        costs; nothing for a fixed budget."""
        if self.pilot is None:
            return {}
        return {"cost_counts": self.pilot.costs.describe(),
                "unit_costs": self.pilot.costs.units.describe()}

    def decision_text(self) -> str:
        """Why the render uses its budget (for logs and the EXR header)."""
        if self.pilot is None:
            fixed = fixed_budget(self.settings)
            return ("fixed by the settings" if fixed is not None else
                    "full BDPT: strategy images" if self.strategy_images else
                    "full BDPT: fewer than %d spp, or a film split in pixel ranges" % MIN_SPP)
        if self.pilot.decision is None:
            return "pilot pass pending"
        by_path = self._path_tracer is not None and self.budget == PATH_TRACING
        rounds = "".join("; after %g spp %s" % (spp, b) for spp, b in self.pilot.rounds)
        return ((self.pilot.first or self.pilot.decision).describe()
                + ("; the pilot of an earlier render of this scene" if self._pilot_reused else "")
                + rounds + ("; its path-tracing passes run Mitsuba's path" if by_path else ""))


# The seed of a dropped pilot pass's random numbers (Renderer._seed_of).
PILOT_SEED = 0x5EED
# The share of a render's priced cost that a pilot's second look may add
# (Renderer._plan_second_look).  Its pass also costs what the price leaves out, a
# pilot pass's fixed cost (about 8 ms at 128x128 on the CPU): behind the glass pane
# 1.02-1.03x the time at 128x128 and 128 spp, 0.98-1.02x at 256-512, 1.007x at
# 256x256 and 256 spp (benchmarks/experiments/second_look.py).
SECOND_LOOK_SHARE = 0.005


class _ReusedPilot:
    """The outcome of the last small render's pilot, for the next render of the same
    scene state, sensor, settings, film, spp, unit costs and variant.  A pilot whose
    samples are dropped (optimizer.Pilot.stride) draws the same random numbers in
    every render (PILOT_SEED), so its decision, and what its pass changed besides (the
    plan after it, the pools' capacities, the stored vertices per light subpath), rest
    on those alone: a render that takes them and skips the pass renders the image it
    would have rendered, the same for its seed as in a fresh process, without the
    pilot's cost.  One entry, as support.facts keeps one scene; its ``facts`` object
    is the same exactly while the scene's state is."""
    key: tuple | None = None
    outcome: tuple | None = None

    @staticmethod
    def _key(r: Renderer) -> tuple:
        return (r._facts, r.settings, r.pixels, r.spp, r.pilot.costs.units, mi.variant())

    @classmethod
    def keep(cls, r: Renderer) -> None:
        if r._facts is None:
            return
        cls.key = cls._key(r)
        cls.outcome = (copy.deepcopy(r.pilot), r.budget, list(r.plan), set(r._moment_passes),
                       list(r._capacity), r._vertices_per_path)

    @classmethod
    def restore(cls, r: Renderer) -> None:
        key = cls._key(r)
        if r._facts is None or cls.key is None or key[0] is not cls.key[0] or key[1:] != cls.key[1:]:
            return
        pilot, budget, plan, moment_passes, capacity, per_path = cls.outcome
        r.pilot, r.budget, r.plan = copy.deepcopy(pilot), budget, list(plan)
        r._moment_passes, r._capacity = set(moment_passes), list(capacity)
        r._vertices_per_path = per_path
        r.passes_done, r._pilot_reused = 1, True       # pass 0, the pilot, is done


# The calibration render: the Cornell box on a film of RES^2 pixels, so that the pilot
# pass takes half of it at 1 sample (optimizer.Pilot.stride), and a pass of light and
# path tracing on a film of half of it, each at the occupancy of real passes: 32768
# lanes on a CPU (on 2 cores the camera walk timed 1.8x dearer per sample over 16384
# lanes than over 32768), 2^21 on a GPU (an H100 holds 132 x 2048 threads, and a
# launch of a few of those waits on its longest lanes: at 2^18 lanes the walks and
# Mitsuba's path were priced 1.3x apart from the 7M- and 16M-lane passes they price).
CALIBRATION_LANES = {"llvm": 1 << 15, "cuda": 1 << 21}
# Bytes per lane that a GPU's calibration passes may take of the memory budget (the
# pilot pass's walks and moment samples, Veach's room's 1.9 KB at most).
CALIBRATION_LANE_BYTES = 2048


def _calibration_res() -> int:
    """The calibration film's side: twice the pilot's lanes in pixels, as many as the
    backend's default memory budget holds."""
    lanes = CALIBRATION_LANES["cuda" if backend.is_cuda() else "llvm"]
    lanes = min(lanes, backend.default_memory_budget() // CALIBRATION_LANE_BYTES)
    return int(math.sqrt(2 * lanes))


def _path_spp(pixels: int) -> int:
    """Samples per pixel of the calibration's render of Mitsuba's path: 4, or on a GPU
    a pass of path tracing's size (backend.path_pass_lanes) as real passes run it."""
    if not backend.is_cuda():
        return 4
    return max(4, backend.path_pass_lanes(backend.default_memory_budget()) // pixels)


def calibrate(repeats: int = 5) -> UnitCosts:
    """Measure this machine's unit costs for the current variant (units.py) and store
    them: the kernel seconds of the walks on the Cornell box per unit of work they
    counted, and Mitsuba's path per ray, each the median of ``repeats`` warm runs
    (the first run, which compiles, is left out)."""
    variant = mi.variant()
    print("bdpt: measuring this machine's unit costs for %s, a few seconds (stored for "
          "later renders; 'bdpt calibrate' measures again)" % variant, file=sys.stderr, flush=True)
    res = _calibration_res()
    scenes = []
    for width, height in ((res, res), (res, res // 2)):
        box = mi.cornell_box()
        box["sensor"]["film"].update(width=width, height=height)
        scenes.append(mi.load_dict(box))
    _calibration_run(*scenes, 0)                   # (it compiles: not counted)
    wall, cpu = time.perf_counter(), time.process_time()
    rows = [_calibration_run(*scenes, seed) for seed in range(1, repeats + 1)]
    share = ((time.process_time() - cpu) / max(time.perf_counter() - wall, 1e-9)
             / max(dr.thread_count(), 1))
    measured = UnitCosts(*(float(v) for v in np.median(np.array(rows), axis=0)))
    units.save(measured)
    busy = units.busy_warning(variant, share)
    if busy:
        warnings.warn(busy, stacklevel=2)
    return measured


def _timed_pass(scene, seed: int, **settings):
    """The first pass of a render at 1 sample per pixel, timed: (the Renderer, kernel
    seconds per camera sample of its light side (the walk, the splats' put), its camera
    side (the rays' making, the walk, the film's put: as Mitsuba's path's megakernel,
    which path_ray prices) and the grid build)."""
    r = Renderer(scene, spp=16, seed=seed, max_depth=8, unit_costs=UnitCosts(),
                 samples_per_pass=0 if settings.get("light_paths") is None else 1, **settings)
    r.timings = {}
    r.render_pass(0)
    _, n, spp = r.plan[0]
    return r, tuple(t / (n * spp) for t in r.timings[0])


def _calibration_run(scene, half, seed: int) -> tuple:
    """One run's unit costs, in UnitCosts' order: a pass of light and path tracing
    on ``half``, then the pilot pass (full BDPT) on ``scene``."""
    r0, (light0, camera0, _) = _timed_pass(half, seed, light_paths=1, connections=0)
    lanes0 = r0.plan[0][1] * r0.plan[0][2]
    camera_rays0, light_rays0 = (n / lanes0 for n in r0.last_counts)
    r, (light1, camera1, _) = _timed_pass(scene, seed)
    c = r.pilot.costs
    camera_ray = camera0 / camera_rays0
    light_ray = light0 / light_rays0            # one light subpath per camera sample
    # The pilot pass's walks less the same rays at those prices: its stored vertices
    # and its connections.
    stored = max(light1 - light_ray * c.light_rays, 0.0) / c.stored_per_path
    connection = max(camera1 - camera_ray * c.camera_rays, 0.0) / max(c.connection_rays, 1e-9)
    path = mi.load_dict({"type": "path", "max_depth": 8})
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        spp = _path_spp(r.pixels)
        dr.eval(mi.render(scene, integrator=path, spp=spp, seed=seed))
        dr.sync_thread()
        seconds = sum(e.get("execution_time", 0.0) for e in dr.kernel_history()
                      if e["type"] == dr.KernelType.JIT) / 1000.0
    path_ray = seconds / (r.pixels * spp) / c.camera_rays
    return (camera_ray, light_ray, stored, connection, path_ray) + _merge_units(scene, seed, camera1)


def _merge_units(scene, seed: int, camera1: float) -> tuple:
    """(grid_vertex, merge_step): the pilot pass again with merging (the same
    samples), its grid build per stored vertex and the camera walk's extra time per
    query step (optimizer.QUERY_STEPS per query and one per item visited,
    optimizer.Costs.merging).
    Spectral variants do not merge: 0, 0."""
    if mi.is_spectral:
        return 0.0, 0.0
    r, (_, camera, grid) = _timed_pass(scene, seed, merging=True)
    c = r.pilot.costs
    steps = QUERY_STEPS * c.merges + c.merge_items * r.pilot.pilot_eta
    return (grid / max(c.stored_per_path, 1e-9),
            max(camera - camera1, 0.0) / max(steps, 1e-9))
