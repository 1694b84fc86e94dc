"""How much of Veach's BDPT's connection loop a SIMD packet (CPU) or warp (GPU) runs
for nothing.  The camera walk connects z_j to every stored vertex of its lane's light
subpath in a loop (connect._subpath_vertices); a packet of W lanes runs that loop as
often as its longest list, and runs the camera walk's own loop as long as its longest
subpath.  This counts both, per lane and depth, on one pass of the CPU backend, and
reports the iterations packets of W = 8, 16 (the CPU's AVX2 and AVX-512 packets) and
32 (a CUDA warp) run over the useful ones.

``--bound N`` times what removing that divergence could give at most: N renders each,
interleaved, of Veach's BDPT as it is and of one whose 16 lanes of a packet (32 of a
warp under CUDA) all connect to the same light subpath (the first lane's: no divergence from list lengths, and one
record read per packet).  That image is biased; only its time is read.

    python benchmarks/experiments/connection_divergence.py cornell-diffuse veach-bidir
    python benchmarks/experiments/connection_divergence.py scenes/deep-box.xml --max-depth 65
    python benchmarks/experiments/connection_divergence.py cornell-diffuse --bound 4 --spp 16

Scene names are the suite's (benchmarks/scenes.py; external ones need BDPT_SHARED), or
an XML file.  The counts come from a copy of the connection loop's condition, traced
beside it (the loop itself is untouched); the pass is the engine's, 1 spp, on
``BDPT_VARIANT`` (default ``llvm_ad_rgb``).
"""
import argparse
import os
import sys
from pathlib import Path

import numpy as np

DEPTHS = 128                    # camera depths counted per lane (deeper ones pooled)


def _counting(connect, counts, alive):
    """``connect._subpath_vertices`` that also scatters each lane's trip count at each
    camera depth to ``counts`` and marks the depth in ``alive``."""
    import drjit as dr
    import mitsuba as mi
    from bdpt_drjit.vertices import NONE
    loop = connect._subpath_vertices

    def counted(ctx, store, state, v, connectible):
        t = state.depth + 1
        item = dr.gather(mi.UInt32, store.first, ctx.light_subpath(ctx.lane), connectible)
        k_max = ctx.strategies.max_depth

        def more(item, n):                         # the loop's own condition
            go = item != NONE
            if k_max >= 0:
                go &= store.vertices.s(item, go) + t - 1 <= k_max
            return go

        _, n = dr.while_loop((dr.select(connectible, item, NONE), dr.zeros(mi.UInt32, dr.width(item))),
                             more, lambda item, n: (dr.gather(mi.UInt32, store.vertices.items.next, item), n + 1))
        slot = ctx.lane * DEPTHS + dr.minimum(state.depth, DEPTHS - 1)
        dr.scatter(counts, n, slot, connectible)
        dr.scatter(alive, mi.UInt32(1), slot)
        return loop(ctx, store, state, v, connectible)
    return counted


def measure(scene, lanes: int, max_depth: int) -> dict:
    import drjit as dr
    import mitsuba as mi
    from bdpt_drjit import connect
    from bdpt_drjit.render import Renderer
    counts, alive = dr.zeros(mi.UInt32, lanes * DEPTHS), dr.zeros(mi.UInt32, lanes * DEPTHS)
    loop = connect._subpath_vertices
    connect._subpath_vertices = _counting(connect, counts, alive)
    try:
        renderer = Renderer(scene, spp=1, seed=3, max_depth=max_depth, light_paths=1,
                            connections="all")
        renderer.run_pass()
    finally:
        connect._subpath_vertices = loop
    trips = counts.numpy().reshape(lanes, DEPTHS).astype(np.int64)
    depths = alive.numpy().reshape(lanes, DEPTHS).astype(np.int64)
    out = {"connections": trips.sum() / lanes, "depths": depths.sum() / lanes}
    for w in (8, 16, 32):
        n = lanes // w * w
        run = trips[:n].reshape(-1, w, DEPTHS).max(axis=1).sum() * w
        walk = depths[:n].reshape(-1, w, DEPTHS).max(axis=1).sum() * w
        out[w] = (run / max(trips[:n].sum(), 1), walk / max(depths[:n].sum(), 1))
    return out


def bound(scene, max_depth: int, spp: int, repeats: int) -> tuple:
    """Median seconds of Veach's BDPT as it is and with a packet's lanes sharing one
    light subpath (biased: a timing bound), interleaved."""
    import statistics
    import time
    import importlib
    import drjit as dr
    import mitsuba as mi
    render = importlib.import_module("bdpt_drjit.render")   # (the package exports a function of that name)

    group = 32 if mi.variant().startswith("cuda") else 16

    def shared(ctx, lane):
        return (lane & ~mi.UInt32(group - 1)) % dr.opaque(mi.UInt32, max(ctx.light_count, 1))

    def seconds(seed: int) -> float:
        start = time.perf_counter()
        r = render.Renderer(scene, spp=spp, seed=seed, max_depth=max_depth, light_paths=1,
                            connections="all")
        while not r.done:
            r.run_pass()
        dr.eval(r.tensor())
        dr.sync_thread()
        return time.perf_counter() - start

    own = render.PassContext.light_subpath
    times = ([], [])
    for rep in range(repeats + 1):                  # the first round warms up
        for which in ((0, 1) if rep % 2 else (1, 0)):
            render.PassContext.light_subpath = own if which == 0 else shared
            try:
                t = seconds(100 + rep)
            finally:
                render.PassContext.light_subpath = own
            if rep:
                times[which].append(t)
    return statistics.median(times[0]), statistics.median(times[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--res", type=int, default=256)
    parser.add_argument("--max-depth", type=int, default=None)
    parser.add_argument("--bound", type=int, default=0, metavar="N",
                        help="time N renders each, as it is and without divergence (biased)")
    parser.add_argument("--spp", type=int, default=16, help="spp of the --bound renders")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))      # this checkout
    import mitsuba as mi
    mi.set_variant(os.environ.get("BDPT_VARIANT", "llvm_ad_rgb"))
    from benchmarks.scenes import SCENES
    from bdpt_drjit import support
    if not args.bound:
        print("| scene | max_depth | connections per sample | camera depths per sample "
              "| connection iterations run / useful, W = 8, 16, 32 | camera depths run / useful |")
        print("|---|---|---|---|---|---|")
    for name in args.scenes:
        if name in SCENES:
            spec = SCENES[name]
            w, h, _ = spec.resolution(args.res)
            scene, depth = spec.load(w, h), spec.max_depth
        else:
            scene = support.load_file(name, resx=args.res, resy=args.res)
            w = h = args.res
            depth = -1
        depth = depth if args.max_depth is None else args.max_depth
        if args.bound:
            own, shared = bound(scene, depth, args.spp, args.bound)
            print("%s: %.3f s as it is, %.3f s with a light subpath per packet (%.3fx)"
                  % (name, own, shared, shared / own))
            continue
        r = measure(scene, w * h, depth)
        print("| %s | %d | %.2f | %.2f | %s | %s |" % (
            name, depth, r["connections"], r["depths"],
            ", ".join("%.2f" % r[w][0] for w in (8, 16, 32)),
            ", ".join("%.2f" % r[w][1] for w in (8, 16, 32))))


if __name__ == "__main__":
    main()
