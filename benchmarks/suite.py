"""What the benchmark suite renders and measures: the modes, references, error against
time on the scene suite, the equal-cost comparisons, throughput, scaling, peak memory
and strategy pyramids, gathered into the results dictionary (results.json).

Method: every render is timed with time.perf_counter() around the render and the
evaluation of its image (Dr.Jit is lazy); the LLVM compile time of any kernel
compiled inside the timed region (Dr.Jit's kernel history) is subtracted, and each
method is warmed up once per scene before its timed renders.  BDPT variants render a
fixed list of spp levels, their renders interleaved (at each level one render of each
in turn, so that other load on a shared machine falls on all of them alike); the
Mitsuba integrators then double their spp until they have used as much time as BDPT
(power) at its last level, so all curves cover the same time range.  Error: relative MSE, mean over pixels and channels of
(img - ref)^2 / (ref^2 + 1e-2), and the mean absolute relative error.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import charts
from . import common as C
from . import throughput as TP
from .scenes import PYRAMID_SCENES, SCENE_LIST, SCENES

ALL_METHODS = ["bdpt-auto", "bdpt-power", "bdpt-balance", "bdpt-uniform", "bdpt-lafortune", "bdpt-no-lt",
               "bdpt-pt", "bdpt-lt", "path", "ptracer"]
SECTIONS = ("error", "throughput", "scaling", "rss", "cold", "pyramid")
CORNELL = C.ROOT / "scenes" / "cornell-box.xml"


@dataclass
class Config:
    mode: str
    res: int
    levels: list
    ref_spp: int                    # BDPT reference spp; Mitsuba references use 4x
    match_cap: int                  # largest spp a time-matched Mitsuba method may use
    scenes: list
    pyramid_scenes: list
    pyramid_res: int
    pyramid_spp: int
    pyramid_rows: int
    tp_res: int
    tp_spp: int
    tp_repeats: int
    grid_res: list                  # time vs pixels x spp
    grid_spp: list
    depths: list                    # time vs max_depth
    depth_res: int
    depth_spp: int
    rss_sizes: list
    cold: bool
    cold_res: int = 64
    seeds: int = 1                  # renders per level (errors averaged, median time) ...
    short_repeats: int = 3          # ... but at least this many for renders shorter than
    short_time: float = 0.1         # this (seconds)
    methods: list = field(default_factory=lambda: list(ALL_METHODS))
    ref_mitsuba_factor: int = 4
    weighting: bool = False         # report the MIS weighting schemes only (run.py --weighting)


MODES = {
    "smoke": Config(mode="smoke", res=16, levels=[1, 2], ref_spp=64, match_cap=2048,
                    scenes=["cornell-diffuse", "point-caustic"], pyramid_scenes=["point-caustic"],
                    pyramid_res=16, pyramid_spp=4, pyramid_rows=3, tp_res=16, tp_spp=2, tp_repeats=1,
                    grid_res=[8, 16], grid_spp=[1, 2], depths=[2, 3], depth_res=16, depth_spp=1,
                    rss_sizes=[], cold=False, short_repeats=1,
                    methods=["bdpt-power", "bdpt-balance", "bdpt-no-lt", "path", "ptracer"]),
    "quick": Config(mode="quick", res=32, levels=[1, 4, 16], ref_spp=1024, match_cap=16384,
                    scenes=[s.name for s in SCENE_LIST], pyramid_scenes=list(PYRAMID_SCENES),
                    pyramid_res=64, pyramid_spp=16, pyramid_rows=4, tp_res=64, tp_spp=16, tp_repeats=3,
                    grid_res=[32, 64, 128], grid_spp=[1, 4, 16], depths=[1, 2, 3, 4, 6, 8, 10, 12],
                    depth_res=32, depth_spp=4, rss_sizes=[(256, 256)], cold=True),
    "full": Config(mode="full", res=128, levels=[1, 2, 4, 8, 16, 32, 64, 128, 256], ref_spp=8192,
                   match_cap=1 << 16, scenes=[s.name for s in SCENE_LIST],
                   pyramid_scenes=list(PYRAMID_SCENES), pyramid_res=256, pyramid_spp=256, pyramid_rows=5,
                   tp_res=256, tp_spp=64, tp_repeats=5, grid_res=[64, 128, 256, 512],
                   grid_spp=[1, 4, 16, 64], depths=[1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20],
                   depth_res=128, depth_spp=16,
                   rss_sizes=[(256, 256), (1024, 1024), (1920, 1080)], cold=True),
}


class Progress:
    def __init__(self):
        self.t0 = time.perf_counter()

    def __call__(self, msg):
        C.log("[%6.1fs] %s" % (time.perf_counter() - self.t0, msg))


# -- references ----------------------------------------------------------------------------------
def get_reference(spec, scene, w, h, factor, cfg: Config, refs_dir: Path, progress) -> tuple[np.ndarray, dict]:
    if spec.reference == "exr":
        ref = spec.exr_reference(factor).astype(np.float32)
        return ref, {"method": "exr", "file": str(spec.exr), "downsample": factor,
                     "note": "Tungsten render, box-downsampled; approximate mean reference"}
    m = C.METHODS[spec.reference]
    spp = cfg.ref_spp * (cfg.ref_mitsuba_factor if m.engine == "mitsuba" else 1)
    key = "%s_%dx%d_d%d_%s_%dspp" % (spec.name, w, h, spec.max_depth, m.name, spp)
    npy, meta_path = refs_dir / (key + ".npy"), refs_dir / (key + ".json")
    if npy.exists() and meta_path.exists():
        return np.load(npy), json.loads(meta_path.read_text())
    progress("  reference: %s %d spp at %dx%d (cached as %s)" % (m.name, spp, w, h, npy.name))
    # Mitsuba renders all samples in one wavefront: split into chunks of <= 2^22 samples.
    pixels = w * h
    chunk = spp if m.engine == "bdpt" else max(1, min(spp, (1 << 22) // pixels))
    acc, done, t = None, 0, 0.0
    while done < spp:
        n = min(chunk, spp - done)
        out = C.render(m, scene, n, 1_000_003 + done, spec.max_depth)
        acc = out.image.astype(np.float64) * n if acc is None else acc + out.image * n
        done += n
        t += out.timing.wall
    ref = (acc / spp).astype(np.float32)
    meta = {"method": m.name, "spp": spp, "time": t, "width": w, "height": h,
            "max_depth": spec.max_depth, "nonfinite": C.bad_pixels(ref)}
    refs_dir.mkdir(parents=True, exist_ok=True)
    np.save(npy, ref)
    C.write_json(meta_path, meta)
    return ref, meta


# -- error against time ------------------------------------------------------------------------------
def _load_or_skip(spec, res, what: str, progress):
    """(scene, w, h, factor), or None with a message where the scene is unavailable."""
    ok, why = spec.available()
    if not ok:
        progress("skip %s %s: %s" % (what, spec.name, why))
        return None
    w, h, factor = spec.resolution(res)
    return spec.load(w, h), w, h, factor


def error_for_scene(spec, cfg: Config, methods, refs_dir: Path, progress) -> dict | None:
    loaded = _load_or_skip(spec, cfg.res, "scene", progress)
    if loaded is None:
        return None
    scene, w, h, factor = loaded
    ref, ref_meta = get_reference(spec, scene, w, h, factor, cfg, refs_dir, progress)
    if ref.shape[:2] != (h, w):
        raise RuntimeError("%s: reference is %s, render is %dx%d" % (spec.name, ref.shape, w, h))
    fixed = [m for m in methods if m.engine == "bdpt"]
    records = interleaved_records(spec, scene, ref, fixed, cfg, progress) if fixed else []
    # The Mitsuba integrators run until they have used BDPT (power)'s time at its last
    # level (or the first method's, without it).
    lead = "bdpt-power" if any(m.name == "bdpt-power" for m in fixed) else fixed[0].name if fixed else None
    target_time = max((r["time"] for r in records if r["method"] == lead), default=None)
    for m in methods:
        if m.engine != "bdpt":
            mine = method_records(spec, scene, ref, m, cfg, target_time, progress)
            records += mine
            target_time = target_time or max(r["time"] for r in mine)
    estimate_mitsuba_rays(scene, spec, methods, records)
    return {"scene": spec.name, "width": w, "height": h, "max_depth": spec.max_depth,
            "baseline": spec.baseline, "reference": ref_meta, "records": records, "expected_failure": spec.expected_failure,
            "ref_mean": float(ref.mean())}


def interleaved_records(spec, scene, ref, methods, cfg: Config, progress) -> list:
    """The records of methods that render the fixed spp levels (BDPT), their renders
    interleaved: at each level the methods take turns, one render each, each round
    starting with the next method, so that other load on the machine falls on all of
    them alike.  An untimed render starts each level: the first render of a new pass
    size (fresh memory) took up to twice as long as the next in the weighting runs of
    2026-11-26, and was charged to whichever method rendered first."""
    for m in methods:
        C.render(m, scene, cfg.levels[0], 777, spec.max_depth)     # warm-up (compile), not recorded
    records = []
    for i, spp in enumerate(cfg.levels):
        if i:
            C.render(methods[0], scene, spp, 777, spec.max_depth)  # the level's memory, not recorded
        outs = {m.name: [] for m in methods}
        needed = {m.name: cfg.seeds for m in methods}
        k = 0
        while any(len(outs[n]) < needed[n] for n in outs):
            turn = methods[k % len(methods):] + methods[:k % len(methods)]
            for m in turn:
                if len(outs[m.name]) < needed[m.name]:
                    outs[m.name].append(C.render(m, scene, spp, level_seed(i, len(outs[m.name])),
                                                 spec.max_depth))
            if k == 0:
                needed = {n: runs_needed(cfg, o[0]) for n, o in outs.items()}
            k += 1
        for m in methods:
            records.append(level_record(spec, ref, m, spp, outs[m.name], progress))
    return records


def method_records(spec, scene, ref, m, cfg: Config, target_time, progress) -> list:
    """One method's records: a Mitsuba integrator (once ``target_time`` is known)
    doubling its spp until it has used that much time; else the fixed spp levels."""
    C.render(m, scene, cfg.levels[0], 777, spec.max_depth)     # warm-up (compile), not recorded
    records = []
    i, spp = 0, 1
    while True:
        if target_time is None:
            if i >= len(cfg.levels):
                break
            spp = cfg.levels[i]
        outs = [C.render(m, scene, spp, level_seed(i, 0), spec.max_depth)]
        outs += [C.render(m, scene, spp, level_seed(i, k), spec.max_depth)
                 for k in range(1, runs_needed(cfg, outs[0]))]
        rec = level_record(spec, ref, m, spp, outs, progress)
        records.append(rec)
        i += 1
        if target_time is not None:
            # Double until it has used BDPT's time (and has >= len(levels) points).
            if (rec["time"] >= target_time and i >= len(cfg.levels)) or spp * 2 > cfg.match_cap:
                break
            spp *= 2
    return records


def level_seed(i: int, k: int) -> int:
    """The seed of the k-th render at the i-th spp level."""
    return 1 + 7919 * k + 31 * i


def runs_needed(cfg: Config, first) -> int:
    """Renders per level: cfg.seeds; short renders are timed noisily on a busy machine
    and their errors vary a lot between seeds (fireflies): repeat them (median time,
    mean error)."""
    return max(cfg.seeds, cfg.short_repeats if first.timing.run < cfg.short_time else 1)


def level_record(spec, ref, m, spp: int, outs: list, progress) -> dict:
    """One method's renders at one spp level, timed and compared with ref."""
    h, w = ref.shape[:2]
    rec = {"scene": spec.name, "method": m.name, "spp": spp,
           "time": C.median([o.timing.run for o in outs]), "renders": len(outs),
           "wall": C.median([o.timing.wall for o in outs]),
           "compile": C.median([o.timing.compile for o in outs]),
           "relmse": float(np.mean([C.rel_mse(o.image, ref) for o in outs])),
           "mare": float(np.mean([C.mare(o.image, ref) for o in outs])),
           "mean": float(np.mean(outs[0].image)),
           "nonfinite": sum(C.bad_pixels(o.image) for o in outs),
           "rays_per_sample": outs[0].rays_per_sample, "pixels": w * h,
           "kernels": outs[0].timing.kernels, "passes": outs[0].passes}
    progress("  %-20s %-14s spp=%-6d time=%8.4fs relMSE=%.4g MARE=%.4g%s"
             % (spec.name, m.name, spp, rec["time"], rec["relmse"], rec["mare"],
                "  NONFINITE=%d" % rec["nonfinite"] if rec["nonfinite"] else ""))
    return rec


