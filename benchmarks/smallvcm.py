"""SmallVCM side by side: this project's ``vcm`` and default ``bdpt`` against SmallVCM's
``vcm`` and ``bpt`` at equal time, on SmallVCM's own Cornell boxes rebuilt in Mitsuba
(issue 30).

SmallVCM (Davidovic and Georgiev's reference implementation of VCM, MIT licence) is not
part of this project: build it in a scratch folder outside the checkout, with
benchmarks/smallvcm.patch (three more scene ids, the film size and the seed from the
environment; nothing else changes):

    fetch github:SmallVCM/SmallVCM; git --git-dir=REPO archive HEAD | tar -x -C DIR
    cd DIR && patch -p0 < /path/to/benchmarks/smallvcm.patch
    g++ -O3 -fopenmp -std=c++11 -o smallvcm src/smallvcm.cxx

    python -m benchmarks.smallvcm DIR/smallvcm                  # means, then equal time
    python -m benchmarks.smallvcm DIR/smallvcm --check          # image means only
    python -m benchmarks.smallvcm DIR/smallvcm --scenes bs_c --runs 4 --cpu-seconds 20

Without the binary it says so and exits (status 0).

Scenes (SmallVCM's ``Scene::LoadCornellBox``, its box masks; ids of the patched build):

    bs_c  4  mirror and glass spheres (r 0.5), ceiling light box (area, radiance 25.03)
    lg_c  5  large glass sphere (r 0.8), ceiling light box
    bs_p  6  mirror and glass spheres, point light (intensity 70 / 4 pi W/sr)

SmallVCM's four stock scenes all have its glossy floor (Phong, exponent 90), which
Mitsuba 3 has no BSDF for; these are its diffuse-floor variants (``kDefault`` is bs_c).
Glass: IOR 1.6, mirror: reflectance 1; walls Lambertian; every triangle keeps SmallVCM's
winding (one-sided diffuse and emitter, as there).  128x128, max path length 10 (edges,
both), box pixel filter.

Reference per scene: SmallVCM ``vcm`` for REF_CPU CPU seconds (its -t counts CPU time
over its 2 threads), cached under benchmarks/results/smallvcm-refs; the image means of
that reference, of a long SmallVCM ``bpt`` and of this project's ``bdpt`` (REF_SPP spp)
are printed first (``--check``).

Equal time: per run, SmallVCM ``vcm`` and ``bpt`` with ``-t CPU`` (``--cpu-seconds``,
default 20: about 10 s wall on 2 idle cores) and this project's ``vcm`` (merging=True,
budgets auto) and default ``bdpt`` at SPP samples per pixel (``--spp``, or chosen after a
warm-up so that a render takes as many CPU seconds), in turn, the order rotating per run.
Each render is timed in wall-clock seconds (SmallVCM: around its process; ours: around
``bdpt_drjit.render`` and its image) and CPU seconds (rusage of the child / this process).
Error at equal time = relMSE x seconds (relMSE: the suite's, common.rel_mse), medians over
runs, as ratios to SmallVCM ``vcm``'s.  Dr.Jit's LLVM backend uses every core (2 here),
SmallVCM runs 2 OpenMP threads (one per core): nothing is restricted.
"""
from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from . import common as C

import bdpt_drjit
import mitsuba as mi

RES = 128
MAX_DEPTH = 10
REF_CPU = 400           # SmallVCM vcm CPU seconds for the reference (about 200 s on 2 cores)
REF_SPP = 1024          # this project's bdpt for the means check

# SmallVCM's Cornell box (scene.hxx, LoadCornellBox)
_CB = np.array([[-1.27029, 1.30455, -1.28002], [1.28975, 1.30455, -1.28002],
                [1.28975, 1.30455, 1.28002], [-1.27029, 1.30455, 1.28002],
                [-1.27029, -1.25549, -1.28002], [1.28975, -1.25549, -1.28002],
                [1.28975, -1.25549, 1.28002], [-1.27029, -1.25549, 1.28002]])
_LB = np.array([[-0.25, 0.25, 1.26002], [0.25, 0.25, 1.26002], [0.25, 0.25, 1.28002],
                [-0.25, 0.25, 1.28002], [-0.25, -0.25, 1.26002], [0.25, -0.25, 1.26002],
                [0.25, -0.25, 1.28002], [-0.25, -0.25, 1.28002]])
_WHITE, _GREEN, _RED = [0.803922] * 3, [0.156863, 0.803922, 0.172549], [0.803922, 0.152941, 0.152941]

SCENES = {                      # name: (SmallVCM scene id of the patched build, content, light)
    "bs_c": (4, "small", "ceiling"),
    "lg_c": (5, "large-glass", "ceiling"),
    "bs_p": (6, "small", "point"),
}


