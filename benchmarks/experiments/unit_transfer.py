"""How the calibration box's unit costs transfer to a suite scene (issue 28): per unit,
what the scene's walks take (kernel seconds per camera sample of fixed budgets, the
stages' laps as the calibration times them) over what the pilot's counts times the
stored units price.  1 everywhere: the units transfer; the spread between units is
what misprices one budget against another.

    python benchmarks/experiments/unit_transfer.py veach-bidir --res 128 --spp 16

light and camera ray: ``light_paths=1 connections=0``; stored vertex and connection:
``light_paths=1 connections=all`` less that; path's ray: Mitsuba's ``path``.
"""
import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import common as C                                     # noqa: E402,F401
import drjit as dr                                                     # noqa: E402
import mitsuba as mi                                                   # noqa: E402
from benchmarks.scenes import SCENES                                   # noqa: E402


def walk_seconds(render, scene, spp: int, max_depth: int, **budget) -> tuple:
    """(light side, camera side) kernel seconds per camera sample, medians of seeds
    1-2 (seed 0 compiles)."""
    rows = []
    for seed in range(3):
        r = render.Renderer(scene, spp=spp, seed=seed, max_depth=max_depth,
                            samples_per_pass=4, **budget)
        r.timings = {}
        while not r.done:
            r.run_pass()
        lanes = sum(n * s for _, n, s in r.plan)
        rows.append(tuple(sum(t[i] for t in r.timings.values()) / lanes for i in (0, 1)))
    return tuple(statistics.median(row[i] for row in rows[1:]) for i in (0, 1))


def path_seconds(scene, spp: int, max_depth: int, samples: int) -> float:
    path = mi.load_dict({"type": "path", "max_depth": max_depth})
    out = []
    for seed in range(3):
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            dr.eval(mi.render(scene, integrator=path, spp=spp, seed=seed))
            dr.sync_thread()
            out.append(sum(e.get("execution_time", 0.0) for e in dr.kernel_history()
                           if e["type"] == dr.KernelType.JIT) / 1000.0)
    return statistics.median(out[1:]) / samples


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    a = ap.parse_args()
    import bdpt_drjit                                                  # noqa: F401
    render = sys.modules["bdpt_drjit.render"]      # (bdpt_drjit.render: the function)
    spec = SCENES[a.scene]
    w, h, _ = spec.resolution(a.res)
    scene = spec.load(w, h)
    pilot = render.Renderer(scene, spp=a.spp, seed=1, max_depth=spec.max_depth)
    pilot.run_pass()
    c, u = pilot.pilot.costs, pilot.pilot.costs.units
    light0, camera0 = walk_seconds(render, scene, a.spp, spec.max_depth,
                                   light_paths=1, connections=0)
    light1, camera1 = walk_seconds(render, scene, a.spp, spec.max_depth,
                                   light_paths=1, connections="all")
    path = path_seconds(scene, a.spp, spec.max_depth, w * h * a.spp)
    print("%s %dx%d, %d spp: measured / priced per unit (%s)"
          % (a.scene, w, h, a.spp, u.describe()))
    for name, measured, priced in (
            ("light ray", light0, c.light_rays * u.light_ray),
            ("camera ray", camera0, c.camera_rays * u.camera_ray),
            ("stored vertex", light1 - light0, c.stored_per_path * u.stored_vertex),
            ("connection", camera1 - camera0, c.connection_rays * u.connection),
            ("path's ray", path, c.camera_rays * u.path_ray)):
        print("  %-14s %.2f" % (name, measured / priced))


if __name__ == "__main__":
    main()
