"""How the calibration box's unit costs transfer to a suite scene (issue 28): per unit,
what the scene's walks take (kernel seconds per camera sample of fixed budgets, the
stages' laps as the calibration times them) over what the pilot's counts times the
stored units price.  1 everywhere: the units transfer; the spread between units is
what misprices one budget against another.

    python benchmarks/experiments/unit_transfer.py veach-bidir --res 128 --spp 16

light and camera ray: ``light_paths=1 connections=0``; stored vertex and connection:
``light_paths=1 connections=all`` less that; path's ray: Mitsuba's ``path``.

What a scene's rays cost besides its counts, each alone:

* ``dense-box --grid N``: the calibration box with every wall and box an N x N-quad
  triangle grid (its geometry denser, its image the same);
* ``--diffuse``: an external scene with its rough conductor and glass made diffuse
  (its geometry the same, its BSDFs the box's);
* ``--packets``: how much longer the walks run than their rays, where a SIMD packet
  of 16 lanes runs a walk's loop while one of its lanes lives (walk.py): the packets'
  longest subpath x 16 over the rays, per walk (Veach's BDPT, 4 spp).
"""
import argparse
import re
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import common as C                                     # noqa: E402,F401
import drjit as dr                                                     # noqa: E402
import mitsuba as mi                                                   # noqa: E402
import numpy as np                                                     # noqa: E402
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


def grid_ply(folder: Path, n: int, cube: bool) -> str:
    """An N x N-quad triangle grid over Mitsuba's rectangle ([-1, 1]^2, z = 0, normal +z),
    or over the six faces of its cube, written as PLY."""
    u = np.linspace(-1.0, 1.0, n + 1)
    x, y = np.meshgrid(u, u, indexing="ij")
    face = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    turns = [np.eye(3)] if not cube else [np.array(m, float) for m in (
        np.eye(3), [[1, 0, 0], [0, -1, 0], [0, 0, -1]], [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],
        [[0, 0, -1], [0, 1, 0], [1, 0, 0]], [[1, 0, 0], [0, 0, 1], [0, -1, 0]],
        [[1, 0, 0], [0, 0, -1], [0, 1, 0]])]
    lift = np.array([0.0, 0.0, 1.0 if cube else 0.0])
    points = np.concatenate([(face + lift) @ m.T for m in turns])
    faces = np.concatenate([tris + i * len(face) for i in range(len(turns))])
    mesh = mi.Mesh("grid", len(points), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(points.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    out = folder / ("%s%d.ply" % ("cube" if cube else "grid", n))
    mesh.write_ply(str(out))
    return str(out)


def dense_box(res: int, n: int, folder: Path) -> mi.Scene:
    box = mi.cornell_box()
    box["sensor"]["film"].update(width=res, height=res)
    for name, shape in list(box.items()):
        if isinstance(shape, dict) and shape.get("type") in ("rectangle", "cube") \
                and "emitter" not in shape:
            box[name] = dict(shape, type="ply",
                             filename=grid_ply(folder, n, shape["type"] == "cube"))
    return mi.load_dict(box)


def made_diffuse(spec, width: int, height: int) -> mi.Scene:
    """An external scene with its rough conductors and dielectrics diffuse."""
    text = spec.file.read_text()
    for kind in ("roughconductor", "conductor", "dielectric", "roughdielectric"):
        text = re.sub(r'<bsdf type="%s"( id="[^"]*")?>.*?</bsdf>' % kind,
                      r'<bsdf type="diffuse"\1/>', text, flags=re.S)
    fr = mi.file_resolver()
    fr.prepend(str(spec.file.parent))
    return mi.load_string(text, optimize=False, resx=width, resy=height,
                          max_depth=spec.max_depth)


def packet_spread(render, scene, max_depth: int, width: int = 16) -> dict:
    """Per walk, the packets' longest subpath x ``width`` over the walk's rays."""
    walks, light, camera = {}, render.Renderer._light_subpaths, render.Renderer._camera_walk

    def light_walk(self, ctx, index, spp):
        store, rays = light(self, ctx, index, spp)
        walks["light"] = rays.numpy()
        return store, rays

    def camera_walk(ctx, rays, store):
        cam = camera(ctx, rays, store)
        walks["camera"] = cam.rays.numpy()
        return cam

    render.Renderer._light_subpaths = light_walk
    render.Renderer._camera_walk = staticmethod(camera_walk)
    try:
        render.Renderer(scene, spp=4, seed=1, max_depth=max_depth, light_paths=1,
                        connections=0, samples_per_pass=4).run_pass()
    finally:
        render.Renderer._light_subpaths = light
        render.Renderer._camera_walk = staticmethod(camera)
    out = {}
    for name, rays in walks.items():
        packets = rays[:len(rays) // width * width].reshape(-1, width).astype(float)
        out[name] = packets.max(1).sum() * width / max(packets.sum(), 1.0)
    return out


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
    ap.add_argument("--grid", type=int, default=18, help="dense-box: quads per side")
    ap.add_argument("--diffuse", action="store_true")
    ap.add_argument("--packets", action="store_true")
    a = ap.parse_args()
    import bdpt_drjit                                                  # noqa: F401
    render = sys.modules["bdpt_drjit.render"]      # (bdpt_drjit.render: the function)
    if a.scene == "dense-box":
        with tempfile.TemporaryDirectory() as folder:
            scene, (w, h), max_depth = dense_box(a.res, a.grid, Path(folder)), (a.res,) * 2, 8
    else:
        spec = SCENES[a.scene]
        w, h, _ = spec.resolution(a.res)
        scene = made_diffuse(spec, w, h) if a.diffuse else spec.load(w, h)
        max_depth = spec.max_depth
    if a.packets:
        print("%s: packet spread %s" % (a.scene, " ".join(
            "%s %.2f" % kv for kv in packet_spread(render, scene, max_depth).items())))
    pilot = render.Renderer(scene, spp=a.spp, seed=1, max_depth=max_depth)
    pilot.run_pass()
    c, u = pilot.pilot.costs, pilot.pilot.costs.units
    light0, camera0 = walk_seconds(render, scene, a.spp, max_depth,
                                   light_paths=1, connections=0)
    light1, camera1 = walk_seconds(render, scene, a.spp, max_depth,
                                   light_paths=1, connections="all")
    path = path_seconds(scene, a.spp, max_depth, w * h * a.spp)
    print("%s %dx%d, %d triangles or shapes, %d spp: measured / priced per unit (%s)"
          % (a.scene, w, h, sum(s.primitive_count() for s in scene.shapes()), a.spp,
             u.describe()))
    for name, measured, priced in (
            ("light ray", light0, c.light_rays * u.light_ray),
            ("camera ray", camera0, c.camera_rays * u.camera_ray),
            ("stored vertex", light1 - light0, c.stored_per_path * u.stored_vertex),
            ("connection", camera1 - camera0, c.connection_rays * u.connection),
            ("path's ray", path, c.camera_rays * u.path_ray)):
        print("  %-14s %.2f" % (name, measured / priced))


if __name__ == "__main__":
    main()
