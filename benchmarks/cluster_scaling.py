"""Cluster scaling on this machine: a plain local render against Ray clusters of
1 and 2 local workers (``bdpt_drjit.cluster``), the same plan and seed.

    python -m benchmarks.cluster_scaling                       # Cornell box 128x128, 64 spp
    python -m benchmarks.cluster_scaling --res 64 --spp 16     # a quick look
    python -m benchmarks.cluster_scaling --publish             # also its table in RESULTS.md

For each mode: the start-up (Ray, the workers loading the scene), then the passes timed
after one warm-up pass per worker (kernels compiled or loaded from Dr.Jit's cache),
the fastest of --repeats renders (the same workers; a plain render after each, the
fastest of all kept, as other load on the machine comes and goes; "vs the plain render
after it" is the median of those pairs' time ratios): samples/s over the wall time of
all passes, the workers' time per pass, and the time
per pass that is not rendering -- the round trip (sending the pass, the worker reading
its film, Ray moving the raw sums, the driver getting them) less the worker's time --
and the driver's float64 merge.  ``local:N`` gives each worker cpu_count/N Dr.Jit
threads; the plain render uses all cores.  The images of all modes must agree (rtol
1e-5): the cluster renders the local render's estimator.  Results in
benchmarks/results/cluster_scaling.json.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from . import common as C

import drjit as dr  # noqa: E402  (after common, which selects the variant)
import mitsuba as mi  # noqa: E402

from bdpt_drjit import Renderer, support  # noqa: E402
from bdpt_drjit.cluster import Cluster, ClusterRun  # noqa: E402

dr.set_flag(dr.JitFlag.KernelHistory, False)       # common turns it on; not needed here
SCENE = C.ROOT / "scenes" / "cornell-box.xml"


class Plain:
    """The plain local render, timed again between the cluster's renders: the machine's
    other load changes over a run, and each mode keeps its fastest render."""

    def __init__(self, args, params):
        self.scene = support.load_file(SCENE, **params)
        self.args = args
        self.make().render_pass(0)                  # warm-up: kernels compiled
        self.best = None

    def make(self):
        a = self.args
        return Renderer(self.scene, spp=a.spp, seed=a.seed, samples_per_pass=a.per_pass,
                        max_depth=a.max_depth)

    def render(self) -> float:
        r = self.make()
        start = time.perf_counter()
        while not r.done:
            r.run_pass()
        image = r.result().image
        wall = time.perf_counter() - start
        if self.best is None or wall < self.best[0]:
            self.best = wall, r, image
        return wall

    def row(self) -> dict:
        wall, r, image = self.best
        return {"mode": "plain", "workers": 1, "threads": dr.thread_count(), "startup": 0.0,
                "wall": wall, "passes": len(r.plan), "worker_time": r.time, "overhead": 0.0,
                "idle": 0.0, "merge": 0.0, "raw_bytes": 0, "image": image, "pixels": r.pixels,
                "paired": 1.0}


def on_cluster(args, params, workers: int, plain: Plain) -> dict:
    scene = support.load_file(SCENE, **params)
    r = Renderer(scene, spp=args.spp, seed=args.seed, samples_per_pass=args.per_pass,
                 max_depth=args.max_depth)
    address = "local:%d" % workers
    with Cluster(address, SCENE, mi.variant()) as cluster:
        run = cluster.start(r, params)
        # One warm-up pass per worker (its result is dropped, its film cleared).
        warm = cluster.ray.get([s.handle.render.remote(0) for s in cluster.slots])
        raw_bytes = sum(v.nbytes for k, v in warm[0]["raw"].items() if k != "light_paths")
        best, ratios = None, []
        for repeat in range(args.repeats):
            run = run if repeat == 0 else ClusterRun(cluster, r)     # the same workers
            start = time.perf_counter()
            while not run.done:
                run.run_pass()
            wall = time.perf_counter() - start
            res = run.result()
            if best is None or wall < best[0]:
                best = wall, run, res
            ratios.append(plain.render() / wall)     # the workers idle meanwhile
        wall, run, res = best
        passes = len(r.plan)
        return {"mode": address, "workers": workers,
                "threads": max(1, (os.cpu_count() or 1) // workers),
                "startup": cluster.startup, "wall": wall, "passes": passes,
                "worker_time": run.sums.time, "overhead": float(np.mean(run.overheads)),
                "idle": (workers * wall - run.sums.time) / passes,
                "merge": run.merge_time / passes, "raw_bytes": raw_bytes,
                "image": res.image, "pixels": r.pixels, "rerun": run.passes_rerun,
                "paired": float(np.median(ratios))}


def table(rows, spp) -> str:
    base = rows[0]["pixels"] * spp / rows[0]["wall"]
    out = ["| mode | workers x threads | start-up / s | wall / s | samples/s | vs plain | "
           "vs the plain render after it | worker time / pass / ms | round trip - worker "
           "time / pass / ms | not rendering / pass / ms | driver merge / pass / ms | "
           "raw sums / pass |",
           "|" + "---|" * 12]
    for m in rows:
        rate = m["pixels"] * spp / m["wall"]
        out.append("| %s | %d x %d | %.1f | %.2f | %.3g | %.2fx | %.2fx | %.0f | %.1f | %.1f | %.2f | %s |" % (
            m["mode"], m["workers"], m["threads"], m["startup"], m["wall"], rate, rate / base,
            m["paired"],
            1e3 * m["worker_time"] / m["passes"], 1e3 * m["overhead"], 1e3 * m["idle"],
            1e3 * m["merge"], "%.0f KiB" % (m["raw_bytes"] / 1024) if m["raw_bytes"] else "-"))
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", default="128", help="film size, N or WxH (default 128)")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--per-pass", type=int, default=2, help="samples per pixel per pass")
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", default="1,2", help="local cluster sizes (default 1,2)")
    ap.add_argument("--repeats", type=int, default=3,
                    help="timed renders per mode, the fastest kept (default 3)")
    ap.add_argument("--publish", action="store_true",
                    help="replace the measured block of RESULTS.md's 'Cluster (Ray)' section")
    args = ap.parse_args(argv)
    if args.publish:
        C.check_block(C.BENCH / "RESULTS.md", "cluster_scaling")
    w, h = C.parse_res(args.res)
    params = {"resx": w, "resy": h}
    machine = C.machine_info()
    started = time.perf_counter()
    plain = Plain(args, params)
    plain.render()
    rows = []
    for n in (int(x) for x in args.workers.split(",")):
        rows.append(on_cluster(args, params, n, plain))
        C.log("local:%d: %.2f s (start-up %.1f s); plain so far %.2f s"
              % (n, rows[-1]["wall"], rows[-1]["startup"], plain.best[0]))
    rows.insert(0, plain.row())
    for m in rows[1:]:
        np.testing.assert_allclose(m["image"], rows[0]["image"], rtol=1e-5, atol=1e-6)
    command = "python -m benchmarks.cluster_scaling " + " ".join(argv if argv is not None
                                                                   else sys.argv[1:])
    block = "\n".join([
        "Reproduce: `%s` (took %.0f s). Cornell box %dx%d, max_depth %d, %d spp in %d passes of "
        "%d spp, seed %d, fastest of %d renders per cluster (and of all plain renders, one after each). Machine: %s, %d cores, load average %.2f at start; Ray %s; %s. "
        "The three images agree to rtol 1e-5 (the same estimator)."
        % (command.strip(), time.perf_counter() - started, w, h, args.max_depth, args.spp,
           rows[0]["passes"], args.per_pass, args.seed, args.repeats, machine["cpu"], machine["cpu_count"],
           machine["load_avg_1min"], __import__("ray").__version__, machine["date"]),
        "",
        table(rows, args.spp)])
    print(block)
    C.write_json(C.RESULTS / "cluster_scaling.json",
                 {"machine": machine, "command": command,
                  "rows": [{k: v for k, v in m.items() if k != "image"} for m in rows]})
    if args.publish:
        C.replace_block(C.BENCH / "RESULTS.md", "cluster_scaling", block)
    return 0


if __name__ == "__main__":
    sys.exit(main())
