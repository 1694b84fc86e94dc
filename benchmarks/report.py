"""RESULTS.md from the results dictionary (results.json): the prose of
report_template.md, the tables built here, and the automatic observations."""
from __future__ import annotations

import math
import re
from pathlib import Path

from . import common as C
from . import throughput as TP

TEMPLATE = Path(__file__).with_name("report_template.md")
LABELS = {"smoke": "SMOKE-TEST", "quick": "QUICK", "full": "FULL"}
SHOULD_WIN = {"cornell-light-up", "glass-caustic-area", "point-caustic", "veach-bidir"}


def template_sections(path: Path = TEMPLATE) -> dict:
    """name -> text of each section of the template (a line "@@ name" starts one)."""
    parts = re.split(r"^@@ (\w+)\n", path.read_text(), flags=re.M)
    return {name: body.strip("\n") for name, body in zip(parts[1::2], parts[2::2])}


class Report:
    """Sections of the template, filled in and put one after another."""

    def __init__(self, chart_rel: str):
        self.sections = template_sections()
        self.chart_rel = chart_rel
        self.blocks = []

    def add(self, name: str, *args, **values) -> None:
        self.blocks.append(self.sections[name].format(*args, chart_rel=self.chart_rel, **values))

    def text(self) -> str:
        return "\n\n".join(self.blocks) + "\n"


def table(header, rows) -> str:
    """A Markdown table; an empty cell is written "| |"."""
    def line(cells):
        return "|" + "|".join(" %s " % c if c != "" else " " for c in cells) + "|"
    return "\n".join([line(header), "|" + "---|" * len(header)] + [line(r) for r in rows])


def ratio_str(x, extrapolated=False, inf_text="never"):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if math.isinf(x):
        return inf_text
    s = "%.3g" % x
    return ("~" + s) if extrapolated else s


def _tp(res, key):
    tp = res.get("throughput") or {}
    v = (tp.get("bdpt-power") or {}).get(key)
    return "%.0f" % v if v is not None else "?"


def results_md(res: dict, cfg, chart_rel: str) -> str:
    """The whole of RESULTS.md; cfg is the run's suite.Config (its mode and res)."""
    rep = Report(chart_rel)
    header(rep, res, cfg)
    scenes = [s for s in res.get("scenes", []) if s]
    if scenes and not cfg.weighting:
        scene_sections(rep, res, scenes)
    if any(s.get("weighting") for s in scenes):
        weighting_section(rep, [s for s in scenes if s.get("weighting")])
    tp = res.get("throughput")
    if tp:
        rep.add("throughput", report=TP.report(tp, tp.get("cold")))
    if res.get("scaling"):
        scaling_sections(rep, res["scaling"])
    if res.get("rss"):
        rep.add("rss", table=rss_table(res["rss"]))
    if res.get("pyramids"):
        rep.add("pyramids")
        for p in res["pyramids"]:
            if p:
                rep.add("pyramid", **p)
    if res.get("observations"):
        rep.add("observations", observations="\n".join("- %s" % o for o in res["observations"]))
    return rep.text()


def as_block(md: str) -> str:
    """A report as a block of benchmarks/RESULTS.md: without its title, every heading
    one level down (the page's own heading and reading stand above the block)."""
    lines = md.split("\n")
    if lines and lines[0].startswith("# "):
        lines = lines[1:]
    out, code = [], False
    for line in lines:
        code ^= line.startswith("```")
        out.append("#" + line if not code and re.match(r"#+ ", line) else line)
    return "\n".join(out).strip("\n")


def header(rep: Report, res: dict, cfg) -> None:
    m = res["machine"]
    small = cfg.mode != "full"
    rep.add("title", label=LABELS[cfg.mode])
    if small:
        rep.add("small_run_note", mode=cfg.mode, res=cfg.res)
    rep.add("reproduce", command=res["command"], elapsed=res["elapsed"])
    if small:
        rep.add("small_run_caveats", res=cfg.res, kernels=_tp(res, "kernels_per_pass"),
                other_launches=_tp(res, "other_launches_per_pass"), **m)
    rep.add("machine", **m)
    if res.get("notes"):
        rep.add("notes", notes="\n".join("- note: %s" % n for n in res["notes"]))
    rep.add("method")