def estimate_mitsuba_rays(scene, spec, methods, records) -> None:
    """Mitsuba's rays per sample (a probe), for the equal-ray comparison; the probe
    replays path and ptracer only (volpath's free flights are not modelled)."""
    est = {}
    for m in methods:
        if m.engine == "mitsuba" and m.opts["type"] in ("path", "ptracer"):
            est[m.name] = C.estimate_mitsuba_rays(scene, m.opts["type"], spec.max_depth, spp=2)
    for r in records:
        if r["rays_per_sample"] is None and r["method"] in est:
            r["rays_per_sample"] = est[r["method"]]
            r["rays_estimated"] = True


def cost(r, key):
    if key == "rays":
        return r["rays_per_sample"] * r["spp"] * r["pixels"] if r["rays_per_sample"] else None
    return r[key]


def equal_comparison(result, key="time", baseline="path", budget_method="bdpt-power"):
    """Error each method reaches at a common cost x (time or rays), and the cost it
    needs to reach a target error (``baseline``'s error at its last level), both also
    as ratios to ``baseline``.  x = what ``budget_method`` used at its last level (the
    Mitsuba methods are run until they have used as much time), else the geometric
    middle of the cost range that every method covers."""
    pts = {}
    for r in result["records"]:
        x = cost(r, key)
        if x is not None:
            pts.setdefault(r["method"], []).append((r["spp"], x, r["relmse"]))
    if not pts:
        return None
    lo = max(min(p[1] for p in v) for v in pts.values())
    hi = min(max(p[1] for p in v) for v in pts.values())
    x0 = math.sqrt(lo * hi)
    if budget_method in pts:
        x0 = max(p[1] for p in pts[budget_method])
    base = pts.get(baseline)
    rows = {}
    # Target error: the larger of what the baseline and the budget method reach at x0,
    # so that both reach it inside their measured ranges.
    e_target = None
    if base:
        e_target = C.error_at_cost(base, x0)[0]
        if budget_method in pts:
            e_target = max(e_target, C.error_at_cost(pts[budget_method], x0)[0])
    for m, p in pts.items():
        e, ex = C.error_at_cost(p, x0)
        tt, ext = C.cost_to_error(p, e_target) if e_target else (float("nan"), True)
        rows[m] = {"err_at_x": e, "err_extrapolated": ex, "x_to_target": tt, "x_extrapolated": ext}
    if base:
        be, bt = rows[baseline]["err_at_x"], rows[baseline]["x_to_target"]
        for m, r in rows.items():
            r["err_ratio"] = r["err_at_x"] / be if be > 0 else float("nan")
            r["x_ratio"] = r["x_to_target"] / bt if bt and bt > 0 and not math.isinf(bt) else float("nan")
    return {"x": x0, "key": key, "overlap": lo <= hi, "target_error": e_target, "methods": rows}