def _obj(path: Path, tris) -> str:
    with open(path, "w") as f:
        for t in tris:
            for p in t:
                f.write("v %.7g %.7g %.7g\n" % tuple(p))
        for i in range(len(tris)):
            f.write("f %d %d %d\n" % (3 * i + 1, 3 * i + 2, 3 * i + 3))
    return str(path)


def build_scene(name: str, res: int = RES, tmp: Path | None = None):
    """SmallVCM's box `name` as a Mitsuba scene (triangles in its order and winding)."""
    _, content, light = SCENES[name]
    tmp = Path(tmp or tempfile.mkdtemp(prefix="smallvcm-"))
    cb, lb = _CB, _LB
    box = light == "ceiling"                                # the light box (no box with a point light)
    white = [(cb[0], cb[4], cb[5]), (cb[5], cb[1], cb[0]),  # floor
             (cb[0], cb[1], cb[2]), (cb[2], cb[3], cb[0]),  # back wall
             (cb[2], cb[6], cb[7]), (cb[7], cb[3], cb[2])]  # ceiling
    if box:
        white += [(lb[0], lb[2], lb[1]), (lb[2], lb[0], lb[3]), (lb[3], lb[4], lb[7]),
                  (lb[4], lb[3], lb[0]), (lb[1], lb[6], lb[5]), (lb[6], lb[1], lb[2]),
                  (lb[4], lb[5], lb[6]), (lb[6], lb[7], lb[4])]
    diffuse = lambda c: {"type": "diffuse", "reflectance": {"type": "rgb", "value": c}}
    d = {"type": "scene",
         "integrator": {"type": "path", "max_depth": MAX_DEPTH},
         "sensor": {"type": "perspective", "fov": 45, "fov_axis": "x",
                    "to_world": mi.ScalarTransform4f().look_at(
                        origin=[-0.0439815, -4.12529, 0.222539],
                        target=[-0.0439815 + 0.00688625, -4.12529 + 0.998505, 0.222539 - 0.0542161],
                        up=[3.73896e-4, 0.0542148, 0.998529]),
                    "film": {"type": "hdrfilm", "width": res, "height": res,
                             "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                    "sampler": {"type": "independent"}},
         "white": {"type": "obj", "filename": _obj(tmp / "white.obj", white), "face_normals": True,
                   "bsdf": diffuse(_WHITE)},
         "left": {"type": "obj", "filename": _obj(tmp / "left.obj", [(cb[3], cb[7], cb[4]), (cb[4], cb[0], cb[3])]),
                  "face_normals": True, "bsdf": diffuse(_GREEN)},
         "right": {"type": "obj", "filename": _obj(tmp / "right.obj", [(cb[1], cb[5], cb[6]), (cb[6], cb[2], cb[1])]),
                   "face_normals": True, "bsdf": diffuse(_RED)}}
    mirror = {"type": "conductor", "material": "none"}
    glass = {"type": "dielectric", "int_ior": 1.6, "ext_ior": 1.0}
    floor_c = (cb[0] + cb[1] + cb[4] + cb[5]) / 4
    if content == "large-glass":
        d["ball"] = {"type": "sphere", "center": (floor_c + [0, 0, 0.8]).tolist(), "radius": 0.8, "bsdf": glass}
    else:
        lw, rw = (cb[0] + cb[4]) / 2 + [0, 0, 0.5], (cb[1] + cb[5]) / 2 + [0, 0, 0.5]
        xlen = rw[0] - lw[0]
        d["mirror_ball"] = {"type": "sphere", "center": (lw + [2 * xlen / 7, 0, 0]).tolist(), "radius": 0.5,
                            "bsdf": mirror}
        d["glass_ball"] = {"type": "sphere", "center": (rw - [2 * xlen / 7, 0, 0]).tolist(), "radius": 0.5,
                           "bsdf": glass}
    if box:
        d["light"] = {"type": "obj", "filename": _obj(tmp / "light.obj", [(lb[0], lb[5], lb[4]), (lb[5], lb[0], lb[1])]),
                      "face_normals": True, "bsdf": diffuse([0.0] * 3),
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [25.03329895614464] * 3}}}
    else:
        d["light"] = {"type": "point", "position": [0.0, -0.5, 1.0],
                      "intensity": {"type": "rgb", "value": [70.0 / (4 * math.pi)] * 3}}
    return mi.load_dict(d, optimize=False)      # as support.load_file