# -- the scene suite --------------------------------------------------------------------------------
def scene_sections(rep: Report, res: dict, scenes: list) -> None:
    methods = list(res["methods"])
    rep.add("scene_suite", table=suite_table(scenes, res.get("skipped_scenes", [])))
    for key, title, xname in (("equal_time", "Error at equal time", "time"),
                              ("equal_rays", "Error at equal ray count", "rays")):
        rows = [[s["scene"], "%.3g" % s[key]["x"]] + ratio_cells(s[key], methods, "err_ratio", "err_extrapolated")
                for s in scenes if s.get(key)]
        rep.add("equal_cost", title=title, xname=xname, max_extrapolation=C.MAX_EXTRAPOLATION,
                table=table(["scene", "%s (x)" % xname] + methods, rows))
    rows = [[s["scene"], "%.3g" % (s["equal_time"]["target_error"] or float("nan"))]
            + ratio_cells(s["equal_time"], methods, "x_ratio", "x_extrapolated")
            for s in scenes if s.get("equal_time")]
    rep.add("time_to_target", max_extrapolation=C.MAX_EXTRAPOLATION,
            table=table(["scene", "target relMSE"] + methods, rows))
    rows = [[s["scene"]] + [rays_cell(s, mm) for mm in methods] for s in scenes]
    rep.add("rays", table=table(["scene"] + methods, rows))
    rep.add("charts")
    for s in scenes:
        rep.add("scene_charts", table=last_level_table(s), **s)


def weighting_section(rep: Report, scenes: list) -> None:
    """The MIS weighting schemes against the power heuristic: error at its time and at
    its spp (with each scheme's time for those spp), and each scene's chart."""
    others = [m for m in C.WEIGHTING[1:] if any(m in s["weighting"]["time"]["methods"] for s in scenes)]
    at_time, at_spp = [], []
    for s in scenes:
        eq = s["weighting"]["time"]
        at_time.append([s["scene"], "%.3g" % eq["x"], "%.3g" % eq["methods"]["bdpt-power"]["err_at_x"]]
                       + ratio_cells(eq, others, "err_ratio", "err_extrapolated"))
        eq = s["weighting"]["spp"]
        power_time = time_at_spp(s, "bdpt-power", eq["x"])
        cells = []
        for mm, cell in zip(others, ratio_cells(eq, others, "err_ratio", "err_extrapolated")):
            t = time_at_spp(s, mm, eq["x"])
            cells.append(cell if t is None or not power_time else "%s (%.2fx)" % (cell, t / power_time))
        at_spp.append([s["scene"], "%d" % eq["x"], "%.3g" % eq["methods"]["bdpt-power"]["err_at_x"]] + cells)
    charts = "\n\n".join("![%s weighting](%s/%s)" % (s["scene"], rep.chart_rel, s["weighting_chart"])
                          for s in scenes if s.get("weighting_chart"))
    rep.add("weighting", max_extrapolation=C.MAX_EXTRAPOLATION, charts=charts,
            time_table=table(["scene", "time x / s", "power: relMSE"] + others, at_time),
            spp_table=table(["scene", "spp", "power: relMSE"] + others, at_spp))


def time_at_spp(s: dict, method: str, spp) -> float | None:
    """A method's (median) render time at a level of ``spp`` samples, if it rendered one."""
    times = [r["time"] for r in s["records"] if r["method"] == method and r["spp"] == spp]
    return times[0] if times else None


def suite_table(scenes: list, skipped: list) -> str:
    rows = []
    for s in scenes:
        r = s["reference"]
        ref = ("Tungsten EXR / %d" % r["downsample"] if r["method"] == "exr"
               else "%s %d spp (%.1f s)" % (r["method"], r["spp"], r["time"]))
        rows.append([s["scene"], "%dx%d" % (s["width"], s["height"]), "%d" % s["max_depth"], ref,
                     s["expected_failure"]])
    rows += [[name, "skipped", "", "", why] for name, why in skipped]
    return table(["scene", "size", "max_depth", "reference", "expected failure"], rows)


def ratio_cells(eq: dict, methods: list, value: str, extrapolated: str) -> list:
    """Each method's ratio to path from an equal-cost comparison, as table cells."""
    cells = []
    for mm in methods:
        r = eq["methods"].get(mm)
        cells.append("n/a" if r is None else ratio_str(r.get(value), r[extrapolated]))
    return cells


def rays_cell(s: dict, method: str) -> str:
    """Rays per sample and per second of a method's last level in a scene."""
    recs = [r for r in s["records"] if r["method"] == method]
    if not recs:
        return "n/a"
    r = recs[-1]
    rps = r["rays_per_sample"]
    sps = r["spp"] * r["pixels"] / r["time"]
    if rps is None:
        return "n/a; %.3g samples/s" % sps
    return "%.3g%s rays/sample; %.3g Mrays/s" % (rps, " est." if r.get("rays_estimated") else "", rps * sps / 1e6)


def last_level_table(s: dict) -> str:
    last = {}
    for r in s["records"]:
        last[r["method"]] = r
    rows = [[mm, "%d" % r["spp"], "%.4g" % r["time"], "%.4g" % r["relmse"], "%.4g" % r["mare"],
             "%.4g" % r["mean"], "%d" % r["nonfinite"]] for mm, r in last.items()]
    return table(["method", "last spp", "time / s", "relMSE", "MARE", "mean (ref %.4g)" % s["ref_mean"],
                  "nonfinite"], rows)


