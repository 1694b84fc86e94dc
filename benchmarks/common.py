"""Shared helpers of the benchmarks: paths, methods, timed renders, error metrics,
reference images and machine information.

Importing this module imports ``bdpt_drjit`` (which selects ``llvm_ad_rgb``) and turns
on Dr.Jit's kernel history, which the timers use to separate compilation from running.
"""
from __future__ import annotations

import dataclasses
import datetime
import inspect
import json
import math
import os
import platform
import re
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import bdpt_drjit  # noqa: F401  (selects llvm_ad_rgb, registers "bdpt")
import drjit as dr
import mitsuba as mi

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
SHARED = Path(os.environ.get("BDPT_SHARED") or ROOT.parent / "shared")
EXTERNAL = SHARED / "scenes" / "external"
RESULTS = BENCH / "results"
CHARTS = BENCH / "charts"

dr.set_flag(dr.JitFlag.KernelHistory, True)


def log(*args) -> None:
    print(*args, flush=True)


# -- methods ------------------------------------------------------------------------
@dataclass(frozen=True)
class Method:
    """One way to render: our BDPT with some settings, or a Mitsuba integrator."""
    name: str
    label: str
    engine: str                    # "bdpt" or "mitsuba"
    options: tuple = ()            # bdpt settings / Mitsuba plugin type, as (key, value) pairs
    color: str = "k"
    style: str = "-"

    @property
    def opts(self) -> dict:
        return dict(self.options)


# Veach's BDPT: one light subpath per camera sample, every connection (fixed budget).
_FULL = (("light_paths", 1), ("connections", "all"))
BDPT_AUTO = Method("bdpt-auto", "BDPT, efficiency-aware budgets (default)", "bdpt", (), "k", "-")
BDPT_POWER = Method("bdpt-power", "BDPT power", "bdpt", (("mis", "power"),) + _FULL, "C0", "-")
BDPT_BALANCE = Method("bdpt-balance", "BDPT balance", "bdpt", (("mis", "balance"),) + _FULL, "C1", "-")
BDPT_UNIFORM = Method("bdpt-uniform", "BDPT uniform", "bdpt", (("mis", "uniform"),) + _FULL, "C2", "-")
BDPT_LAFORTUNE = Method("bdpt-lafortune", "BDPT lafortune", "bdpt", (("mis", "lafortune"),), "C6", "-")
BDPT_NO_LT = Method("bdpt-no-lt", "BDPT without light image", "bdpt",
                    (("mis", "power"), ("light_image", False)) + _FULL, "C4", "--")
BDPT_PT = Method("bdpt-pt", "BDPT engine, PT strategies only", "bdpt",
                 (("mis", "power"), ("strategy_subset", "pt")), "C7", ":")
BDPT_LT = Method("bdpt-lt", "BDPT engine, LT strategies only", "bdpt",
                 (("mis", "power"), ("strategy_subset", "lt")), "C8", ":")
BDPT_FIRST_LT = Method("bdpt-first-lt", "BDPT engine, light image at smooth first hits", "bdpt",
                       (("mis", "power"), ("light_paths", 2), ("connections", 0),
                        ("first_hits", "light_image")), "C9", ":")
# Metropolis light transport (mmlt.py, mlt.py): spp is the mutations per pixel.
MLT = Method("mlt", "MLT, multiplexed (mlt)", "bdpt", (("integrator", "mlt"),), "C1", "--")
PSSMLT = Method("pssmlt", "PSSMLT over BDPT samples (pssmlt)", "bdpt",
                (("integrator", "pssmlt"),), "C2", "--")
PATH = Method("path", "Mitsuba path", "mitsuba", (("type", "path"),), "C3", "-")
PTRACER = Method("ptracer", "Mitsuba ptracer", "mitsuba", (("type", "ptracer"),), "C5", "-.")
VOLPATH = Method("volpath", "Mitsuba volpath", "mitsuba", (("type", "volpath"),), "C9", "-")
VOLPATHMIS = Method("volpathmis", "Mitsuba volpathmis", "mitsuba", (("type", "volpathmis"),), "C8", "--")

METHODS = {m.name: m for m in (BDPT_AUTO, BDPT_POWER, BDPT_BALANCE, BDPT_UNIFORM, BDPT_LAFORTUNE, BDPT_NO_LT,
                                BDPT_PT, BDPT_LT, BDPT_FIRST_LT, MLT, PSSMLT, PATH, PTRACER, VOLPATH,
                                VOLPATHMIS)}