def read_hdr(path) -> np.ndarray:
    """A Radiance .hdr as SmallVCM writes it (flat RGBE, no run-length coding): (H, W, 3)."""
    data = Path(path).read_bytes()
    head, _, rest = data.partition(b"\n\n")
    dims, _, pix = rest.partition(b"\n")
    _, h, _, w = dims.split()
    rgbe = np.frombuffer(pix, np.uint8)[:int(h) * int(w) * 4].reshape(int(h), int(w), 4).astype(np.float64)
    scale = np.where(rgbe[..., 3] > 0, np.ldexp(1.0, rgbe[..., 3].astype(int) - 136), 0.0)
    return (rgbe[..., :3] + 0.5) * scale[..., None]       # truncated on writing: + 0.5 is unbiased


# -- runs ----------------------------------------------------------------------------------
# SmallVCM's radius: 0.003 x its scene's bounding-sphere radius (2.2166 in these boxes)
SMALLVCM_RADIUS = 0.003 * 0.5 * float(np.linalg.norm(_CB.max(0) - _CB.min(0)))
OURS = {"vcm": C.Method("vcm", "vcm (merging, budgets auto)", "bdpt", (("merging", True),)),
        "bdpt": C.BDPT_AUTO,
        # SmallVCM's vcm in this engine: 1 light subpath per pixel, every connection,
        # merging in every pass at SmallVCM's first radius (diagnostic, ``--fixed``)
        "vcm-fixed": C.Method("vcm-fixed", "vcm, SmallVCM's budget and radius", "bdpt",
                              (("merging", True), ("light_paths", 1), ("connections", "all"),
                               ("radius", SMALLVCM_RADIUS)))}


def _cpu_self() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_smallvcm(binary: str, name: str, algo: str, cpu_seconds: float, seed: int, out: Path):
    """SmallVCM's `algo` on scene `name` for `cpu_seconds` of its clock() (CPU time over its
    threads): (image, wall seconds, CPU seconds)."""
    env = dict(os.environ, SMALLVCM_RES=str(RES), SMALLVCM_SEED=str(seed))
    c0, t0 = _cpu_children(), time.perf_counter()
    subprocess.run([binary, "-s", str(SCENES[name][0]), "-a", algo, "-t", "%g" % cpu_seconds,
                    "-o", str(out)], env=env, check=True, stdout=subprocess.DEVNULL)
    wall, cpu = time.perf_counter() - t0, _cpu_children() - c0
    return read_hdr(out), wall, cpu


def run_ours(method: C.Method, scene, spp: int, seed: int):
    c0 = _cpu_self()
    out = C.render(method, scene, spp, seed, MAX_DEPTH)
    return out.image[..., :3].astype(np.float64), out.timing.wall, _cpu_self() - c0


def reference(binary: str, name: str, refdir: Path) -> np.ndarray:
    cache = refdir / ("%s_vcm_%dcpu.hdr" % (name, REF_CPU))
    if not cache.exists():
        refdir.mkdir(parents=True, exist_ok=True)
        C.log("reference: SmallVCM vcm %s, %d CPU seconds" % (name, REF_CPU))
        run_smallvcm(binary, name, "vcm", REF_CPU, 777000, cache)
    return read_hdr(cache)


