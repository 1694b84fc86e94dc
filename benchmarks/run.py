"""The benchmark suite: error against time on the scene suite, weighting schemes,
equal-ray comparison, throughput and scaling, and strategy pyramids.

    python -m benchmarks.run --smoke    # CI smoke test: 2 scenes, 16x16, seconds
    python -m benchmarks.run --quick    # a few minutes on 2 cores: 32x32, 3 spp levels
    python -m benchmarks.run            # the full run (long: run it on an idle machine)

Options: --out DIR (default benchmarks/results), --scenes a,b, --methods a,b, --res N,
--levels 1,2,4, --ref-spp N, --seeds N, --skip error,throughput,scaling,rss,cold,pyramid.

Outputs (under --out): refs/ (cached references, .npy + .json), charts/*.png,
results.json, RESULTS.md.  Without --out (and not --smoke) the charts are also copied
to benchmarks/charts/ and the summary to benchmarks/RESULTS.md, to be committed.

Method: every render is timed with time.perf_counter() around the render and the
evaluation of its image (Dr.Jit is lazy); the LLVM compile time of any kernel
compiled inside the timed region (Dr.Jit's kernel history) is subtracted, and each
method is warmed up once per scene before its timed renders.  BDPT variants render a
fixed list of spp levels; the Mitsuba integrators double their spp until they have
used as much time as BDPT (power) at its last level, so all curves cover the same
time range.  Error: relative MSE, mean over pixels and channels of
(img - ref)^2 / (ref^2 + 1e-2), and the mean absolute relative error.
"""
from __future__ import annotations

import argparse
import math
import shutil
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from . import common as C
from . import throughput as TP
from .scenes import PYRAMID_SCENES, SCENE_LIST, SCENES

ALL_METHODS = ["bdpt-power", "bdpt-balance", "bdpt-uniform", "bdpt-lafortune", "bdpt-no-lt",
               "bdpt-pt", "bdpt-lt", "path", "ptracer"]
WEIGHTING = ["bdpt-power", "bdpt-balance", "bdpt-uniform", "bdpt-lafortune"]
SECTIONS = ("error", "throughput", "scaling", "rss", "cold", "pyramid")


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


# -- small helpers -----------------------------------------------------------------------------
class Progress:
    def __init__(self):
        self.t0 = time.perf_counter()

    def __call__(self, msg):
        C.log("[%6.1fs] %s" % (time.perf_counter() - self.t0, msg))


def fig(plt, w=6, h=4):
    f, ax = plt.subplots(figsize=(w, h), dpi=100)
    return f, ax


def no_minor_labels(ax):
    from matplotlib.ticker import NullFormatter
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.yaxis.set_minor_formatter(NullFormatter())