def compare(r: dict) -> None:
    """A scene result's equal-time and equal-ray comparisons, and the weighting
    schemes' against the power heuristic."""
    base = r.get("baseline", "path")
    r["equal_time"] = equal_comparison(r, "time", baseline=base)
    r["equal_rays"] = equal_comparison(r, "rays", baseline=base)
    r["weighting"] = weighting_comparison(r)


def weighting_schemes(r: dict) -> list:
    """The MIS weighting schemes (C.WEIGHTING) among a scene result's methods."""
    present = {x["method"] for x in r["records"]}
    return [m for m in C.WEIGHTING if m in present]


def weighting_comparison(r: dict) -> dict | None:
    """Each weighting scheme's error at the power heuristic's time and at its spp (x =
    power's last level), as ratios to power's; None without power and another scheme."""
    schemes = weighting_schemes(r)
    if "bdpt-power" not in schemes or len(schemes) < 2:
        return None
    mine = dict(r, records=[x for x in r["records"] if x["method"] in schemes])
    return {key: equal_comparison(mine, key, baseline="bdpt-power") for key in ("time", "spp")}


# -- throughput & scaling ------------------------------------------------------------------------------
def connection_strategies(d: int) -> int:
    """Number of (s, t) with s, t >= 2 and s + t - 1 <= d (the connection kernels)."""
    return sum(max(0, k - 2) for k in range(3, d + 1)) if d >= 0 else -1


