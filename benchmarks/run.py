"""The benchmark suite: error against time on the scene suite, weighting schemes,
equal-ray comparison, throughput and scaling, and strategy pyramids.

    python -m benchmarks.run --smoke    # CI smoke test: 2 scenes, 16x16, seconds
    python -m benchmarks.run --quick    # a few minutes on 2 cores: 32x32, 3 spp levels
    python -m benchmarks.run            # the full run (long: run it on an idle machine)
    python -m benchmarks.run --weighting --res 128 --levels 4,16,64 --ref-spp 2048 --seeds 2
                                        # the MIS weighting schemes (3-9 min on 2 cores)

Options: --out DIR (default benchmarks/results), --scenes a,b, --methods a,b, --res N,
--levels 1,2,4, --ref-spp N, --seeds N, --skip error,throughput,scaling,rss,cold,pyramid,
--weighting (the four MIS heuristics on Veach's budget, error against time only),
--section NAME (the block of RESULTS.md to rewrite).

Outputs (under --out): refs/ (cached references, .npy + .json), charts/*.png,
results.json, RESULTS.md.  Without --out (and not --smoke) the charts are also copied
to benchmarks/charts/ and the report into its block of benchmarks/RESULTS.md (the
lines between ``<!-- NAME: begin -->`` and ``<!-- NAME: end -->``, NAME = --section:
"suite" by default, "weighting" with --weighting), to be committed.

This file is the command line; what is rendered and measured is in suite.py (its
docstring says how), the tables and text of RESULTS.md in report.py (prose in
report_template.md), the charts in charts.py.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from . import charts
from . import common as C
from . import report, suite
from .scenes import SCENES


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help="a few minutes: 32x32, 3 spp levels")
    g.add_argument("--smoke", action="store_true", help="CI smoke test: 2 scenes, 16x16, 2 levels")
    ap.add_argument("--out", type=Path, help="output folder (default benchmarks/results)")
    ap.add_argument("--scenes", help="comma-separated scene names (default: the mode's)")
    ap.add_argument("--methods", help="comma-separated methods (default: %s)" % ",".join(suite.ALL_METHODS))
    ap.add_argument("--res", type=int, help="image width for the error runs")
    ap.add_argument("--levels", help="comma-separated spp levels of the BDPT runs")
    ap.add_argument("--ref-spp", type=int, help="reference spp (BDPT; Mitsuba uses 4x)")
    ap.add_argument("--seeds", type=int, help="renders per level (errors averaged)")
    ap.add_argument("--skip", default="", help="comma-separated sections to skip: " + ",".join(suite.SECTIONS))
    ap.add_argument("--weighting", action="store_true",
                    help="the MIS weighting schemes (%s; Veach's budget, light_paths=1 "
                         "connections=all) on the suite's scenes: error against time, "
                         "nothing else" % ", ".join(C.WEIGHTING))
    ap.add_argument("--section", help="the block of benchmarks/RESULTS.md that the report "
                                      "replaces (default: suite; weighting with --weighting)")
    ap.add_argument("--no-publish", action="store_true",
                    help="do not copy charts to benchmarks/charts nor the report into benchmarks/RESULTS.md")
    ap.add_argument("--report-only", action="store_true",
                    help="redo the tables, charts and RESULTS.md from OUT/results.json without rendering")
    return ap


def names(text: str) -> list:
    return [s.strip() for s in text.split(",") if s.strip()]


def config(ap: argparse.ArgumentParser, args, mode: str) -> suite.Config:
    """The mode's configuration with the options' changes; unknown names are refused."""
    cfg = replace(suite.MODES[mode])
    if args.scenes:
        cfg.scenes = names(args.scenes)
        unknown = [s for s in cfg.scenes if s not in SCENES]
        if unknown:
            ap.error("unknown scenes %s (known: %s)" % (unknown, ", ".join(SCENES)))
        cfg.pyramid_scenes = [s for s in cfg.pyramid_scenes if s in cfg.scenes]
    if args.methods:
        cfg.methods = names(args.methods)
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
    if args.weighting:
        cfg.weighting = True
        if not args.methods:
            cfg.methods = list(C.WEIGHTING)
    return cfg


def sections_skipped(ap: argparse.ArgumentParser, args) -> set:
    """The sections not run: --skip's, and with --weighting all but the error runs."""
    skip = set(names(args.skip))
    if skip - set(suite.SECTIONS):
        ap.error("unknown sections to skip: %s" % sorted(skip - set(suite.SECTIONS)))
    if args.weighting:
        skip |= set(suite.SECTIONS) - {"error"}
    return skip


def main(argv=None) -> int:
    ap = parser()
    args = ap.parse_args(argv)
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    cfg = config(ap, args, mode)
    skip = sections_skipped(ap, args)
    out = args.out or C.RESULTS
    publish = None
    if args.out is None and not args.smoke and not args.no_publish:
        publish = args.section or ("weighting" if args.weighting else "suite")
        C.check_block(C.BENCH / "RESULTS.md", publish)      # before hours of rendering
    (out / "charts").mkdir(parents=True, exist_ok=True)
    progress = suite.Progress()
    C.matplotlib()          # fails here, before any rendering, where matplotlib is missing
    cmd = "python -m benchmarks.run" + ("" if argv is None and len(sys.argv) <= 1 else " " + " ".join(
        sys.argv[1:] if argv is None else argv))
    if args.report_only:
        return report_only(out, publish, progress)
    progress("benchmarks.run, %s mode -> %s" % (mode, out))
    res = suite.run(cfg, mode, skip, out, cmd, progress)
    res["observations"] = report.observations(res)
    C.write_json(out / "results.json", res)
    finish(res, cfg, out, publish, progress)
    return 0


def report_only(out: Path, publish: str | None, progress) -> int:
    res = json.loads((out / "results.json").read_text())
    cfg = suite.Config(**res["config"])
    methods = [C.METHODS[m] for m in res["methods"]]
    for r in res["scenes"]:
        if not r:
            continue
        suite.compare(r)
        charts.scene_charts(r, out / "charts", methods)
    res["observations"] = report.observations(res)
    C.write_json(out / "results.json", res)
    finish(res, cfg, out, publish, progress)
    return 0


def finish(res, cfg, out: Path, publish: str | None, progress) -> None:
    """RESULTS.md under out; with publish (a block's name), also the charts and the
    report in that block of benchmarks/RESULTS.md, to be committed."""
    md = report.results_md(res, cfg, "charts")
    (out / "RESULTS.md").write_text(md)
    if publish:
        # Another block than the suite's or the weighting's keeps its charts in a
        # folder of its own: they bear the same scenes' names.
        folder = "" if publish in ("suite", "weighting") else publish
        block = md if not folder else report.results_md(res, cfg, "charts/" + folder)
        C.replace_block(C.BENCH / "RESULTS.md", publish, report.as_block(block))
        (C.CHARTS / folder).mkdir(parents=True, exist_ok=True)
        for png in (out / "charts").glob("*.png"):
            charts.small_png(png, C.CHARTS / folder / png.name)
        progress("published charts to %s and the report to the block '%s' of %s"
                 % (C.CHARTS, publish, C.BENCH / "RESULTS.md"))
    for o in res["observations"]:
        progress("observation: " + o)
    progress("done in %.0f s; results in %s" % (res["elapsed"], out))


if __name__ == "__main__":
    sys.exit(main())
