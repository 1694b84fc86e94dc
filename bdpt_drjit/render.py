"""The renderer: passes, each a list of named stages.

    for each pass:
        camera rays        camera.Camera.sample_rays     one lane per pixel sample
        light subpaths     walk.trace_light_subpaths     y_i stored for connections,
                                                         t = 1 splats (splat.py)
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

import os
import time
import warnings
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from . import camera as camera_stage
from .emitters import Emitters
from .film import FilmAccumulator
from .mis import Weights
from .settings import Settings
from .strategies import StrategyImages, StrategySet
from .vertices import RECORD_BYTES, SPLAT_BYTES, LightVertexStore
from .walk import trace_camera_subpaths, trace_light_subpaths

# Bytes per lane besides the pools: camera rays, radiance, the lane's list head and
# the samplers' state (the walks' state lives in registers of the loop kernels).
_LANE_BYTES = 160
# Stored light vertices and splats per lane a pass plans for (measured: 3.0 and 3.2
# on the Cornell box, at max_depth 8 and -1 alike; 2.6 and 3.4 with its glass and
# mirror spheres).  A pass that needs more runs its light walk again with larger pools.
_VERTICES_PER_LANE = 4
_SPLATS_PER_LANE = 5


@dataclass
class PassContext:
    """What the stages of one pass share; the walks only read it."""
    scene: mi.Scene
    camera: camera_stage.Camera
    settings: Settings
    strategies: StrategySet
    weights: Weights
    emitters: Emitters
    camera_sampler: mi.Sampler
    light_sampler: mi.Sampler
    lane: mi.UInt32                    # each lane's own index (pools, strategy images)
    time: mi.Float                     # per lane, shared by its two subpaths
    wavelengths: mi.UnpolarizedSpectrum
    camera_weight: mi.Spectrum         # sensor sampling weight (spectral response)
    light_ratio: mi.Float              # N_L / N_C
    images: StrategyImages | None = None


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
    spp: int = 0
    passes: int = 0
    time: float = 0.0
    rays: int = 0
    stats: dict = field(default_factory=dict)

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
    passes = []
    if pixels * per_pass <= max_lanes:
        done = 0
        while done < spp:
            n = accepted(min(per_pass, spp - done))
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
                 strategy_images: bool = False, **settings):
        check_variant()
        self.sensor = camera_stage.select_sensor(scene, sensor)
        self.camera = camera_stage.Camera(self.sensor)
        self.scene = scene
        self.settings = Settings.from_dict(settings)
        self.emitters = Emitters(scene)
        if self.emitters.count == 0:
            warnings.warn("bdpt: the scene has no emitters; the image is black", stacklevel=2)
        self.strategies = StrategySet(self.settings, self.emitters.count > 0)
        self.weights = Weights(self.settings.mis, self.strategies)
        self.seed = int(seed)
        self.strategy_images = strategy_images
        film = self.sensor.film()
        grid = camera_stage.film_grid(film)
        self.pixels = int(grid[0]) * int(grid[1])
        self.spp = int(spp) if spp else self.sensor.sampler().sample_count()
        if self.spp <= 0:
            raise ValueError("bdpt: spp must be positive, got %d" % self.spp)
        layers = self.strategies.layers() if strategy_images else []
        lane_bytes = (_LANE_BYTES + _VERTICES_PER_LANE * RECORD_BYTES
                      + _SPLATS_PER_LANE * SPLAT_BYTES + len(layers) * 16)
        max_lanes = min(max(1024, self.settings.memory_budget // lane_bytes), 2 ** 31)
        self.plan = plan_passes(self.spp, self.pixels, max_lanes, self.settings.samples_per_pass,
                                self._accepted_count)
        self.film = FilmAccumulator(film, coalesce=self.spp >= 4, layers=layers)
        self.passes_done = 0
        self.spp_done = 0.0           # samples per pixel rendered (fractional: pixel ranges)
        self.time = 0.0
        self.rays = 0
        self._last_lanes = 0
        self._capacity = {}          # pool capacities per lane, raised on overflow

    def _accepted_count(self, n: int) -> int:
        sampler = self.sensor.sampler().clone()
        sampler.set_sample_count(n)
        return sampler.sample_count()

    @property
    def done(self) -> bool:
        return self.passes_done >= len(self.plan)

    @property
    def at_round_end(self) -> bool:
        """Every pixel has had the same number of camera samples, so the image is
        unbiased here.  Only a very large film, split into pixel ranges, is ever
        between rounds: a stop there would leave pixels with the light image alone."""
        return abs(self.spp_done - round(self.spp_done)) < 1e-6

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
        with dr.suspend_grad():
            self._render_pass(index, pixel_offset, n_pixels, spp, lanes)
        self.time += time.perf_counter() - start
        self.passes_done += 1
        self.spp_done += n_pixels * spp / self.pixels

    # -- one pass -----------------------------------------------------------------------
    def _sampler(self, index: int, stream: int, lanes: int, spp: int) -> mi.Sampler:
        sampler = self.sensor.sampler().clone()
        sampler.set_sample_count(spp)
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(_mix_seed(self.seed, index, stream), lanes)
        return sampler

    def _context(self, index, rays, sampler, lanes: int, spp: int) -> PassContext:
        images = StrategyImages(self.strategies, lanes) if self.strategy_images else None
        return PassContext(
            scene=self.scene, camera=self.camera, settings=self.settings,
            strategies=self.strategies, weights=self.weights, emitters=self.emitters,
            camera_sampler=sampler, light_sampler=self._sampler(index, 1, lanes, spp),
            lane=dr.arange(mi.UInt32, lanes), time=rays.ray.time,
            wavelengths=rays.ray.wavelengths, camera_weight=rays.weight,
            light_ratio=dr.opaque(mi.Float, 1.0), images=images)

    def _render_pass(self, index, pixel_offset, n_pixels, spp, lanes):
        # Stage 1: camera rays.
        sampler = self._sampler(index, 0, lanes, spp)
        rays = self.camera.sample_rays(sampler, pixel_offset, n_pixels, spp)
        sampler.schedule_state()
        dr.eval(rays)
        ctx = self._context(index, rays, sampler, lanes, spp)

        # Stage 2: light subpaths: stored light vertices and t = 1 splats.
        store, light_rays = self._light_subpaths(ctx, index, lanes, spp)

        # Stage 3: camera subpaths, with every strategy t >= 2.
        cam = trace_camera_subpaths(ctx, rays, store)
        dr.eval(cam.radiance, cam.hit, cam.rays)

        # Stage 4: film.
        self.film.put_camera(rays, cam.radiance, cam.hit,
                             None if ctx.images is None else ctx.images.values, lanes)
        if store is not None:
            self.film.put_splats(store.splats.items, store.splats.size(), ctx.wavelengths,
                                 None if ctx.images is None else ctx.images.layer_of)
        self.film.light_paths += lanes
        self.rays += int(dr.sum(cam.rays + light_rays)[0])

    def _light_subpaths(self, ctx, index: int, lanes: int, spp: int):
        """Stage 2; runs the light walk again with larger pools if one overflowed
        (nothing has reached the film yet, and the sampler is seeded the same)."""
        max_i = self.strategies.max_light_vertices()
        if max_i is not None and max_i < 0:             # no strategy uses light subpaths
            return None, dr.zeros(mi.UInt32, lanes)
        per_lane = self._capacity.setdefault(lanes, [_VERTICES_PER_LANE, _SPLATS_PER_LANE])
        while True:
            store = LightVertexStore(lanes, lanes * per_lane[0], lanes * per_lane[1])
            light_rays = trace_light_subpaths(ctx, store)
            dr.eval(light_rays, store.vertices.items, store.splats.items, store.first)
            if not store.overflowed():
                return store, light_rays
            per_lane[0] = max(per_lane[0], -(-store.vertices.size() * 5 // (4 * lanes)))
            per_lane[1] = max(per_lane[1], -(-store.splats.size() * 5 // (4 * lanes)))
            ctx.light_sampler = self._sampler(index, 1, lanes, spp)

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
        self.spp_done = sum(n * spp for _, n, spp in self.plan[:passes]) / self.pixels
        self.time, self.rays = float(time), int(rays)

    def tensor(self) -> mi.TensorXf:
        return self.film.develop()

    def result(self) -> RenderResult:
        tensor = self.tensor()
        layers = self.film.develop_layers() if self.strategy_images else {}
        return RenderResult(image=tensor.numpy(), tensor=tensor,
                            strategy_images={k: v.numpy() for k, v in layers.items() if k[0] != "k"},
                            length_images={k[1]: v.numpy() for k, v in layers.items() if k[0] == "k"},
                            spp=int(self.spp_done + 1e-9), passes=self.passes_done, time=self.time,
                            rays=self.rays,
                            stats={"pixels": self.pixels,
                                   "lanes_per_pass": max(p[1] * p[2] for p in self.plan),
                                   "rays_per_sample": self.rays / max(1, self.spp_done * self.pixels)})


def render(scene, spp: int | None = None, seed: int = 0, sensor=0,
           strategy_images: bool = False, cluster: str | None = None,
           scene_params: dict | None = None, **settings) -> RenderResult:
    """Render ``scene`` (a ``mi.Scene`` or a path to an XML file) with BDPT.

    Keyword settings: see ``bdpt_drjit.settings.PARAMS`` (max_depth, rr_depth, mis,
    light_image, hide_emitters, technique, strategy_subset, samples_per_pass,
    memory_budget).  With ``strategy_images=True`` the result's
    ``strategy_images[(s, t)]`` holds every strategy's MIS-weighted image; they sum
    to ``image``.  ``scene_params``: the XML file's parameters ($name).
    ``cluster``: render the passes on Ray workers (``"local:N"``, ``"auto"`` or a Ray
    address; ``scene`` must then be a file path): the same estimator (cluster.py).
    """
    if cluster is not None:
        from .cluster import render_on_cluster
        return render_on_cluster(scene, cluster, spp=spp, seed=seed, sensor=sensor,
                                 strategy_images=strategy_images, scene_params=scene_params,
                                 **settings)
    if isinstance(scene, (str, os.PathLike)):
        scene = mi.load_file(str(scene), **(scene_params or {}))
    elif scene_params:
        raise ValueError("bdpt: scene_params apply to a scene file, not to a loaded mi.Scene")
    r = Renderer(scene, sensor=sensor, spp=spp, seed=seed, strategy_images=strategy_images,
                 **settings)
    while not r.done:
        r.run_pass()
    return r.result()