def scaling(cfg: Config, progress) -> dict:
    """Time against pixels x spp (with a linear fit) and against max_depth."""
    out = {"pixels_spp": scaling_samples(cfg, progress), "depth": []}
    out["fits"] = {name: linear_fit([(r["samples"], r["time"]) for r in out["pixels_spp"]
                                     if r["method"] == name])
                   for name in ("bdpt-power", "path")}
    out["depth"] = scaling_depth(cfg, progress)
    b = [r for r in out["depth"] if r["method"] == "bdpt-power"]
    if len(b) >= 3:
        ds = np.array([r["max_depth"] for r in b], float)
        ts = np.array([r["time"] for r in b], float)
        out["depth_fit_quadratic"] = [float(c) for c in np.polyfit(ds, ts, 2)]
        ks = np.array([r["kernels_per_pass"] for r in b], float)
        out["depth_fit_kernels_quadratic"] = [float(c) for c in np.polyfit(ds, ks, 2)]
    return out


def scaling_samples(cfg: Config, progress) -> list:
    rows = []
    for res in cfg.grid_res:
        sc = TP.load_scene(CORNELL, res, res, 8)
        for m in (C.BDPT_POWER, C.PATH):
            C.render(m, sc, cfg.grid_spp[0], 99, 8)
            for spp in cfg.grid_spp:
                o = [C.render(m, sc, spp, 5 + k, 8) for k in range(2)]
                t = C.median([x.timing.run for x in o])
                rows.append({"method": m.name, "res": res, "spp": spp, "samples": res * res * spp, "time": t})
                progress("  scaling %-10s %4dx%-4d %3d spp: %.4f s" % (m.name, res, res, spp, t))
    return rows


