"""Per-render cost that grows with the scene's triangles: a grid mesh of 2 n^2
triangles with vertex normals, rendered at 32x32 and 1 spp (so the samples cost
nothing), and the reversed-normals check that every render runs on every mesh.

    python benchmarks/experiments/big_mesh.py          # n = 512: 524288 triangles
"""
import sys
import time
from pathlib import Path

import numpy as np


def grid_scene(n: int):
    import mitsuba as mi
    xs, ys = np.meshgrid(np.linspace(-1, 1, n + 1), np.linspace(-1, 1, n + 1))
    positions = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1).astype(np.float32)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.uint32)
    mesh = mi.Mesh("grid", len(positions), len(faces), has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params["vertex_normals"] = mi.Float(np.tile(np.float32([0, 0, 1]), len(positions)))
    params.update()
    camera = mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0])
    return mesh, mi.load_dict({
        "type": "scene", "grid": mesh, "light": {"type": "point", "position": [0, 0, 1]},
        "sensor": {"type": "perspective", "to_world": camera,
                   "film": {"type": "hdrfilm", "width": 32, "height": 32}}})


def main(n: int = 512) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))      # this checkout
    import bdpt_drjit
    from bdpt_drjit import support
    mesh, scene = grid_scene(n)
    bdpt_drjit.render(scene, spp=1, seed=0, max_depth=3)                # kernels
    for name, run in (("render", lambda s: bdpt_drjit.render(scene, spp=1, seed=s, max_depth=3)),
                      ("reversed_normals", lambda s: support.reversed_normals(mesh))):
        times = []
        for seed in range(1, 4):
            start = time.perf_counter()
            run(seed)
            times.append(time.perf_counter() - start)
        print("%d triangles: %s %.1f ms (median of 3)" % (2 * n * n, name, 1e3 * sorted(times)[1]))


if __name__ == "__main__":
    main(*map(int, sys.argv[1:]))