# The MIS weighting schemes, compared on Veach's budget (light_paths=1 connections=all,
# which mis="lafortune" fixes itself; it has no light image): `benchmarks.run --weighting`.
WEIGHTING = ["bdpt-power", "bdpt-balance", "bdpt-uniform", "bdpt-lafortune"]


def bdpt_settings_fields() -> set:
    """Names of the keyword settings that bdpt_drjit.render accepts."""
    names = {f.name for f in dataclasses.fields(bdpt_drjit.Settings)}
    names |= set(inspect.signature(bdpt_drjit.render).parameters)
    return names


def method_supported(method: Method) -> tuple[bool, str]:
    if method.engine == "mitsuba":
        return True, ""
    opts = method.opts
    if "mis" in opts and opts["mis"] not in bdpt_drjit.HEURISTICS:
        return False, "mis=%r is not in bdpt_drjit.HEURISTICS %s" % (opts["mis"], bdpt_drjit.HEURISTICS)
    unknown = set(opts) - bdpt_settings_fields()
    if unknown:
        return False, "bdpt_drjit.render has no setting %s" % ", ".join(sorted(unknown))
    try:
        bdpt_drjit.Settings(**{k: v for k, v in opts.items()
                               if k in {f.name for f in dataclasses.fields(bdpt_drjit.Settings)}})
    except Exception as e:  # noqa: BLE001  (an option value the engine refuses)
        return False, "bdpt refuses %s: %s" % (opts, e)
    return True, ""


def available_methods(names, quiet=False) -> list[Method]:
    out = []
    for n in names:
        m = METHODS[n]
        ok, why = method_supported(m)
        if ok:
            out.append(m)
        elif not quiet:
            log("  note: skipping method %s (%s)" % (m.name, why))
    return out


# -- timed renders ----------------------------------------------------------------------
@dataclass
class Timing:
    wall: float = 0.0              # perf_counter around render + evaluation
    compile: float = 0.0           # LLVM backend compile time of kernels launched (cache misses)
    codegen: float = 0.0           # Dr.Jit IR generation (tracing -> LLVM IR), every launch
    execution: float = 0.0         # kernel execution (as Dr.Jit's history reports it)
    kernels: int = 0               # JIT kernel launches
    other_launches: int = 0        # memcpy / reductions / ...
    misses: int = 0                # kernels compiled (not in memory or disk cache)
    disk_loads: int = 0            # kernels loaded from Dr.Jit's disk cache

    @property
    def run(self) -> float:
        """Wall time with compilation taken out."""
        return max(self.wall - self.compile, 1e-9)


def _history_timing(wall: float, taken=()) -> Timing:
    """Timing from Dr.Jit's kernel history, plus entries a renderer ``taken`` from it
    (the calibration's timed passes take their kernels from it)."""
    hist = list(taken) + dr.kernel_history()
    t = Timing(wall=wall)
    for e in hist:
        if e["type"] == dr.KernelType.JIT:
            t.kernels += 1
            t.codegen += e.get("codegen_time", 0.0) / 1000
            if not e.get("cache_hit", 1):
                t.misses += 1
                t.compile += e.get("backend_time", 0.0) / 1000
            elif e.get("cache_disk", 0):
                t.disk_loads += 1
                t.compile += e.get("backend_time", 0.0) / 1000
        else:
            t.other_launches += 1
        t.execution += e.get("execution_time", 0.0) / 1000
    return t


@dataclass
class RenderOut:
    image: np.ndarray
    timing: Timing
    spp: int
    pixels: int
    rays: float | None = None          # measured rays (bdpt) or None
    passes: int = 1
    strategies: dict = field(default_factory=dict)

    @property
    def samples_per_second(self) -> float:
        return self.spp * self.pixels / self.timing.run

    @property
    def rays_per_sample(self) -> float | None:
        return None if self.rays is None else self.rays / (self.spp * self.pixels)


def film_pixels(scene) -> int:
    size = scene.sensors()[0].film().crop_size()
    return int(size[0]) * int(size[1])


