"""Throughput: BDPT against Mitsuba's ``path`` on the Cornell box, in one process.

    python -m benchmarks.throughput                    # 256x256, max_depth 8, 64 spp, 3 repeats
    python -m benchmarks.throughput --spp 4 --res 64   # a quick check
    python -m benchmarks.throughput --no-cold          # skip the cold-compile subprocess
    python -m benchmarks.throughput --json out.json

For each method: a first render (compiles the kernels, or loads them from Dr.Jit's
disk cache ~/.drjit), then ``--repeats`` timed renders with different seeds.  Reported:
samples per second (median; wall time minus any compile time, image evaluated inside
the timed region), their ratio, rays per sample (BDPT counts its rays; for ``path``
they are estimated by a probe, see common.estimate_mitsuba_rays), kernel launches per
pass (Dr.Jit kernel history), peak memory (process RSS via getrusage, and Dr.Jit's
allocator watermark), and compile vs run time.

Compile time: the first render in this process may load kernels from Dr.Jit's disk
cache; the cold compile is measured in a subprocess whose HOME (and so kernel cache)
is an empty temporary folder.

``--probe METHOD`` renders once with one method and prints one JSON line; suite.py uses
it in subprocesses to get each resolution's own peak RSS, and with an empty kernel
cache (HOME pointed at a temporary folder) to time a cold compile.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import common as C

DEFAULT_SCENE = C.ROOT / "scenes" / "cornell-box.xml"


def current_rss_mib() -> float:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except OSError:
        return float("nan")


def load_scene(path, width, height, max_depth):
    from bdpt_drjit import support
    return support.load_file(path, resx=width, resy=height, max_depth=max_depth)


def measure(method: C.Method, scene, spp: int, repeats: int, max_depth: int,
            seed: int = 1, ray_probe: bool = True) -> dict:
    """First render (compile) and ``repeats`` warm renders of one method."""
    C.clear_jit_watermark()
    first = C.render(method, scene, spp, seed, max_depth)
    runs = [C.render(method, scene, spp, seed + 1 + i, max_depth) for i in range(max(1, repeats))]
    run_time = C.median([r.timing.run for r in runs])
    wall = C.median([r.timing.wall for r in runs])
    passes = runs[0].passes
    pixels = runs[0].pixels
    if method.engine == "bdpt":
        rps, rays_kind = C.median([r.rays_per_sample for r in runs]), "measured"
    elif ray_probe and method.name in ("path", "ptracer"):
        rps, rays_kind = C.estimate_mitsuba_rays(scene, method.name, max_depth,
                                                 spp=max(1, min(4, spp))), "estimated"
    else:
        rps, rays_kind = None, "n/a"
    sps = spp * pixels / run_time
    return {
        "method": method.name, "spp": spp, "pixels": pixels, "max_depth": max_depth,
        "repeats": len(runs), "passes": passes,
        "samples_per_second": sps,
        "time_median": run_time, "wall_median": wall,
        "times": [r.timing.run for r in runs],
        "rays_per_sample": rps, "rays_kind": rays_kind,
        "rays_per_second": None if rps is None else rps * sps,
        "kernels_per_pass": C.median([r.timing.kernels for r in runs]) / passes,
        "other_launches_per_pass": C.median([r.timing.other_launches for r in runs]) / passes,
        "codegen_per_render": C.median([r.timing.codegen for r in runs]),
        "kernel_execution_per_render": C.median([r.timing.execution for r in runs]),
        "first_wall": first.timing.wall, "first_compile": first.timing.compile,
        "first_kernels_compiled": first.timing.misses, "first_kernels_from_disk": first.timing.disk_loads,
        "jit_peak_mib": C.jit_watermark_mib(), "rss_peak_mib": C.peak_rss_mib(),
    }


def cold_compile(method: str, scene: Path, width: int, height: int, spp: int, max_depth: int,
                 timeout: float = 600) -> dict:
    """Time a compile with an empty Dr.Jit kernel cache: a subprocess whose HOME is a
    fresh temporary folder (Dr.Jit keeps its disk cache in $HOME/.drjit)."""
    with tempfile.TemporaryDirectory(prefix="bdpt-cold-") as home:
        env = dict(os.environ, HOME=home)
        return probe_subprocess(method, scene, width, height, spp, max_depth, env=env,
                                extra=["--twice"], timeout=timeout)


def probe_subprocess(method: str, scene: Path, width: int, height: int, spp: int, max_depth: int,
                     env=None, extra=(), timeout: float = 600) -> dict:
    cmd = [sys.executable, "-m", "benchmarks.throughput", "--probe", method, "--scene", str(scene),
           "--res", "%dx%d" % (width, height), "--spp", str(spp), "--max-depth", str(max_depth), *extra]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=str(C.ROOT), env=env, capture_output=True, text=True, timeout=timeout)
    if p.returncode != 0:
        return {"error": (p.stderr or p.stdout).strip().splitlines()[-1:] or ["exit %d" % p.returncode],
                "returncode": p.returncode, "process_wall": time.perf_counter() - t0}
    line = [ln for ln in p.stdout.splitlines() if ln.startswith("{")][-1]
    out = json.loads(line)
    out["process_wall"] = time.perf_counter() - t0
    return out


def probe_main(args) -> None:
    """One render in this (fresh) process; prints a JSON line."""
    method = C.METHODS[args.probe]
    w, h = C.parse_res(args.res)
    scene = load_scene(args.scene, w, h, args.max_depth)
    base_rss = current_rss_mib()
    C.clear_jit_watermark()
    first = C.render(method, scene, args.spp, 1, args.max_depth)
    out = {"method": method.name, "width": w, "height": h, "spp": args.spp,
           "max_depth": args.max_depth, "baseline_rss_mib": base_rss,
           "first_wall": first.timing.wall, "first_compile": first.timing.compile,
           "first_kernels_compiled": first.timing.misses,
           "first_kernels_from_disk": first.timing.disk_loads,
           "kernels": first.timing.kernels, "passes": first.passes}
    if args.twice:
        second = C.render(method, scene, args.spp, 2, args.max_depth)
        out.update(second_wall=second.timing.wall, second_compile=second.timing.compile)
    out.update(rss_peak_mib=C.peak_rss_mib(), jit_peak_mib=C.jit_watermark_mib())
    print(json.dumps(out), flush=True)


def fmt(x, spec="%.3g"):
    return "n/a" if x is None else spec % x


def report(results: dict, cold: dict | None = None) -> str:
    b, p = results["bdpt-power"], results["path"]
    lines = []
    w = lines.append
    w("scene %s, %dx%d, max_depth %d, %d spp, median of %d repeats (compile excluded)"
      % (results["scene"], results["width"], results["height"], b["max_depth"], b["spp"], b["repeats"]))
    w("%-28s %14s %14s" % ("", "bdpt (power)", "mitsuba path"))
    rows = [
        ("samples / s", "samples_per_second", "%.4g"),
        ("render time / s", "time_median", "%.4g"),
        ("rays / sample", "rays_per_sample", "%.3g"),
        ("rays / s", "rays_per_second", "%.4g"),
        ("kernel launches / pass", "kernels_per_pass", "%.0f"),
        ("other launches / pass", "other_launches_per_pass", "%.0f"),
        ("passes", "passes", "%d"),
        ("IR codegen / render, s", "codegen_per_render", "%.3f"),
        ("first render wall / s", "first_wall", "%.3f"),
        ("  of which compile / s", "first_compile", "%.3f"),
        ("  kernels compiled", "first_kernels_compiled", "%d"),
        ("  kernels from disk cache", "first_kernels_from_disk", "%d"),
        ("Dr.Jit peak memory / MiB", "jit_peak_mib", "%.1f"),
    ]
    for label, key, spec in rows:
        w("%-28s %14s %14s" % (label, fmt(b.get(key), spec), fmt(p.get(key), spec)))
    w("%-28s %14s %14s" % ("rays counted", b["rays_kind"], p["rays_kind"]))
    w("process peak RSS: %.0f MiB" % results["rss_peak_mib"])
    w("ratio path / bdpt samples per second: %.2f  (bdpt is %.2fx slower per sample)"
      % (results["ratio_samples"], results["ratio_samples"]))
    if results.get("ratio_rays"):
        w("ratio bdpt / path rays per second: %.2f (path rays estimated)" % results["ratio_rays"])
    if cold:
        for m, c in cold.items():
            if "error" in c:
                w("cold compile %s: failed: %s" % (m, c["error"]))
            else:
                w("cold compile %s (empty kernel cache, %dx%d %d spp): first render %.2f s "
                  "(%d kernels compiled, %.2f s LLVM), second render %.3f s"
                  % (m, c["width"], c["height"], c["spp"], c["first_wall"], c["first_kernels_compiled"],
                     c["first_compile"], c.get("second_wall", float("nan"))))
    return "\n".join(lines)


def run(width=256, height=256, spp=64, repeats=3, max_depth=8, scene=DEFAULT_SCENE,
        cold=False, cold_res=(64, 64), cold_spp=4) -> dict:
    sc = load_scene(scene, width, height, max_depth)
    results = {"scene": Path(scene).name, "width": width, "height": height}
    for m in (C.BDPT_POWER, C.PATH):
        C.log("  throughput: %s %dx%d %d spp x %d repeats ..." % (m.name, width, height, spp, repeats))
        results[m.name] = measure(m, sc, spp, repeats, max_depth)
    b, p = results["bdpt-power"], results["path"]
    results["ratio_samples"] = p["samples_per_second"] / b["samples_per_second"]
    if b["rays_per_second"] and p["rays_per_second"]:
        results["ratio_rays"] = b["rays_per_second"] / p["rays_per_second"]
    results["rss_peak_mib"] = C.peak_rss_mib()
    if cold:
        results["cold"] = {}
        for name in ("bdpt-power", "path"):
            C.log("  cold compile: %s ..." % name)
            results["cold"][name] = cold_compile(name, Path(scene), cold_res[0], cold_res[1], cold_spp, max_depth)
    return results


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--res", default="256", help="N or WxH (default 256)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--scene", default=str(DEFAULT_SCENE))
    ap.add_argument("--json", type=Path, help="write the results as JSON")
    ap.add_argument("--no-cold", dest="cold", action="store_false",
                    help="skip the cold-compile measurement (a subprocess with an empty kernel cache)")
    ap.add_argument("--probe", choices=sorted(C.METHODS), help=argparse.SUPPRESS)
    ap.add_argument("--twice", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.probe:
        return probe_main(args)
    w, h = C.parse_res(args.res)
    results = run(w, h, args.spp, args.repeats, args.max_depth, args.scene, cold=args.cold)
    results["machine"] = C.machine_info()
    results["command"] = "python -m benchmarks.throughput " + " ".join(sys.argv[1:] if argv is None else argv)
    print(report(results, results.get("cold")))
    if args.json:
        C.write_json(args.json, results)
        print("wrote", args.json)


if __name__ == "__main__":
    main()
