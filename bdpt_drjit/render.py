"""The renderer: passes of wavefronts, each a list of named stages.

    for each pass:
        camera rays       camera.sample_camera_rays      one lane per pixel sample
        light subpaths    walk.trace_light_subpaths      + t = 1 splats; stores y_i
        camera subpaths   walk.trace_camera_subpaths     + s = 0, s = 1, and s, t >= 2
                          (connect.connect_vertices: z_j to every stored y_i, in
                          the kernel of depth j, while z_j's interaction is live)
        film              film.FilmAccumulator           camera block + light block

Each camera sample i is paired with light subpath i (N_L = N_C), so the light image
is normalized by W*H / (total camera samples) and MIS uses N_L / N_C = 1.
Passes split the work so that vertex buffers stay under a memory budget; a pass
covers all pixels at ``spp_pass`` samples, or a range of pixels at 1 sample for
very large films.  Peak memory therefore does not grow with spp.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from . import camera as camera_stage
from .compact import SparseLights
from .emitters import Emitters
from .film import FilmAccumulator
from .mis import Heuristic
from .settings import Settings
from .walk import trace_camera_subpaths, trace_light_subpaths

# Bytes per lane: stored light vertices (compact interaction, throughput, MIS
# state: 141 bytes each, at most max_depth of them) and the transient state of one
# depth step.  Calibrated on peak RSS (Cornell box, 1920x1080, 1 spp): 1221 bytes per
# lane at max_depth 8, 1501 at max_depth 10; the estimate below errs high.
_VERTEX_BYTES = 145
_LANE_BYTES = 400


@dataclass
class PassContext:
    """What the stages of one pass share."""
    scene: mi.Scene
    sensor: mi.Sensor
    settings: Settings
    emitters: Emitters
    h: Heuristic
    film: FilmAccumulator
    camera_sampler: mi.Sampler
    light_sampler: mi.Sampler
    time: mi.Float = None
    wavelengths: mi.UnpolarizedSpectrum = None
    camera_weight: mi.Spectrum = None
    rays: mi.UInt32 = None
    light_ratio: float = 1.0        # N_L / N_C

    @property
    def use_mis(self) -> bool:
        return self.settings.technique is None and self.settings.strategy_subset != "lt"

    def connects(self, i: int) -> bool:
        """Does some enabled strategy s, t >= 2 connect light vertex y_i?"""
        st = self.settings
        if st.technique is not None:
            return st.technique[0] == i + 1 and st.technique[1] >= 2 and self.enabled(*st.technique)
        # Unbounded depth: whether (i+1, t) is enabled does not depend on t >= 2.
        t_max = st.max_depth + 1 if st.max_depth >= 0 else 2
        return any(self.enabled(i + 1, t) for t in range(2, t_max + 1))

    @property
    def pt_only(self) -> bool:
        return self.settings.strategy_subset == "pt"

    def enabled(self, s: int, t: int) -> bool:
        st = self.settings
        k = s + t - 1
        if k < 1 or (st.max_depth >= 0 and k > st.max_depth):
            return False
        if st.technique is not None and st.technique != (s, t):
            return False
        if st.strategy_subset == "pt" and not (s <= 1 and t >= 2):
            return False
        if st.strategy_subset == "lt" and t != 1:
            return False
        if t == 1 and not st.light_image:
            return False
        if st.hide_emitters and k == 1:
            return False
        if self.emitters.count == 0:
            return False
        return True


@dataclass
class RenderResult:
    """What ``render`` returns.  ``image`` is an (H, W, C) float32 NumPy array."""
    image: np.ndarray
    tensor: mi.TensorXf
    strategies: dict = field(default_factory=dict)
    spp: int = 0
    passes: int = 0
    time: float = 0.0
    rays: int = 0
    stats: dict = field(default_factory=dict)

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


class Renderer:
    """A progressive BDPT render of one sensor: call ``run_pass`` until ``done``.

    ``bdpt_drjit.render`` drives it to the end; the command line drives it pass by
    pass to show progress, write checkpoints and stop on a signal or time budget.
    """

    def __init__(self, scene: mi.Scene, sensor=0, spp: int | None = None, seed: int = 0,
                 strategy_images: bool = False, **settings):
        check_variant()
        if isinstance(sensor, (int, np.integer)):
            sensors = scene.sensors()
            if not sensors:
                raise ValueError("bdpt: the scene has no sensor")
            if not 0 <= sensor < len(sensors):
                raise ValueError("bdpt: sensor index %d is out of range: the scene has %d "
                                 "sensor%s (indices 0 to %d)" % (sensor, len(sensors),
                                 "" if len(sensors) == 1 else "s", len(sensors) - 1))
            sensor = sensors[int(sensor)]
        camera_stage.check_sensor(sensor)
        self.scene, self.sensor = scene, sensor
        self.settings = Settings.from_dict(settings)
        self.emitters = Emitters(scene)
        if self.emitters.count == 0:
            warnings.warn("bdpt: the scene has no emitters; the image is black", stacklevel=2)
        self.seed = int(seed)
        self.strategy_images = strategy_images
        film = sensor.film()
        grid = camera_stage.film_grid(film)
        self.pixels = int(grid[0]) * int(grid[1])
        self.spp = int(spp) if spp else sensor.sampler().sample_count()
        if self.spp <= 0:
            raise ValueError("bdpt: spp must be positive, got %d" % self.spp)
        self._plan()
        self.film = FilmAccumulator(film, coalesce=self.spp >= 4, strategy_images=strategy_images)
        self.spp_done = 0
        self.passes_done = 0
        self.time = 0.0
        self.rays = 0
        self._sample_count = 0       # camera samples = light paths so far
        self._last_lanes = 0

    # -- planning ----------------------------------------------------------------
    def _lane_bytes(self) -> int:
        d = self.settings.max_depth if self.settings.max_depth >= 0 else 24
        return d * _VERTEX_BYTES + _LANE_BYTES

    def _plan(self) -> None:
        """Split spp x pixels into passes of at most ``max_lanes`` lanes.

        Automatic passes are made equal in size: Dr.Jit keeps freed buffers for
        reuse by requests of the same size, so a smaller last pass would allocate a
        second set beside the cached first one (measured: 1.9 -> 3.0 GB at 1920x1080
        with passes of 1.38M and 0.70M lanes; 1.3 GB with two equal ones)."""
        max_lanes = max(1024, self.settings.memory_budget // self._lane_bytes())
        max_lanes = min(max_lanes, 2 ** 31)
        explicit = self.settings.samples_per_pass
        # An explicit samples_per_pass is honoured up to the memory budget.
        per_pass = min(explicit or self.spp, max(1, max_lanes // self.pixels), self.spp)
        if not explicit or per_pass < explicit:
            per_pass = -(-self.spp // -(-self.spp // per_pass))    # equal passes
        passes = []
        if self.pixels * per_pass <= max_lanes:
            done = 0
            while done < self.spp:
                # Some samplers round the count (orthogonal: to a prime squared); a
                # pass then takes what the sampler accepts, as Mitsuba's render does.
                n = self._accepted_count(min(per_pass, self.spp - done))
                passes.append((0, self.pixels, n))
                done += n
        else:                          # very large film: equal pixel ranges at 1 spp
            chunks = -(-self.pixels // max_lanes)
            chunk = -(-self.pixels // chunks)
            for _ in range(self.spp):
                for start in range(0, self.pixels, chunk):
                    passes.append((start, min(chunk, self.pixels - start), 1))
        self.plan = passes

    def _accepted_count(self, n: int) -> int:
        sampler = self.sensor.sampler().clone()
        sampler.set_sample_count(n)
        return sampler.sample_count()

    @property
    def done(self) -> bool:
        return self.passes_done >= len(self.plan)

    # -- one pass -----------------------------------------------------------------
    def _sampler(self, stream: int, pass_index: int, lanes: int, spp: int) -> mi.Sampler:
        sampler = self.sensor.sampler().clone()
        sampler.set_sample_count(spp)
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(_mix_seed(self.seed, pass_index, stream), lanes)
        return sampler

    def _max_vertices(self):
        """How many camera and light vertices the enabled strategies can use."""
        st = self.settings
        if st.technique is not None:
            s, t = st.technique
            return t - 1, (s - 1 if s >= 2 else 0)
        if st.max_depth < 0:
            return None, None
        if st.strategy_subset == "pt":
            return st.max_depth, -1
        if st.strategy_subset == "lt":
            return 0, st.max_depth - 1
        return st.max_depth, st.max_depth - (1 if st.light_image else 2)

    def run_pass(self) -> None:
        if self.done:
            return
        pixel_offset, n_pixels, spp = self.plan[self.passes_done]
        lanes = n_pixels * spp
        if self.passes_done and lanes != self._last_lanes:
            # Buffers cached for the previous size would sit beside this pass's.
            dr.flush_malloc_cache()
        self._last_lanes = lanes
        start = time.perf_counter()
        with dr.suspend_grad():
            self._render_pass(pixel_offset, n_pixels, spp, lanes)
        self.time += time.perf_counter() - start
        self.passes_done += 1
        self.spp_done = sum(p[1] * p[2] for p in self.plan[:self.passes_done]) // self.pixels

    def _render_pass(self, pixel_offset, n_pixels, spp, lanes):
        pass_index = self.passes_done
        cam_sampler = self._sampler(0, pass_index, lanes, spp)
        ctx = PassContext(scene=self.scene, sensor=self.sensor, settings=self.settings,
                          emitters=self.emitters, h=Heuristic(self.settings.mis),
                          film=self.film, camera_sampler=cam_sampler,
                          light_sampler=self._sampler(1, pass_index, lanes, spp))
        ctx.rays = dr.zeros(mi.UInt32, lanes)
        max_cam, max_light = self._max_vertices()

        # Stage 1: camera rays.
        cam = camera_stage.sample_camera_rays(self.sensor, cam_sampler, pixel_offset, n_pixels, spp)
        ctx.time, ctx.wavelengths, ctx.camera_weight = cam.ray.time, cam.ray.wavelengths, cam.weight
        cam_sampler.schedule_state()
        dr.eval(cam)

        # Stage 2: light subpaths (+ t = 1 splats).
        light_vertices, sparse = [], SparseLights(ctx, lanes)
        if self.emitters.count and (max_light is None or max_light >= 0) and (
                max_light != 0 or self.settings.light_image):
            light_vertices = trace_light_subpaths(ctx, max_light, sparse)

        # Stage 3: camera subpaths (+ s = 0, s = 1, and s, t >= 2 connections to the
        # stored light vertices, in the same kernel per depth).
        radiance = trace_camera_subpaths(ctx, cam, max_cam, light_vertices, sparse)

        # Stage 4: film.
        self.film.put_camera(cam.pos, cam.ray.wavelengths, radiance, 1.0)
        self.film.light_paths += lanes
        self.rays += int(dr.sum(ctx.rays)[0])

    # -- results -------------------------------------------------------------------
    def tensor(self) -> mi.TensorXf:
        return self.film.develop()

    def result(self) -> RenderResult:
        tensor = self.tensor()
        strategies = {}
        if self.strategy_images:
            strategies = {k: v.numpy() for k, v in self.film.develop_strategies().items()}
        return RenderResult(image=tensor.numpy(), tensor=tensor, strategies=strategies,
                            spp=self.spp_done, passes=self.passes_done, time=self.time,
                            rays=self.rays,
                            stats={"pixels": self.pixels, "lanes_per_pass": max(p[1] * p[2] for p in self.plan),
                                   "rays_per_sample": self.rays / max(1, self.spp_done * self.pixels)})


def render(scene, spp: int | None = None, seed: int = 0, sensor=0,
           strategy_images: bool = False, **settings) -> RenderResult:
    """Render ``scene`` (a ``mi.Scene`` or a path to an XML file) with BDPT.

    Keyword settings: max_depth (-1), rr_depth (5), mis ("power" | "balance" |
    "uniform" | "lafortune"), light_image (True), hide_emitters (False), technique
    (None or (s, t) / "s,t"), strategies ("all" | "pt" | "lt"), samples_per_pass
    (0 = automatic), memory_budget (bytes).
    With ``strategy_images=True`` the result's ``strategies[(s, t)]`` holds every
    strategy's MIS-weighted image; they sum to ``image``.
    """
    if isinstance(scene, str):
        scene = mi.load_file(scene)
    r = Renderer(scene, sensor=sensor, spp=spp, seed=seed, strategy_images=strategy_images,
                 **settings)
    while not r.done:
        r.run_pass()
    return r.result()