def linear_fit(pts) -> dict:
    """time = a + b * samples by least squares, its R^2 and the log-log slope (1 = linear)."""
    n = np.array([p[0] for p in pts], float)
    t = np.array([p[1] for p in pts], float)
    A = np.stack([np.ones_like(n), n], axis=1)
    (a, b), *_ = np.linalg.lstsq(A, t, rcond=None)
    pred = a + b * n
    r2 = 1 - np.sum((t - pred) ** 2) / max(np.sum((t - t.mean()) ** 2), 1e-30)
    slope = float(np.polyfit(np.log(n), np.log(t), 1)[0]) if len(n) > 1 else float("nan")
    return {"overhead_s": float(a), "per_sample_s": float(b), "r2": float(r2),
            "loglog_slope": slope, "samples_per_s_asymptotic": 1 / b if b > 0 else None}


def scaling_depth(cfg: Config, progress) -> list:
    rows = []
    res, spp = cfg.depth_res, cfg.depth_spp
    for d in cfg.depths:
        sc = TP.load_scene(CORNELL, res, res, d)
        for m in (C.BDPT_POWER, C.PATH):
            C.render(m, sc, spp, 99, d)
            o = [C.render(m, sc, spp, 5 + k, d) for k in range(3)]
            t = C.median([x.timing.run for x in o])
            rows.append({"method": m.name, "max_depth": d, "time": t,
                         "kernels_per_pass": o[0].timing.kernels / o[0].passes,
                         "connections": connection_strategies(d) if m.engine == "bdpt" else 0,
                         "rays_per_sample": o[0].rays_per_sample})
            progress("  depth   %-10s max_depth=%-3d %.4f s  %d kernels/pass"
                     % (m.name, d, t, o[0].timing.kernels / o[0].passes))
    return rows


def rss_section(cfg: Config, progress) -> list:
    rows = []
    for (w, h) in cfg.rss_sizes:
        for name in ("bdpt-power", "path"):
            progress("  peak RSS: %s %dx%d 1 spp (subprocess) ..." % (name, w, h))
            r = TP.probe_subprocess(name, CORNELL, w, h, 1, 8)
            r.setdefault("method", name)
            r.update(width=w, height=h)
            rows.append(r)
            if "error" in r:
                progress("    failed: %s" % r["error"])
            else:
                progress("    peak RSS %.0f MiB (baseline %.0f), Dr.Jit peak %.0f MiB, %.2f s"
                         % (r["rss_peak_mib"], r["baseline_rss_mib"], r["jit_peak_mib"], r["first_wall"]))
    return rows