# -- scaling and memory -----------------------------------------------------------------------------
def scaling_sections(rep: Report, sc: dict) -> None:
    fits = [[name, "%.3g" % f["overhead_s"],
             "%.3g" % f["samples_per_s_asymptotic"] if f["samples_per_s_asymptotic"] else "n/a",
             "%.4f" % f["r2"], "%.3f" % f["loglog_slope"]] for name, f in sc["fits"].items()]
    depths = []
    for d in sorted({r["max_depth"] for r in sc["depth"]}):
        b = next(r for r in sc["depth"] if r["method"] == "bdpt-power" and r["max_depth"] == d)
        p = next(r for r in sc["depth"] if r["method"] == "path" and r["max_depth"] == d)
        depths.append(["%d" % d, "%.4f" % b["time"], "%.0f" % b["kernels_per_pass"], "%d" % b["connections"],
                       "%.3g" % (b["rays_per_sample"] or 0), "%.4f" % p["time"]])
    rep.add("scaling",
            fits=table(["method", "overhead a / s", "samples/s (1/b)", "R^2", "log-log slope"], fits),
            depths=table(["max_depth", "bdpt time / s", "bdpt kernels/pass", "connection strategies",
                          "bdpt rays/sample", "path time / s"], depths))
    if sc.get("depth_fit_quadratic"):
        rep.add("scaling_quadratic", *sc["depth_fit_quadratic"], *sc["depth_fit_kernels_quadratic"])


def rss_table(rss: list) -> str:
    rows = []
    for r in rss:
        size = "%dx%d" % (r["width"], r["height"])
        if "error" in r:
            rows.append([r["method"], size, "failed: %s" % r["error"], "", "", "", ""])
        else:
            rows.append([r["method"], size, "%.0f" % r["rss_peak_mib"], "%.0f" % r["baseline_rss_mib"],
                         "%.0f" % r["jit_peak_mib"], "%d" % r["passes"], "%.2f" % r["first_wall"]])
    return table(["method", "size", "peak RSS / MiB", "RSS before render / MiB", "Dr.Jit peak / MiB",
                  "passes", "time / s"], rows)


# -- observations -----------------------------------------------------------------------------------
def recs_of(scene_result, method):
    return sorted((r for r in scene_result["records"] if r["method"] == method), key=lambda r: r["spp"])


def observations(res: dict) -> list:
    """Automatic flags: BDPT losing where it should win, non-finite pixels, ..."""
    obs = []
    for s in res.get("scenes", []):
        if not s:
            continue
        eq = s.get("equal_time")
        if eq and "bdpt-power" in eq["methods"] and "path" in eq["methods"] and s["scene"] in SHOULD_WIN:
            obs.append(should_win(s, eq["methods"]["bdpt-power"]["err_ratio"]))
        recs = s["records"]
        bad = [r for r in recs if r["nonfinite"]]
        if bad:
            obs.append("%s: non-finite pixels from %s" % (s["scene"], sorted({r["method"] for r in bad})))
        for mm in sorted({r["method"] for r in recs}):
            last = recs_of(s, mm)[-1]
            if s.get("ref_mean") and abs(last["mean"] / s["ref_mean"] - 1) > 0.2:
                obs.append("%s: %s's image has %.2fx the reference's mean at %d spp (an effect "
                           "it cannot render?)"
                           % (s["scene"], mm, last["mean"] / s["ref_mean"], last["spp"]))
        bal = [r for r in recs if r["method"] == "bdpt-balance"]
        pw = [r for r in recs if r["method"] == "bdpt-power"]
        if bal and pw and bal[-1]["relmse"] < 0.8 * pw[-1]["relmse"]:
            obs.append("%s: balance heuristic beats power (%.3g vs %.3g relMSE at %d spp)"
                       % (s["scene"], bal[-1]["relmse"], pw[-1]["relmse"], pw[-1]["spp"]))
    return obs


def should_win(s: dict, r: float) -> str:
    """The observation on a scene where BDPT should beat path at equal time (error ratio r)."""
    if not r > 1:
        return "%s: BDPT (power) reaches %.2fx path's error at equal time (expected < 1)." % (s["scene"], r)
    why = ""
    pe = [q["relmse"] for q in recs_of(s, "path")][-3:]
    if len(pe) == 3 and pe[-1] > 0.8 * pe[0]:
        why = (" Path's error has stopped falling (%.3g -> %.3g over its last 3 levels): "
               "its image misses an effect (bias), which relMSE charges less than "
               "BDPT's noise at this small budget; BDPT should cross below it with "
               "more time." % (pe[0], pe[-1]))
    return ("%s: BDPT (power) has %.2fx path's error at equal time, although it should "
            "win here.%s" % (s["scene"], r, why))