def check_means(binary: str, name: str, ref: np.ndarray, scratch: Path, spp: int) -> dict:
    """Image means (and of the left/right halves) of SmallVCM's reference, a SmallVCM bpt
    render and this project's bdpt (light_paths=1, connections=all: no decision)."""
    scene = build_scene(name, tmp=scratch)
    ours, wall, _ = run_ours(C.Method("bdpt-full", "", "bdpt", (("light_paths", 1), ("connections", "all"))),
                             scene, spp, 4242)
    bpt, _, _ = run_smallvcm(binary, name, "bpt", 60, 888000, scratch / ("%s_bpt.hdr" % name))
    row = {}
    for k, img in (("smallvcm vcm ref", ref), ("smallvcm bpt 60 cpu-s", bpt), ("bdpt %d spp" % spp, ours)):
        row[k] = [float(img.mean()), float(img[:, :RES // 2].mean()), float(img[:, RES // 2:].mean())]
    C.log("%s means (all, left, right): %s; ours/ref %.4f, relMSE ours %.2e" % (
        name, "; ".join("%s %s" % (k, ", ".join("%.4f" % x for x in v)) for k, v in row.items()),
        row["bdpt %d spp" % spp][0] / row["smallvcm vcm ref"][0], C.rel_mse(ours, ref)))
    return row


def equal_time(binary: str, name: str, ref: np.ndarray, scratch: Path, cpu_seconds: float, runs: int,
               spp: dict | None = None, save: Path | None = None, fixed: bool = False) -> dict:
    scene = build_scene(name, tmp=scratch)
    # warm-up: kernels, and the spp whose CPU time is SmallVCM's (a line through the CPU
    # seconds of 16 and 64 spp: the pilot's cost does not scale with spp)
    spp = dict(spp or {})
    ours = {k: m for k, m in OURS.items() if fixed or k != "vcm-fixed"}
    for key, m in ours.items():
        run_ours(m, scene, 16, 999)
        if key not in spp:
            c16, c64 = run_ours(m, scene, 16, 998)[2], run_ours(m, scene, 64, 997)[2]
            per = max((c64 - c16) / 48, 1e-6)
            spp[key] = max(16, int(round(16 + (cpu_seconds - c16) / per)))
    C.log("%s: spp %s for SmallVCM's -t %g" % (name, spp, cpu_seconds))
    order = ["sv-vcm", "ours-vcm", "sv-bpt", "ours-bdpt"] + (["ours-vcm-fixed"] if fixed else [])
    rows = {k: [] for k in order}
    for r in range(runs):
        for k in order[r % len(order):] + order[:r % len(order)]:
            if k.startswith("sv-"):
                img, wall, cpu = run_smallvcm(binary, name, k[3:], cpu_seconds, 1000 * (r + 1),
                                              scratch / ("%s_%s.hdr" % (name, k)))
            else:
                img, wall, cpu = run_ours(OURS[k[5:]], scene, spp[k[5:]], 1000 * (r + 1))
            e = C.rel_mse(img, ref)
            rows[k].append((wall, cpu, e))
            if save:
                np.save(save / ("%s_%s_%d.npy" % (name, k, r)), img.astype(np.float32))
            C.log("  run %d %-9s %.2f s wall %.2f s cpu relMSE %.4e" % (r, k, wall, cpu, e))
    med = {k: {"wall": statistics.median(w for w, _, _ in v), "cpu": statistics.median(c for _, c, _ in v),
               "relmse": statistics.median(e for _, _, e in v),
               "err_wall": statistics.median(w * e for w, _, e in v),
               "err_cpu": statistics.median(c * e for _, c, e in v)} for k, v in rows.items()}
    base = med["sv-vcm"]
    for k, v in med.items():
        v["ratio_wall"] = v["err_wall"] / base["err_wall"]
        v["ratio_cpu"] = v["err_cpu"] / base["err_cpu"]
    return {"scene": name, "smallvcm_id": SCENES[name][0], "cpu_seconds": cpu_seconds, "spp": spp,
            "runs": runs, "medians": med, "rows": rows}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("binary", help="SmallVCM built with benchmarks/smallvcm.patch")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--cpu-seconds", type=float, default=20.0, help="SmallVCM's -t (CPU seconds)")
    ap.add_argument("--spp", help="ours' spp, e.g. vcm=64,bdpt=128 (default: SmallVCM's wall time)")
    ap.add_argument("--check", action="store_true", help="image means only")
    ap.add_argument("--check-spp", type=int, default=REF_SPP)
    ap.add_argument("--no-check", action="store_true", help="equal time only")
    ap.add_argument("--out", default=str(C.RESULTS / "smallvcm.json"))
    ap.add_argument("--save", help="a folder for every run's image (.npy)")
    ap.add_argument("--fixed", action="store_true",
                    help="also vcm-fixed: SmallVCM's budget and radius in this engine")
    a = ap.parse_args(argv)
    if not Path(a.binary).is_file():
        C.log("SmallVCM binary %s not found: nothing to compare (build it as the module "
              "docstring says)" % a.binary)
        return
    spp = {k: int(v) for k, v in (kv.split("=") for kv in a.spp.split(","))} if a.spp else None
    scratch = Path(tempfile.mkdtemp(prefix="smallvcm-"))
    out = {"machine": C.machine_info(), "binary": a.binary, "scenes": {}}
    for name in a.scenes.split(","):
        ref = reference(a.binary, name, C.RESULTS / "smallvcm-refs")
        res = {} if a.no_check else {"means": check_means(a.binary, name, ref, scratch, a.check_spp)}
        if not a.check:
            save = Path(a.save) if a.save else None
            if save:
                save.mkdir(parents=True, exist_ok=True)
            res.update(equal_time(a.binary, name, ref, scratch, a.cpu_seconds, a.runs, spp, save, a.fixed))
            for k, v in res["medians"].items():
                C.log("%s %-9s wall %.2f s cpu %.2f s relMSE %.4e  err x wall %.3f x SmallVCM vcm's, "
                      "x cpu %.3f" % (name, k, v["wall"], v["cpu"], v["relmse"], v["ratio_wall"], v["ratio_cpu"]))
        out["scenes"][name] = res
        C.write_json(Path(a.out), out)


if __name__ == "__main__":
    main()