# -- strategy pyramid ---------------------------------------------------------------------------------
def pyramid(spec, cfg: Config, path: Path, progress) -> dict | None:
    loaded = _load_or_skip(spec, cfg.pyramid_res, "pyramid", progress)
    if loaded is None:
        return None
    scene, w, h, _ = loaded
    progress("  pyramid %s: %dx%d %d spp, per-strategy images ..." % (spec.name, w, h, cfg.pyramid_spp))
    out = C.render(C.BDPT_POWER, scene, cfg.pyramid_spp, 4242, spec.max_depth, strategy_images=True)
    img, strat = out.image, out.strategies
    total = sum(strat.values()) if strat else np.zeros_like(img)
    sum_err = float(np.max(np.abs(total - img))) if strat else float("nan")
    K = min(cfg.pyramid_rows, spec.max_depth)
    full = charts.pyramid(spec.name, img, strat, K, path)
    return {"scene": spec.name, "width": w, "height": h, "spp": cfg.pyramid_spp, "rows": K,
            "strategies": len(strat), "max_abs_sum_error": sum_err,
            "mean_per_strategy": strategy_means(strat, K),
            "image_mean": float(img.mean()), "chart": path.name, "image": full.name}


def strategy_means(strat: dict, rows: int) -> dict:
    """"s,t" -> mean of that strategy's image (0 where it has none), rows k = 1..rows."""
    means = {}
    for k in range(1, rows + 1):
        for s in range(0, k + 1):
            im = strat.get((s, k + 1 - s))
            means["%d,%d" % (s, k + 1 - s)] = 0.0 if im is None else float(np.mean(im))
    return means


# -- the whole suite -----------------------------------------------------------------------------------
def new_results(mode: str, cmd: str, cfg: Config, methods) -> dict:
    res = {"mode": mode, "command": cmd, "machine": C.machine_info(), "config": cfg.__dict__,
           "methods": [m.name for m in methods], "notes": [], "scenes": [], "skipped_scenes": []}
    for name in cfg.methods:
        ok, why = C.method_supported(C.METHODS[name])
        if not ok:
            res["notes"].append("method %s skipped: %s" % (name, why))
    return res


def error_section(res: dict, cfg: Config, methods, out: Path, progress) -> None:
    """Error against time on every scene of cfg.scenes; results.json after each."""
    for i, name in enumerate(cfg.scenes):
        spec = SCENES[name]
        progress("[%d/%d] scene %s" % (i + 1, len(cfg.scenes), name))
        r = error_for_scene(spec, cfg, methods, out / "refs", progress)
        if r is None:
            res["skipped_scenes"].append((name, spec.available()[1]))
            continue
        compare(r)
        r["chart"] = None if cfg.weighting else "%s_error_time.png" % name
        r["weighting_chart"] = "%s_weighting.png" % name if r["weighting"] else None
        charts.scene_charts(r, out / "charts", methods)
        res["scenes"].append(r)
        C.write_json(out / "results.json", res)


def run(cfg: Config, mode: str, skip: set, out: Path, cmd: str, progress) -> dict:
    """Every section not in ``skip``: the results dictionary (charts under out/charts)."""
    charts_dir = out / "charts"
    methods = C.available_methods(cfg.methods)
    res = new_results(mode, cmd, cfg, methods)
    t_start = time.perf_counter()
    if "error" not in skip:
        error_section(res, cfg, methods, out, progress)
    if "throughput" not in skip:
        progress("throughput: Cornell box %dx%d, %d spp" % (cfg.tp_res, cfg.tp_res, cfg.tp_spp))
        cold = cfg.cold and "cold" not in skip
        res["throughput"] = TP.run(cfg.tp_res, cfg.tp_res, cfg.tp_spp, cfg.tp_repeats, 8, CORNELL,
                                   cold=cold, cold_res=(cfg.cold_res, cfg.cold_res))
        C.log(TP.report(res["throughput"], res["throughput"].get("cold")))
    if "scaling" not in skip:
        progress("scaling: time vs pixels x spp and vs max_depth")
        res["scaling"] = scaling(cfg, progress)
        charts.scaling(res["scaling"], cfg.depth_res, cfg.depth_spp, charts_dir)
    if "rss" not in skip and cfg.rss_sizes:
        progress("peak memory per resolution")
        res["rss"] = rss_section(cfg, progress)
    if "pyramid" not in skip:
        res["pyramids"] = []
        for name in cfg.pyramid_scenes:
            progress("strategy pyramid: %s" % name)
            res["pyramids"].append(pyramid(SCENES[name], cfg, charts_dir / ("pyramid_%s.png" % name), progress))
    res["elapsed"] = time.perf_counter() - t_start
    return res
