"""Before / after of ``vcm`` against the default bdpt on two checkouts, interleaved: one
worker process per tree (each imports its own bdpt_drjit), and for every seed the four
renders (tree A bdpt, tree A vcm, tree B bdpt, tree B vcm) in turn, the order rotating;
medians of wall time, CPU time and relative MSE (the suite's metric, against a cached
reference), and vcm / bdpt per tree.  Pin each tree's unit costs with its own
calibration file (``bdpt calibrate`` with BDPT_CALIBRATION set, in that tree).

    python benchmarks/experiments/vcm_trees.py cornell-diffuse 32 12 REFS \
        OLD_TREE:old_units.json NEW_TREE:new_units.json

REFS: a folder with ``SCENE_*.npy`` per scene (vcm_ab.py's); the SmallVCM boxes (bs_c,
lg_c, bs_p) read benchmarks/results/smallvcm-refs of this checkout instead.
"""
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[2]


def worker(tree: str, refs: str) -> None:
    """Read 'SCENE SPP SEED MERGING' lines, render with ``tree``'s bdpt_drjit, print JSON."""
    sys.path.insert(0, tree)
    import glob
    import numpy as np
    import bdpt_drjit
    assert bdpt_drjit.__file__.startswith(tree), bdpt_drjit.__file__
    sys.path.insert(1, str(HERE))
    os.environ.setdefault("BDPT_SHARED", str(HERE.parent / "shared"))   # (a tree's own
    from benchmarks import common as C                                  # benchmarks first)
    from benchmarks.scenes import SCENES
    cache = {}

    def scene(name):
        if name not in cache:
            if name in ("bs_c", "lg_c", "bs_p"):
                from benchmarks import smallvcm as S
                ref = S.read_hdr(HERE / "benchmarks/results/smallvcm-refs" / ("%s_vcm_400cpu.hdr" % name))
                cache[name] = (S.build_scene(name), S.MAX_DEPTH, ref)
            else:
                spec = SCENES[name]
                w, h, _ = spec.resolution(128)
                ref = np.load(glob.glob("%s/%s_*.npy" % (refs, name))[0])[..., :3]
                cache[name] = (spec.load(w, h), spec.max_depth, ref)
        return cache[name]

    for line in sys.stdin:
        name, spp, seed, merging = line.split()
        sc, depth, ref = scene(name)
        c0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        r = bdpt_drjit.render(sc, spp=int(spp), seed=int(seed), max_depth=depth,
                              merging=merging == "1")
        img = np.asarray(r.image)[..., :3].astype(np.float64)
        wall, c1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
        cpu = c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime
        print(json.dumps({"wall": wall, "cpu": cpu, "relmse": C.rel_mse(img, ref),
                          "budget": str(r.stats.get("budget"))}), flush=True)


def main() -> None:
    if sys.argv[1] == "--worker":
        return worker(sys.argv[2], sys.argv[3])
    name, spp, seeds, refs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    trees = [arg.split(":") for arg in sys.argv[5:7]]
    procs = [subprocess.Popen([sys.executable, __file__, "--worker", tree, refs], text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              env=dict(os.environ, BDPT_CALIBRATION=units, PYTHONPATH=tree))
             for tree, units in trees]

    def run(t, seed, merging):
        procs[t].stdin.write("%s %d %d %d\n" % (name, spp, seed, merging))
        procs[t].stdin.flush()
        return json.loads(procs[t].stdout.readline())

    keys = [(0, 0), (0, 1), (1, 0), (1, 1)]
    for k in keys:                                                    # kernels
        run(*k[:1], 999, k[1])
    rows = {k: [] for k in keys}
    for s in range(seeds):
        for k in keys[s % 4:] + keys[:s % 4]:
            rows[k].append(run(k[0], s, k[1]))
        print(s, " | ".join("%s %.2f s %.4g %s" % ("vcm" if k[1] else "bdpt", rows[k][-1]["wall"],
                                                    rows[k][-1]["relmse"], rows[k][-1]["budget"])
                            for k in keys), flush=True)
    med = {k: {f: statistics.median(r[f] for r in v) for f in ("wall", "cpu", "relmse")}
           for k, v in rows.items()}
    for t, (tree, _) in enumerate(trees):
        b, v = med[(t, 0)], med[(t, 1)]
        print("%s %s: bdpt %.3f s (%.3f CPU s) relMSE %.5g; vcm %.3f s (%.3f CPU s) relMSE %.5g; "
              "vcm / bdpt: time %.3f, CPU %.3f, relMSE %.3f, relMSE x time %.3f, x CPU %.3f"
              % (name, tree, b["wall"], b["cpu"], b["relmse"], v["wall"], v["cpu"], v["relmse"],
                 v["wall"] / b["wall"], v["cpu"] / b["cpu"], v["relmse"] / b["relmse"],
                 v["wall"] * v["relmse"] / (b["wall"] * b["relmse"]),
                 v["cpu"] * v["relmse"] / (b["cpu"] * b["relmse"])))
    for p in procs:
        p.stdin.close()
        p.wait()


if __name__ == "__main__":
    main()