def save(f, path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    f.tight_layout()
    f.savefig(path, dpi=100)
    import matplotlib.pyplot as plt
    plt.close(f)


def ratio_str(x, extrapolated=False, inf_text="never"):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if math.isinf(x):
        return inf_text
    s = "%.3g" % x
    return ("~" + s) if extrapolated else s


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
        import json
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
    records = []
    target_time = None
    order = sorted(methods, key=lambda m: (m.name != "bdpt-power", m.engine != "bdpt"))
    for m in order:
        # Warm-up (compile) at the first level, not recorded.
        C.render(m, scene, cfg.levels[0], 777, spec.max_depth)
        spp_list = list(cfg.levels) if m.engine == "bdpt" or target_time is None else None
        i, spp = 0, 1
        while True:
            if spp_list is not None:
                if i >= len(spp_list):
                    break
                spp = spp_list[i]
            outs = [C.render(m, scene, spp, 1 + 31 * i, spec.max_depth)]
            # Short renders are timed noisily on a busy machine and their errors vary a lot
            # between seeds (fireflies): repeat them (median time, mean error).
            n_runs = max(cfg.seeds, cfg.short_repeats if outs[0].timing.run < cfg.short_time else 1)
            outs += [C.render(m, scene, spp, 1 + 7919 * k + 31 * i, spec.max_depth) for k in range(1, n_runs)]
            rel = float(np.mean([C.rel_mse(o.image, ref) for o in outs]))
            ma = float(np.mean([C.mare(o.image, ref) for o in outs]))
            t = C.median([o.timing.run for o in outs])
            rec = {"scene": spec.name, "method": m.name, "spp": spp, "time": t, "renders": len(outs),
                   "wall": C.median([o.timing.wall for o in outs]),
                   "compile": C.median([o.timing.compile for o in outs]),
                   "relmse": rel, "mare": ma, "mean": float(np.mean(outs[0].image)),
                   "nonfinite": sum(C.bad_pixels(o.image) for o in outs),
                   "rays_per_sample": outs[0].rays_per_sample, "pixels": w * h,
                   "kernels": outs[0].timing.kernels, "passes": outs[0].passes}
            records.append(rec)
            progress("  %-20s %-14s spp=%-6d time=%8.4fs relMSE=%.4g MARE=%.4g%s"
                     % (spec.name, m.name, spp, t, rel, ma,
                        "  NONFINITE=%d" % rec["nonfinite"] if rec["nonfinite"] else ""))
            i += 1
            if spp_list is None:
                # Mitsuba: double until it has used BDPT's time (and has >= len(levels) points).
                if (t >= target_time and i >= len(cfg.levels)) or spp * 2 > cfg.match_cap:
                    break
                spp *= 2
        if m.name == "bdpt-power" or target_time is None:
            target_time = max(target_time or 0.0, max(r["time"] for r in records if r["method"] == m.name))
    # Mitsuba ray estimate (probe), for the equal-ray comparison.
    est = {}
    for m in methods:
        if m.engine == "mitsuba":
            est[m.name] = C.estimate_mitsuba_rays(scene, m.opts["type"], spec.max_depth, spp=2)
    for r in records:
        if r["rays_per_sample"] is None and r["method"] in est:
            r["rays_per_sample"] = est[r["method"]]
            r["rays_estimated"] = True
    return {"scene": spec.name, "width": w, "height": h, "max_depth": spec.max_depth,
            "reference": ref_meta, "records": records, "expected_failure": spec.expected_failure,
            "ref_mean": float(ref.mean())}


def curves(result, key="time"):
    """method -> (xs, relmse list) in spp order, for charts."""
    out = {}
    for r in result["records"]:
        out.setdefault(r["method"], []).append((r["spp"], cost(r, key), r["relmse"]))
    return {m: ([p[1] for p in sorted(v)], [p[2] for p in sorted(v)])
            for m, v in out.items() if all(p[1] is not None for p in v)}


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


def chart_error(result, plt, path: Path, methods):
    f, ax = fig(plt)
    cv = curves(result, "time")
    for m in methods:
        if m.name not in cv or m.name == "bdpt-lafortune":     # in the weighting chart only
            continue
        xs, es = cv[m.name]
        ax.loglog(xs, es, m.style, color=m.color, marker="o", ms=3, label=m.label)
    eq = result.get("equal_time")
    if eq:
        ax.axvline(eq["x"], color="0.7", lw=0.8, ls=":")
    no_minor_labels(ax)
    ax.set_xlabel("render time / s (compile excluded)")
    ax.set_ylabel("relative MSE")
    ax.set_title("%s (%dx%d, max_depth %d)" % (result["scene"], result["width"], result["height"],
                                               result["max_depth"]), fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    save(f, path)


def chart_weighting(result, plt, path: Path, methods):
    f, ax = fig(plt)
    names = [m for m in methods if m.name in WEIGHTING]
    cv = curves(result, "spp")
    for m in names:
        if m.name in cv:
            xs, es = cv[m.name]
            ax.loglog(xs, es, m.style, color=m.color, marker="o", ms=3, label=m.label)
    if cv.get("bdpt-power"):
        xs, es = cv["bdpt-power"]
        ax.loglog(xs, [es[0] * xs[0] / x for x in xs], color="0.6", lw=0.8, ls=":", label="1/spp")
    no_minor_labels(ax)
    ax.set_xlabel("samples per pixel")
    ax.set_ylabel("relative MSE")
    ax.set_title("MIS weighting: %s" % result["scene"], fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    save(f, path)


# -- throughput & scaling ------------------------------------------------------------------------------
CORNELL = C.ROOT / "scenes" / "cornell-box.xml"


def connection_strategies(d: int) -> int:
    """Number of (s, t) with s, t >= 2 and s + t - 1 <= d (the connection kernels)."""
    return sum(max(0, k - 2) for k in range(3, d + 1)) if d >= 0 else -1


def scaling(cfg: Config, plt, charts: Path, progress) -> dict:
    out = {"pixels_spp": [], "depth": []}
    # time vs pixels x spp
    for res in cfg.grid_res:
        sc = TP.load_scene(CORNELL, res, res, 8)
        for m in (C.BDPT_POWER, C.PATH):
            C.render(m, sc, cfg.grid_spp[0], 99, 8)
            for spp in cfg.grid_spp:
                o = [C.render(m, sc, spp, 5 + k, 8) for k in range(2)]
                t = C.median([x.timing.run for x in o])
                out["pixels_spp"].append({"method": m.name, "res": res, "spp": spp,
                                          "samples": res * res * spp, "time": t})
                progress("  scaling %-10s %4dx%-4d %3d spp: %.4f s" % (m.name, res, res, spp, t))
    fits = {}
    for name in ("bdpt-power", "path"):
        pts = [(r["samples"], r["time"]) for r in out["pixels_spp"] if r["method"] == name]
        n = np.array([p[0] for p in pts], float)
        t = np.array([p[1] for p in pts], float)
        A = np.stack([np.ones_like(n), n], axis=1)
        (a, b), *_ = np.linalg.lstsq(A, t, rcond=None)
        pred = a + b * n
        r2 = 1 - np.sum((t - pred) ** 2) / max(np.sum((t - t.mean()) ** 2), 1e-30)
        # log-log slope (1 = linear in samples)
        slope = float(np.polyfit(np.log(n), np.log(t), 1)[0]) if len(n) > 1 else float("nan")
        fits[name] = {"overhead_s": float(a), "per_sample_s": float(b), "r2": float(r2),
                      "loglog_slope": slope, "samples_per_s_asymptotic": 1 / b if b > 0 else None}
    out["fits"] = fits
    f, ax = fig(plt)
    for m in (C.BDPT_POWER, C.PATH):
        pts = sorted((r["samples"], r["time"]) for r in out["pixels_spp"] if r["method"] == m.name)
        ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o", color=m.color, ms=4, label=m.label)
        ft = fits[m.name]
        xs = np.geomspace(pts[0][0], pts[-1][0], 50)
        ax.loglog(xs, ft["overhead_s"] + ft["per_sample_s"] * xs, "-", color=m.color, lw=0.8,
                  label="fit %.3g s + N/%.3g/s" % (ft["overhead_s"], 1 / ft["per_sample_s"])
                  if ft["per_sample_s"] > 0 else "fit")
    no_minor_labels(ax)
    ax.set_xlabel("samples (pixels x spp)")
    ax.set_ylabel("render time / s")
    ax.set_title("Time vs pixels x spp (Cornell box, max_depth 8)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    save(f, charts / "scaling_samples.png")

    # time vs max_depth
    res, spp = cfg.depth_res, cfg.depth_spp
    for d in cfg.depths:
        sc = TP.load_scene(CORNELL, res, res, d)
        for m in (C.BDPT_POWER, C.PATH):
            C.render(m, sc, spp, 99, d)
            o = [C.render(m, sc, spp, 5 + k, d) for k in range(3)]
            t = C.median([x.timing.run for x in o])
            out["depth"].append({"method": m.name, "max_depth": d, "time": t,
                                 "kernels_per_pass": o[0].timing.kernels / o[0].passes,
                                 "connections": connection_strategies(d) if m.engine == "bdpt" else 0,
                                 "rays_per_sample": o[0].rays_per_sample})
            progress("  depth   %-10s max_depth=%-3d %.4f s  %d kernels/pass"
                     % (m.name, d, t, o[0].timing.kernels / o[0].passes))
    b = [r for r in out["depth"] if r["method"] == "bdpt-power"]
    if len(b) >= 3:
        ds = np.array([r["max_depth"] for r in b], float)
        ts = np.array([r["time"] for r in b], float)
        out["depth_fit_quadratic"] = [float(c) for c in np.polyfit(ds, ts, 2)]
        ks = np.array([r["kernels_per_pass"] for r in b], float)
        out["depth_fit_kernels_quadratic"] = [float(c) for c in np.polyfit(ds, ks, 2)]
    f, ax = fig(plt)
    for m in (C.BDPT_POWER, C.PATH):
        pts = [(r["max_depth"], r["time"]) for r in out["depth"] if r["method"] == m.name]
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=m.color, ms=4, label=m.label + " time")
    ax.set_xlabel("max_depth")
    ax.set_ylabel("render time / s")
    ax2 = ax.twinx()
    ax2.plot([r["max_depth"] for r in b], [r["connections"] for r in b], "s--", color="0.5", ms=3,
             label="connection strategies (s,t>=2)")
    ax2.plot([r["max_depth"] for r in b], [r["kernels_per_pass"] for r in b], "^:", color="C2", ms=3,
             label="BDPT kernel launches / pass")
    ax2.set_ylabel("count")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper left")
    ax.set_title("Time vs max_depth (Cornell box %dx%d, %d spp)" % (res, res, spp), fontsize=10)
    ax.grid(True, alpha=0.3)
    save(f, charts / "scaling_depth.png")
    return out


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
def pyramid(spec, cfg: Config, plt, path: Path, progress) -> dict | None:
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
    # Each cell has its own exposure (printed in its title): at one common exposure most
    # strategies are nearly black.  The cell's mean tells its share of the image.
    base_exposure = C.auto_exposure(img)
    fw, fh = 1.25 * (K + 1), 1.25 * h / w * K + 0.6
    f, axes = plt.subplots(K, K + 1, figsize=(fw, fh), dpi=100, squeeze=False)
    energy = {}
    for k in range(1, K + 1):
        for s in range(0, K + 1):
            ax = axes[k - 1][s]
            ax.set_xticks([])
            ax.set_yticks([])
            t = k + 1 - s
            if s > k or t < 1:
                ax.axis("off")
                continue
            im = strat.get((s, t))
            if im is None:
                im = np.zeros_like(img)
                ax.set_facecolor("0.85")
            energy["%d,%d" % (s, t)] = float(np.mean(im))
            exposure = C.auto_exposure(im) if np.any(im > 0) else base_exposure
            ax.imshow(C.to_srgb8(im, exposure), interpolation="nearest")
            share = float(np.mean(im)) / max(float(np.mean(img)), 1e-12)
            ax.set_title("s=%d t=%d  %.0f%%  x%.2g" % (s, t, 100 * share, exposure / base_exposure),
                         fontsize=5.5, pad=1)
            if s == 0:
                ax.set_ylabel("k=%d" % k, fontsize=7)
    f.suptitle("%s: MIS-weighted strategies (power); row k = s+t-1 edges, column s;\n"
               "title: share of the image's mean, exposure relative to the full image"
               % spec.name, fontsize=7)
    f.subplots_adjust(wspace=0.05, hspace=0.25, left=0.04, right=0.99, bottom=0.01, top=0.88)
    path.parent.mkdir(parents=True, exist_ok=True)
    f.savefig(path, dpi=100)
    plt.close(f)
    # the full image next to it
    full = path.with_name(path.stem + "_image.png")
    from PIL import Image  # matplotlib depends on pillow
    Image.fromarray(C.to_srgb8(img, base_exposure)).resize((w * max(1, 192 // w), h * max(1, 192 // w)),
                                                      Image.NEAREST).save(full)
    return {"scene": spec.name, "width": w, "height": h, "spp": cfg.pyramid_spp, "rows": K,
            "strategies": len(strat), "max_abs_sum_error": sum_err, "mean_per_strategy": energy,
            "image_mean": float(img.mean()), "chart": path.name, "image": full.name}


# -- report ----------------------------------------------------------------------------------------------
def results_md(res: dict, cfg: Config, chart_rel: str) -> str:
    m = res["machine"]
    L = []
    w = L.append
    label = {"smoke": "SMOKE-TEST", "quick": "QUICK", "full": "FULL"}[cfg.mode]
    w("# Benchmark results (%s run)" % label)
    w("")
    if cfg.mode != "full":
        w("> **These are %s figures** (tiny images, few samples, %s). They only show that the "
          "suite runs and the rough trends; they are to be replaced by the full run "
          "(`python -m benchmarks.run` on an idle machine)." % (cfg.mode, "%dx%d" % (cfg.res, cfg.res)))
        w("")
    w("Reproduce: `%s` (from the repository root; took %.0f s)." % (res["command"], res["elapsed"]))
    w("")
    if cfg.mode != "full":
        w("Caveats of these small runs:")
        w("")
        w("- At %dx%d a BDPT render costs a fixed ~0.03-0.15 s whatever its spp (Python tracing "
          "and launching ~%s kernels plus ~%s smaller launches per pass), so the equal-time "
          "comparisons are biased against BDPT here; the equal-ray table is the comparison that "
          "does not depend on the image size." % (cfg.res, cfg.res, _tp(res, "kernels_per_pass"),
                                                 _tp(res, "other_launches_per_pass")))
        w("- The machine was shared (load average at start %.2f on %d cores): times vary by up "
          "to 2-3x between runs." % (res["machine"]["load_avg_1min"], res["machine"]["cpu_count"]))
        w("- Few renders per level: in scenes with fireflies (caustics, SDS, veach-bidir) the "
          "relative MSE of one render is dominated by rare outliers and jumps between levels.")
        w("")
    w("Machine: %s, %d cores (os.cpu_count), load average %.2f at start; %s; Python %s; "
      "variant `%s`; Mitsuba %s; Dr.Jit %s; LLVM %s; bdpt-drjit %s. Date: %s."
      % (m["cpu"], m["cpu_count"], m["load_avg_1min"], m["platform"], m["python"], m["variant"],
         m["mitsuba"], m["drjit"], m["llvm"], m["bdpt_drjit"], m["date"]))
    w("")
    if res.get("notes"):
        for n in res["notes"]:
            w("- note: %s" % n)
        w("")
    w("Method: wall time (`time.perf_counter()`) around each render including the evaluation "
      "of its image, minus the LLVM compile time of kernels compiled inside it (Dr.Jit kernel "
      "history); one warm-up render per method and scene. Error = relative MSE "
      "(mean of (img-ref)^2/(ref^2+1e-2)) against the reference; MARE = mean |img-ref|/(ref+1e-2).")
    w("")
    scenes = [s for s in res.get("scenes", []) if s]
    if scenes:
        w("## Scene suite")
        w("")
        w("| scene | size | max_depth | reference | expected failure |")
        w("|---|---|---|---|---|")
        for s in scenes:
            r = s["reference"]
            ref = ("Tungsten EXR / %d" % r["downsample"] if r["method"] == "exr"
                   else "%s %d spp (%.1f s)" % (r["method"], r["spp"], r["time"]))
            w("| %s | %dx%d | %d | %s | %s |" % (s["scene"], s["width"], s["height"], s["max_depth"], ref,
                                                 s["expected_failure"]))
        for sk in res.get("skipped_scenes", []):
            w("| %s | skipped | | | %s |" % (sk[0], sk[1]))
        w("")
        methods = [mm for mm in res["methods"]]
        for key, title, xname in (("equal_time", "Error at equal time", "time"),
                                  ("equal_rays", "Error at equal ray count", "rays")):
            w("## %s (ratio to Mitsuba `path`; < 1: better than path)" % title)
            w("")
            w("Relative MSE each method reaches with the same %s x = what BDPT (power) used "
              "at its last spp level, interpolated in log-log through spp; `~` = "
              "extrapolated (at most %gx beyond the measured range, else n/a)."
              % (xname, C.MAX_EXTRAPOLATION))
            w("")
            w("| scene | %s (x) | " % xname + " | ".join(methods) + " |")
            w("|---|---|" + "---|" * len(methods))
            for s in scenes:
                eq = s.get(key)
                if not eq:
                    continue
                cells = []
                for mm in methods:
                    r = eq["methods"].get(mm)
                    cells.append("n/a" if r is None else ratio_str(r.get("err_ratio"), r["err_extrapolated"]))
                w("| %s | %.3g | %s |" % (s["scene"], eq["x"], " | ".join(cells)))
            w("")
        w("## Time to reach a target error (ratio to Mitsuba `path`; < 1: faster)")
        w("")
        w("Target = the larger of the relative MSEs that Mitsuba `path` and BDPT (power) reach "
          "at the equal-time budget above; `never` = the curve stops improving before it "
          "(e.g. a missing effect); `~` = extrapolated; n/a = more than %gx beyond the "
          "measured range." % C.MAX_EXTRAPOLATION)
        w("")
        w("| scene | target relMSE | " + " | ".join(methods) + " |")
        w("|---|---|" + "---|" * len(methods))
        for s in scenes:
            eq = s.get("equal_time")
            if not eq:
                continue
            cells = []
            for mm in methods:
                r = eq["methods"].get(mm)
                cells.append("n/a" if r is None else ratio_str(r.get("x_ratio"), r["x_extrapolated"]))
            w("| %s | %.3g | %s |" % (s["scene"], eq["target_error"] or float("nan"), " | ".join(cells)))
        w("")
        w("## Rays per sample and per second")
        w("")
        w("BDPT counts its rays; for Mitsuba's integrators the rays per sample are ESTIMATED "
          "by a probe that replays their loop (common.estimate_mitsuba_rays): `est.`.")
        w("")
        w("| scene | " + " | ".join(methods) + " |")
        w("|---|" + "---|" * len(methods))
        for s in scenes:
            cells = []
            for mm in methods:
                recs = [r for r in s["records"] if r["method"] == mm]
                if not recs:
                    cells.append("n/a")
                    continue
                r = recs[-1]
                rps = r["rays_per_sample"]
                sps = r["spp"] * r["pixels"] / r["time"]
                if rps is None:
                    cells.append("n/a; %.3g samples/s" % sps)
                else:
                    cells.append("%.3g%s rays/sample; %.3g Mrays/s" % (rps, " est." if r.get("rays_estimated") else "",
                                                                    rps * sps / 1e6))
            w("| %s | %s |" % (s["scene"], " | ".join(cells)))
        w("")
        w("## Charts: error against time, and MIS weighting schemes")
        w("")
        for s in scenes:
            w("### %s" % s["scene"])
            w("")
            w("%s" % s["expected_failure"])
            w("")
            w("![%s error](%s/%s) ![%s weighting](%s/%s)" % (s["scene"], chart_rel, s["chart"], s["scene"],
                                                           chart_rel, s["weighting_chart"]))
            w("")
            fin = {}
            for r in s["records"]:
                fin[r["method"]] = r
            w("| method | last spp | time / s | relMSE | MARE | mean (ref %.4g) | nonfinite |" % s["ref_mean"])
            w("|---|---|---|---|---|---|---|")
            for mm, r in fin.items():
                w("| %s | %d | %.4g | %.4g | %.4g | %.4g | %d |" % (mm, r["spp"], r["time"], r["relmse"],
                                                                r["mare"], r["mean"], r["nonfinite"]))
            w("")
    tp = res.get("throughput")
    if tp:
        w("## Throughput (Cornell box, `benchmarks/throughput.py`)")
        w("")
        w("```")
        w(TP.report(tp, tp.get("cold")))
        w("```")
        w("")
    sc = res.get("scaling")
    if sc:
        w("## Scaling")
        w("")
        w("![time vs samples](%s/scaling_samples.png) ![time vs depth](%s/scaling_depth.png)"
          % (chart_rel, chart_rel))
        w("")
        w("Fit time = a + b * (pixels x spp):")
        w("")
        w("| method | overhead a / s | samples/s (1/b) | R^2 | log-log slope |")
        w("|---|---|---|---|---|")
        for name, f in sc["fits"].items():
            w("| %s | %.3g | %s | %.4f | %.3f |" % (name, f["overhead_s"],
                                                 "%.3g" % f["samples_per_s_asymptotic"]
                                                 if f["samples_per_s_asymptotic"] else "n/a",
                                                 f["r2"], f["loglog_slope"]))
        w("")
        w("Time vs max_depth (Cornell box):")
        w("")
        w("| max_depth | bdpt time / s | bdpt kernels/pass | connection strategies | bdpt rays/sample | path time / s |")
        w("|---|---|---|---|---|---|")
        for d in sorted({r["max_depth"] for r in sc["depth"]}):
            b = next(r for r in sc["depth"] if r["method"] == "bdpt-power" and r["max_depth"] == d)
            p = next(r for r in sc["depth"] if r["method"] == "path" and r["max_depth"] == d)
            w("| %d | %.4f | %.0f | %d | %.3g | %.4f |" % (d, b["time"], b["kernels_per_pass"], b["connections"],
                                                       b["rays_per_sample"] or 0, p["time"]))
        if sc.get("depth_fit_quadratic"):
            a2, a1, a0 = sc["depth_fit_quadratic"]
            w("")
            w("Quadratic fit of bdpt time: %.3g d^2 + %.3g d + %.3g s; kernel launches per pass: "
              "%.3g d^2 + %.3g d + %.3g." % (a2, a1, a0, *sc["depth_fit_kernels_quadratic"]))
        w("")
    if res.get("rss"):
        w("## Peak memory (one subprocess per size, 1 spp, Cornell box)")
        w("")
        w("| method | size | peak RSS / MiB | RSS before render / MiB | Dr.Jit peak / MiB | passes | time / s |")
        w("|---|---|---|---|---|---|---|")
        for r in res["rss"]:
            if "error" in r:
                w("| %s | %dx%d | failed: %s | | | | |" % (r["method"], r["width"], r["height"], r["error"]))
            else:
                w("| %s | %dx%d | %.0f | %.0f | %.0f | %d | %.2f |" % (r["method"], r["width"], r["height"],
                                                                 r["rss_peak_mib"], r["baseline_rss_mib"],
                                                                 r["jit_peak_mib"], r["passes"], r["first_wall"]))
        w("")
    if res.get("pyramids"):
        w("## Strategy pyramids")
        w("")
        w("Per-(s,t) MIS-weighted images of BDPT (power heuristic), row k = s+t-1 (path edges), "
          "column s (light vertices); each cell has its own exposure (relative to the full image, "
          "in its title, with its share of the image's mean). Cf. Veach's thesis "
          "fig. 10.3 / Adamsen's fig. 16.")
        w("")
        for p in res["pyramids"]:
            if not p:
                continue
            w("### %s (%dx%d, %d spp; strategies sum to the image within %.2g)"
              % (p["scene"], p["width"], p["height"], p["spp"], p["max_abs_sum_error"]))
            w("")
            w("![%s pyramid](%s/%s) ![%s image](%s/%s)" % (p["scene"], chart_rel, p["chart"], p["scene"],
                                                         chart_rel, p["image"]))
            w("")
    if res.get("observations"):
        w("## Observations (automatic checks)")
        w("")
        for o in res["observations"]:
            w("- %s" % o)
        w("")
    return "\n".join(L)


def recs_of(scene_result, method):
    return sorted((r for r in scene_result["records"] if r["method"] == method), key=lambda r: r["spp"])


def _tp(res, key):
    tp = res.get("throughput") or {}
    v = (tp.get("bdpt-power") or {}).get(key)
    return "%.0f" % v if v is not None else "?"


def observations(res: dict) -> list:
    """Automatic flags: BDPT losing where it should win, non-finite pixels, ..."""
    obs = []
    should_win = {"cornell-light-up", "glass-caustic-area", "point-caustic", "veach-bidir"}
    for s in res.get("scenes", []):
        if not s:
            continue
        eq = s.get("equal_time")
        if eq and "bdpt-power" in eq["methods"] and "path" in eq["methods"]:
            r = eq["methods"]["bdpt-power"]["err_ratio"]
            if s["scene"] in should_win and r > 1:
                why = ""
                pe = [q["relmse"] for q in recs_of(s, "path")][-3:]
                if len(pe) == 3 and pe[-1] > 0.8 * pe[0]:
                    why = (" Path's error has stopped falling (%.3g -> %.3g over its last 3 levels): "
                           "its image misses an effect (bias), which relMSE charges less than "
                           "BDPT's noise at this small budget; BDPT should cross below it with "
                           "more time." % (pe[0], pe[-1]))
                obs.append("%s: BDPT (power) has %.2fx path's error at equal time, although it should "
                           "win here.%s" % (s["scene"], r, why))
            elif s["scene"] in should_win:
                obs.append("%s: BDPT (power) reaches %.2fx path's error at equal time (expected < 1)."
                           % (s["scene"], r))
        recs = s["records"]
        bad = [r for r in recs if r["nonfinite"]]
        if bad:
            obs.append("%s: non-finite pixels from %s" % (s["scene"], sorted({r["method"] for r in bad})))
        bal = [r for r in recs if r["method"] == "bdpt-balance"]
        pw = [r for r in recs if r["method"] == "bdpt-power"]
        if bal and pw and bal[-1]["relmse"] < 0.8 * pw[-1]["relmse"]:
            obs.append("%s: balance heuristic beats power (%.3g vs %.3g relMSE at %d spp)"
                       % (s["scene"], bal[-1]["relmse"], pw[-1]["relmse"], pw[-1]["spp"]))
    return obs


# -- main ----------------------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help="a few minutes: 32x32, 3 spp levels")
    g.add_argument("--smoke", action="store_true", help="CI smoke test: 2 scenes, 16x16, 2 levels")
    ap.add_argument("--out", type=Path, help="output folder (default benchmarks/results)")
    ap.add_argument("--scenes", help="comma-separated scene names (default: the mode's)")
    ap.add_argument("--methods", help="comma-separated methods (default: %s)" % ",".join(ALL_METHODS))
    ap.add_argument("--res", type=int, help="image width for the error runs")
    ap.add_argument("--levels", help="comma-separated spp levels of the BDPT runs")
    ap.add_argument("--ref-spp", type=int, help="reference spp (BDPT; Mitsuba uses 4x)")
    ap.add_argument("--seeds", type=int, help="renders per level (errors averaged)")
    ap.add_argument("--skip", default="", help="comma-separated sections to skip: " + ",".join(SECTIONS))
    ap.add_argument("--no-publish", action="store_true",
                    help="do not copy charts to benchmarks/charts and RESULTS.md to benchmarks/")
    ap.add_argument("--report-only", action="store_true",
                    help="redo the tables, charts and RESULTS.md from OUT/results.json without rendering")
    args = ap.parse_args(argv)
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    cfg = replace(MODES[mode])
    if args.scenes:
        cfg.scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
        unknown = [s for s in cfg.scenes if s not in SCENES]
        if unknown:
            ap.error("unknown scenes %s (known: %s)" % (unknown, ", ".join(SCENES)))
        cfg.pyramid_scenes = [s for s in cfg.pyramid_scenes if s in cfg.scenes]
    if args.methods:
        cfg.methods = [s.strip() for s in args.methods.split(",") if s.strip()]
        unknown = [s for s in cfg.methods if s not in C.METHODS]
        if unknown:
            ap.error("unknown methods %s (known: %s)" % (unknown, ", ".join(C.METHODS)))
    if args.res:
        cfg.res = args.res
    if args.levels:
        cfg.levels = [int(x) for x in args.levels.split(",")]
    if args.ref_spp:
        cfg.ref_spp = args.ref_spp
    if args.seeds:
        cfg.seeds = args.seeds
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    if skip - set(SECTIONS):
        ap.error("unknown sections to skip: %s" % sorted(skip - set(SECTIONS)))
    out = args.out or C.RESULTS
    publish = args.out is None and not args.smoke and not args.no_publish
    charts = out / "charts"
    charts.mkdir(parents=True, exist_ok=True)
    refs = out / "refs"
    progress = Progress()
    plt = C.matplotlib()
    cmd = "python -m benchmarks.run" + ("" if argv is None and len(sys.argv) <= 1 else " " + " ".join(
        sys.argv[1:] if argv is None else argv))
    if args.report_only:
        return report_only(out, publish, plt, progress)
    progress("benchmarks.run, %s mode -> %s" % (mode, out))
    methods = C.available_methods(cfg.methods)
    res = {"mode": mode, "command": cmd, "machine": C.machine_info(), "config": cfg.__dict__,
           "methods": [m.name for m in methods], "notes": [], "scenes": [], "skipped_scenes": []}
    for name in cfg.methods:
        ok, why = C.method_supported(C.METHODS[name])
        if not ok:
            res["notes"].append("method %s skipped: %s" % (name, why))
    if "bdpt-pt" not in res["methods"]:
        res["notes"].append("the engine has no PT-only / LT-only strategy switch (`strategies=`); "
                            "'bdpt-no-lt' (light_image=False) still uses connections and NEE, and "
                            "Mitsuba's path / ptracer stand in for pure path / light tracing")
    t_start = time.perf_counter()
    if "error" not in skip:
        for i, name in enumerate(cfg.scenes):
            spec = SCENES[name]
            progress("[%d/%d] scene %s" % (i + 1, len(cfg.scenes), name))
            r = error_for_scene(spec, cfg, methods, refs, progress)
            if r is None:
                res["skipped_scenes"].append((name, spec.available()[1]))
                continue
            r["equal_time"] = equal_comparison(r, "time")
            r["equal_rays"] = equal_comparison(r, "rays")
            r["chart"] = "%s_error_time.png" % name
            r["weighting_chart"] = "%s_weighting.png" % name
            chart_error(r, plt, charts / r["chart"], methods)
            chart_weighting(r, plt, charts / r["weighting_chart"], methods)
            res["scenes"].append(r)
            C.write_json(out / "results.json", res)
    if "throughput" not in skip:
        progress("throughput: Cornell box %dx%d, %d spp" % (cfg.tp_res, cfg.tp_res, cfg.tp_spp))
        cold = cfg.cold and "cold" not in skip
        res["throughput"] = TP.run(cfg.tp_res, cfg.tp_res, cfg.tp_spp, cfg.tp_repeats, 8, CORNELL,
                                   cold=cold, cold_res=(cfg.cold_res, cfg.cold_res))
        C.log(TP.report(res["throughput"], res["throughput"].get("cold")))
    if "scaling" not in skip:
        progress("scaling: time vs pixels x spp and vs max_depth")
        res["scaling"] = scaling(cfg, plt, charts, progress)
    if "rss" not in skip and cfg.rss_sizes:
        progress("peak memory per resolution")
        res["rss"] = rss_section(cfg, progress)
    if "pyramid" not in skip:
        res["pyramids"] = []
        for name in cfg.pyramid_scenes:
            progress("strategy pyramid: %s" % name)
            res["pyramids"].append(pyramid(SCENES[name], cfg, plt, charts / ("pyramid_%s.png" % name), progress))
    res["observations"] = observations(res)
    res["elapsed"] = time.perf_counter() - t_start
    C.write_json(out / "results.json", res)
    finish(res, cfg, out, publish, progress)
    return 0


def report_only(out: Path, publish: bool, plt, progress) -> int:
    import json
    res = json.loads((out / "results.json").read_text())
    cfg = Config(**res["config"])
    methods = [C.METHODS[m] for m in res["methods"]]
    charts = out / "charts"
    for r in res["scenes"]:
        if not r:
            continue
        r["equal_time"] = equal_comparison(r, "time")
        r["equal_rays"] = equal_comparison(r, "rays")
        chart_error(r, plt, charts / r["chart"], methods)
        chart_weighting(r, plt, charts / r["weighting_chart"], methods)
    res["observations"] = observations(res)
    C.write_json(out / "results.json", res)
    finish(res, cfg, out, publish, progress)
    return 0


def small_png(src: Path, dst: Path) -> None:
    """Copy a chart as a palette PNG (a third of the size, to be committed)."""
    try:
        from PIL import Image
        with Image.open(src) as im:
            im.convert("RGB").quantize(colors=128).save(dst, optimize=True)
    except Exception:  # noqa: BLE001  (no pillow, odd image: plain copy)
        shutil.copy2(src, dst)


def finish(res, cfg, out: Path, publish: bool, progress) -> None:
    charts = out / "charts"
    md = results_md(res, cfg, "charts")
    (out / "RESULTS.md").write_text(md)
    if publish:
        C.CHARTS.mkdir(parents=True, exist_ok=True)
        for png in charts.glob("*.png"):
            small_png(png, C.CHARTS / png.name)
        (C.BENCH / "RESULTS.md").write_text(md)
        progress("published charts to %s and %s" % (C.CHARTS, C.BENCH / "RESULTS.md"))
    for o in res["observations"]:
        progress("observation: " + o)
    progress("done in %.0f s; results in %s" % (res["elapsed"], out))


if __name__ == "__main__":
    sys.exit(main())