def render(method: Method, scene, spp: int, seed: int, max_depth: int,
           strategy_images: bool = False) -> RenderOut:
    """Render and force evaluation inside the timed region; compile time is
    measured from Dr.Jit's kernel history."""
    dr.kernel_history()                              # clear
    dr.sync_thread()
    if method.engine == "bdpt":
        t0 = time.perf_counter()
        r = bdpt_drjit.render(scene, spp=spp, seed=seed, max_depth=max_depth,
                              strategy_images=strategy_images, **method.opts)
        img = np.asarray(r.image)
        wall = time.perf_counter() - t0
        return RenderOut(img, _history_timing(wall, r.kernel_history), spp, film_pixels(scene),
                         rays=float(r.rays),
                         passes=r.passes, strategies=r.strategies)
    integ = mi.load_dict({**method.opts, "max_depth": max_depth})
    t0 = time.perf_counter()
    tensor = mi.render(scene, integrator=integ, spp=spp, seed=seed)
    dr.eval(tensor)
    img = np.array(tensor)
    wall = time.perf_counter() - t0
    return RenderOut(img, _history_timing(wall), spp, film_pixels(scene))


def median(values):
    return float(np.median(np.asarray(values, dtype=float)))


def peak_rss_mib() -> float:
    """Peak resident set size of this process.  On Linux VmHWM from /proc/self/status:
    getrusage's ru_maxrss survives fork + exec, so a subprocess would report its
    parent's peak if that was larger.  Elsewhere ru_maxrss (KiB on Linux, bytes on macOS)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024 * 1024) if sys.platform == "darwin" else r / 1024


def jit_watermark_mib() -> float:
    backend = dr.JitBackend.LLVM if mi.variant().startswith("llvm") else dr.JitBackend.CUDA
    return dr.detail.malloc_watermark(backend) / 2 ** 20


def clear_jit_watermark() -> None:
    """Reset Dr.Jit's peak-memory counter (the allocator cache is flushed first, as the
    watermark counts cached blocks too)."""
    dr.sync_thread()
    dr.flush_malloc_cache()
    dr.detail.malloc_clear_statistics()


# -- Mitsuba ray-count estimate ---------------------------------------------------------
def _count(mask) -> int:
    c = dr.count(mask)
    return int(c[0]) if hasattr(c, "__getitem__") else int(c)


def estimate_mitsuba_rays(scene, integrator: str, max_depth: int, spp: int = 4,
                          rr_depth: int = 5, seed: int = 7) -> float:
    """Rays per sample of Mitsuba's ``path`` or ``ptracer``, ESTIMATED by a probe that
    replays their loop structure (Mitsuba does not count rays): ``path`` traces one
    ray per bounce plus one shadow ray per emitter sample at a smooth BSDF;
    ``ptracer`` traces the emitted ray, one ray per bounce and one visibility ray per
    sensor connection (plus one for the emitter's own connection).  Russian roulette
    as in Mitsuba (from depth ``rr_depth``, continuation min(max(throughput)*eta^2, .95))."""
    sensor = scene.sensors()[0]
    size = sensor.film().crop_size()
    w, h = int(size[0]), int(size[1])
    n = w * h * spp
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    ctx = mi.BSDFContext(mi.TransportMode.Radiance if integrator == "path" else mi.TransportMode.Importance)
    total = 0
    depth_limit = max_depth if max_depth >= 0 else 1 << 30
    with dr.suspend_grad():
        if integrator == "path":
            idx = dr.arange(mi.UInt32, n) // spp
            pos = mi.Vector2f(mi.Float(idx % w), mi.Float(idx // w)) + sampler.next_2d()
            ray, _ = sensor.sample_ray(0.0, 0.5, pos / mi.ScalarVector2f(w, h), mi.Point2f(0.5))
        else:
            if not scene.emitters():
                return 0.0
            ray = scene.sample_emitter_ray(0.0, sampler.next_1d(), sampler.next_2d(),
                                           sampler.next_2d(), True)[0]
            total += n                      # the emitter's own connection to the sensor
        active = mi.Bool(True)
        throughput = mi.Spectrum(1.0)
        eta = mi.Float(1.0)
        depth = 0
        while depth < depth_limit:
            si = scene.ray_intersect(ray, active)
            total += _count(active)
            active_next = active & si.is_valid() & (depth + 1 < depth_limit)
            if not dr.any(active_next):
                break
            bsdf = si.bsdf(ray)
            smooth = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            if integrator == "path":
                ds, _ = scene.sample_emitter_direction(si, sampler.next_2d(), False, smooth)
                conn = smooth & (ds.pdf != 0)
            else:
                ds, _ = sensor.sample_direction(si, sampler.next_2d(), smooth)
                conn = smooth & (ds.pdf > 0)
            total += _count(conn)
            bs, w_bsdf = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
            throughput *= w_bsdf
            eta *= bs.eta
            ray = si.spawn_ray(si.to_world(bs.wo))
            depth += 1
            tmax = dr.max(mi.unpolarized_spectrum(throughput))
            rr_prob = dr.minimum(tmax * dr.square(eta), 0.95)
            cont = mi.Bool(True)
            if depth >= rr_depth:
                cont = sampler.next_1d() < rr_prob
                throughput *= dr.rcp(rr_prob)
            active = active_next & cont & (tmax != 0) & (bs.pdf > 0)
            dr.eval(ray, active, throughput, eta)
            sampler.schedule_state()
    return total / n


# -- errors ----------------------------------------------------------------------------
def rel_mse(img: np.ndarray, ref: np.ndarray) -> float:
    """Mean over pixels and channels of (img - ref)^2 / (ref^2 + 1e-2)."""
    d = np.nan_to_num(img.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0) - ref
    return float(np.mean(d * d / (ref.astype(np.float64) ** 2 + 1e-2)))


def mare(img: np.ndarray, ref: np.ndarray) -> float:
    """Mean absolute relative error: mean of |img - ref| / (|ref| + 1e-2)."""
    d = np.nan_to_num(img.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0) - ref
    return float(np.mean(np.abs(d) / (np.abs(ref.astype(np.float64)) + 1e-2)))


def bad_pixels(img: np.ndarray) -> int:
    return int(np.count_nonzero(~np.isfinite(img)))


# -- references --------------------------------------------------------------------------
def read_exr(path: Path) -> np.ndarray:
    """First RGB(A) layer of an EXR file as an (H, W, 3) float32 array."""
    import OpenEXR
    with OpenEXR.File(str(path)) as f:
        ch = f.parts[0].channels
        if "RGB" in ch:
            return np.asarray(ch["RGB"].pixels, dtype=np.float32)[..., :3]
        if "RGBA" in ch:
            return np.asarray(ch["RGBA"].pixels, dtype=np.float32)[..., :3]
        return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)


def box_downsample(img: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return img
    h, w = img.shape[0] // factor, img.shape[1] // factor
    img = img[:h * factor, :w * factor]
    return img.reshape(h, factor, w, factor, -1).mean(axis=(1, 3))


# -- images and charts --------------------------------------------------------------------
def to_srgb8(img: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    x = np.clip(np.nan_to_num(img[..., :3] * exposure, nan=0.0), 0.0, 1.0)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (x * 255 + 0.5).astype(np.uint8)


def auto_exposure(img: np.ndarray) -> float:
    lum = np.nan_to_num(img[..., :3]).mean(axis=-1)
    p = float(np.percentile(lum, 99)) if lum.size else 1.0
    return 1.0 / p if p > 0 else 1.0


def matplotlib():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


# -- equal-cost interpolation -------------------------------------------------------------
# A method's error curve is measured at a few spp levels: points (spp, cost, error), where
# cost is time or rays.  Cost is not proportional to spp at small spp (per-render
# overhead), so error and cost are both interpolated in log-log against spp, and
# "error at equal cost" / "cost to reach an error" go through spp.  Outside the measured
# range: error follows the least-squares log-log slope of the last (first) 3 points,
# clamped to [-1.5, 0]; cost is proportional to spp.  Extrapolating more than
# ``MAX_EXTRAPOLATION`` beyond the range gives NaN.
MAX_EXTRAPOLATION = 4.0


def _prep(points):
    pts = sorted((float(n), float(c), float(e)) for n, c, e in points if n > 0 and c > 0 and e > 0)
    if not pts:
        return None
    n = np.log([p[0] for p in pts])
    c = np.log(np.maximum.accumulate([p[1] for p in pts]))     # cost never falls with spp
    e = np.log([p[2] for p in pts])
    return n, c, e


def _slope(x, y, end: bool) -> float:
    if len(x) < 2:
        return -1.0
    sel = slice(-3, None) if end else slice(0, 3)
    xs, ys = x[sel], y[sel]
    if np.ptp(xs) == 0:
        return -1.0
    return float(np.clip(np.polyfit(xs, ys, 1)[0], -1.5, 0.0))


def _interp_monotone(x0, xs, ys):
    """ys at x0 along the polyline (xs ascending, possibly with ties)."""
    for k in range(1, len(xs)):
        if xs[k - 1] <= x0 <= xs[k]:
            if xs[k] == xs[k - 1]:
                return ys[k]
            f = (x0 - xs[k - 1]) / (xs[k] - xs[k - 1])
            return ys[k - 1] + f * (ys[k] - ys[k - 1])
    return ys[0] if x0 <= xs[0] else ys[-1]


def error_at_cost(points, cost: float):
    """(error, extrapolated) that a method reaches at ``cost``."""
    P = _prep(points)
    if P is None:
        return float("nan"), True
    n, c, e = P
    l0 = math.log(cost)
    if c[0] <= l0 <= c[-1]:
        ln = _interp_monotone(l0, c, n)
        return float(np.exp(np.interp(ln, n, e))), False
    if l0 < c[0]:
        if c[0] - l0 > math.log(MAX_EXTRAPOLATION):
            return float("nan"), True
        ln = n[0] + (l0 - c[0])
        return float(np.exp(e[0] + _slope(n, e, False) * (ln - n[0]))), True
    if l0 - c[-1] > math.log(MAX_EXTRAPOLATION):
        return float("nan"), True
    ln = n[-1] + (l0 - c[-1])
    return float(np.exp(e[-1] + _slope(n, e, True) * (ln - n[-1]))), True


def cost_to_error(points, error: float, min_slope: float = -0.25):
    """(cost, extrapolated) at which a method first reaches ``error``; inf when its curve
    has stopped improving (slope above ``min_slope``) before reaching it."""
    P = _prep(points)
    if P is None:
        return float("inf"), True
    n, c, e = P
    l0 = math.log(error)
    if e[0] <= l0:                         # reached at the first level already
        s = _slope(n, e, False)
        if s >= 0 or e[0] == l0:
            return float(np.exp(c[0])), e[0] != l0
        ln = n[0] + (l0 - e[0]) / s
        if n[0] - ln > math.log(MAX_EXTRAPOLATION):
            return float("nan"), True
        return float(np.exp(c[0] + (ln - n[0]))), True
    for k in range(1, len(n)):
        if e[k] <= l0:
            f = (l0 - e[k - 1]) / (e[k] - e[k - 1])
            ln = n[k - 1] + f * (n[k] - n[k - 1])
            return float(np.exp(np.interp(ln, n, c))), False
    s = _slope(n, e, True)
    if s > min_slope:
        return float("inf"), True
    ln = n[-1] + (l0 - e[-1]) / s
    if ln - n[-1] > math.log(MAX_EXTRAPOLATION):
        return float("nan"), True
    return float(np.exp(c[-1] + (ln - n[-1]))), True


# -- machine -----------------------------------------------------------------------------
def machine_info() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    return {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "cpu_count": os.cpu_count(),
        "cpu": cpu,
        "load_avg_1min": round(load, 2),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "variant": mi.variant(),
        "mitsuba": mi.__version__,
        "drjit": dr.__version__,
        "bdpt_drjit": getattr(bdpt_drjit, "__version__", "?"),
        "llvm": ".".join(map(str, dr.detail.llvm_version())) if mi.variant().startswith("llvm") else "",
    }


def parse_res(text) -> tuple[int, int]:
    """'256' -> (256, 256); '1920x1080' -> (1920, 1080)."""
    if isinstance(text, (tuple, list)):
        return int(text[0]), int(text[1])
    m = re.fullmatch(r"\s*(\d+)\s*(?:[xX,]\s*(\d+))?\s*", str(text))
    if not m:
        raise ValueError("resolution must be N or WxH, got %r" % (text,))
    w = int(m.group(1))
    return w, int(m.group(2) or w)


class JSONEncoder(json.JSONEncoder):
    def default(self, o):
        if isinstance(o, (np.floating, np.integer, np.bool_)):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, Path):
            return str(o)
        if dataclasses.is_dataclass(o):
            return dataclasses.asdict(o)
        return super().default(o)


def check_block(path: Path, name: str) -> tuple[str, str]:
    """The markers of the block ``name`` of the Markdown file ``path``, which must hold
    it once (a run that publishes checks this before it starts)."""
    begin, end = "<!-- %s: begin -->" % name, "<!-- %s: end -->" % name
    text = path.read_text()
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise SystemExit("%s has no single %s ... %s block: add one where the section belongs"
                         % (path, begin, end))
    return begin, end


def replace_block(path: Path, name: str, text: str) -> None:
    """Put ``text`` between the lines ``<!-- name: begin -->`` and ``<!-- name: end -->``
    of the Markdown file ``path`` (RESULTS.md: each of its measured sections is such a
    block, written by the command that measures it); a file without them is refused."""
    begin, end = check_block(path, name)
    block = "%s\n%s\n%s" % (begin, text.strip("\n"), end)
    path.write_text(re.sub(re.escape(begin) + ".*?" + re.escape(end), lambda _: block,
                           path.read_text(), flags=re.S))


def write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, cls=JSONEncoder, allow_nan=True))
