"""Random small scenes: bdpt against Mitsuba's ``volpath``, block by block.

    python -m benchmarks.random_scenes                    # 20 scenes, seed 1, llvm_ad_rgb
    python -m benchmarks.random_scenes --seed 7 --scenes 40 --variant llvm_ad_spectral
    python -m benchmarks.random_scenes --options budgets  # fixed budgets, not the default
    python -m benchmarks.random_scenes --options integrators   # mlt, pssmlt and vcm
    python -m benchmarks.random_scenes --res 64 --spp 32  # small renders' pilot (1/4 film)

Each scene has a sensor (perspective, thin lens or orthographic; a random reconstruction
filter, rgb or rgba, sometimes a crop window or a sampled filter border), a floor
(sometimes textured), a sphere or a cube (sometimes a cube of fog) and sometimes a wall
with random BSDFs, and a light (an area rectangle or sphere, a point, a spot, a
directional light, a constant or an environment-map sky), sometimes with a small
sphere light beside it.  bdpt renders it 4 x 128 spp (``--spp``) with an option set drawn
per scene, volpath 4 x 512 spp, on films of 24 x 24 pixels (``--res``).  Per 4 x 4 block of the image, z = the difference of the means over
the seeds' standard errors and 2% of the reference; a scene is flagged BAD at z > 6, a
non-finite pixel, or a mean alpha off volpath's by over ALPHA_TOLERANCE; ERR where bdpt
raises (a clear refusal is expected there; anything else is a bug).  Alpha (rgba
films) is printed beside volpath's.

Where volpath cannot be the reference the scene is not drawn, or differs by design:
* a delta light (point, spot, directional) with a delta-lobe BSDF (smooth glass, mirror,
  smooth plastic): light reaches surfaces through them only along light subpaths;
* a surface that lets light pass (mask, thindielectric): its passes count toward
  max_depth here as in Mitsuba's path, not in volpath, so such scenes render at
  max_depth -1.
Seeds are fixed: a scene and its renders depend only on ``--seed`` and its index.
"""
from __future__ import annotations

import argparse
import random
from pathlib import Path

import numpy as np

import mitsuba as mi          # bdpt_drjit is imported once the variant is set (main)

SKY = Path(__file__).resolve().parents[1] / "scenes" / "textures" / "sky.exr"
RES = 24                        # the film's side (--res)
# An rgba film's mean alpha against volpath's: the default bdpt's differed by 0.01 at
# most over seeds 35-38 (the film's edge pixels' samples); mlt's was 0 before it had
# alpha at all.
ALPHA_TOLERANCE = 0.03
LIGHTS = ["area", "area", "point", "spot", "directional", "constant", "sphere", "envmap"]
DELTA_LIGHTS = ("point", "spot", "directional")
PASSING = ("mask", "thindielectric")
OPTIONS = {"default": [{}, {"light_paths": 1, "connections": "all"}, {"hide_emitters": True},
                       {"rr_depth": 1}, {"light_image": False}],
           "budgets": [{"light_paths": 0.25, "connections": 1},
                       {"light_paths": 4, "connections": 0, "first_hits": "light_image"},
                       {"light_paths": 1, "connections": 2},
                       {"mis": "balance", "light_paths": 1, "connections": "all"},
                       {"samples_per_pass": 3},
                       {"light_paths": 2, "connections": "all", "rr_depth": 2}],
           # The other integrators of the engine: MLT (spp = mutations per pixel) and
           # vcm, whose merging is consistent, not unbiased (its bias at 128 spp is a
           # small share of the 2% the test allows).
           "integrators": [{"integrator": "mlt"}, {"integrator": "pssmlt"},
                           {"merging": True}]}


def bsdf(rng: random.Random, delta_ok: bool) -> dict:
    kinds = ["diffuse", "roughconductor", "roughplastic", "principled", "twosided", "blend",
             "roughdielectric", "mask"]
    kinds += ["dielectric", "conductor", "thindielectric", "plastic"] if delta_ok else []
    colour = {"type": "rgb", "value": [rng.uniform(0.2, 0.9) for _ in range(3)]}
    diffuse = {"type": "diffuse", "reflectance": colour}
    return {"diffuse": diffuse,
            "roughconductor": {"type": "roughconductor", "alpha": rng.choice([0.1, 0.3]),
                               "distribution": rng.choice(["ggx", "beckmann"])},
            "roughplastic": {"type": "roughplastic", "diffuse_reflectance": colour, "alpha": 0.2},
            "plastic": {"type": "plastic", "diffuse_reflectance": colour},
            "principled": {"type": "principled", "base_color": colour, "roughness": 0.4,
                           "metallic": rng.choice([0.0, 0.7])},
            "twosided": {"type": "twosided", "bsdf": diffuse},
            "blend": {"type": "blendbsdf", "weight": 0.4, "a": {"type": "diffuse"},
                      "b": {"type": "roughconductor", "alpha": 0.2}},
            "roughdielectric": {"type": "roughdielectric", "alpha": 0.2},
            "mask": {"type": "mask", "opacity": 0.5, "bsdf": diffuse},
            "dielectric": {"type": "dielectric"}, "conductor": {"type": "conductor"},
            "thindielectric": {"type": "thindielectric"}}[rng.choice(kinds)]


def sensor(rng: random.Random) -> dict:
    T = mi.ScalarTransform4f
    kind = rng.choice(["perspective", "perspective", "thinlens", "orthographic"])
    view = T().look_at(origin=[0, 1.0, 4.0], target=[0, 0.3, 0], up=[0, 1, 0])
    film = {"type": "hdrfilm", "width": RES, "height": RES,
            "pixel_format": rng.choice(["rgb", "rgba"]),
            "rfilter": {"type": rng.choice(["box", "gaussian", "tent", "lanczos"])}}
    if rng.random() < 0.3:
        film.update(crop_offset_x=3, crop_offset_y=5, crop_width=RES * 2 // 3,
                    crop_height=RES // 2)
    if rng.random() < 0.3:
        film["sample_border"] = True
    out = {"type": kind, "to_world": view, "film": film,
           "sampler": {"type": rng.choice(["independent", "multijitter"]), "sample_count": 4}}
    if kind == "orthographic":
        out["to_world"] = view @ T().scale([2, 2, 1])
    else:
        out["fov"] = 45
    if kind == "thinlens":
        out.update(aperture_radius=0.05, focus_distance=4.0)
    return out


def light(kind: str) -> dict:
    T = mi.ScalarTransform4f
    rgb = lambda v: {"type": "rgb", "value": v}   # noqa: E731
    return {
        "area": {"type": "rectangle", "emitter": {"type": "area", "radiance": rgb([10, 9, 8])},
                 "to_world": T().translate([0, 2.5, 0]).rotate([1, 0, 0], 90).scale(0.5)},
        "sphere": {"type": "sphere", "center": [1, 2, 1], "radius": 0.3,
                   "emitter": {"type": "area", "radiance": rgb([10, 9, 8])}},
        "point": {"type": "point", "position": [0.5, 2.5, 1.0], "intensity": rgb([20, 20, 20])},
        "spot": {"type": "spot", "intensity": rgb([30, 30, 30]), "cutoff_angle": 40,
                 "to_world": T().look_at(origin=[0, 3, 1], target=[0, 0, 0], up=[0, 0, 1])},
        "directional": {"type": "directional", "direction": [0.3, -1, -0.2],
                        "irradiance": rgb([3, 3, 3])},
        "constant": {"type": "constant", "radiance": rgb([0.7, 0.8, 1.0])},
        "envmap": {"type": "envmap", "filename": str(SKY),
                   "scale": 0.5},
    }[kind]


def scene(rng: random.Random) -> tuple:
    """(scene dict, one-line description, whether a surface lets light pass)."""
    T = mi.ScalarTransform4f
    kind = rng.choice(LIGHTS)
    delta_ok = kind not in DELTA_LIGHTS
    d = {"type": "scene", "sensor": sensor(rng), "light": light(kind),
         "floor": {"type": "rectangle", "bsdf": bsdf(rng, delta_ok),
                   "to_world": T().rotate([1, 0, 0], -90).scale(3)},
         "ball": {"type": rng.choice(["sphere", "cube"]), "bsdf": bsdf(rng, delta_ok),
                  "to_world": T().translate([0, 0.5, 0]).scale(0.5)}}
    if rng.random() < 0.5:
        d["wall"] = {"type": "rectangle", "bsdf": bsdf(rng, False),
                     "to_world": T().translate([0, 1.5, -1.5]).scale(3)}
    if rng.random() < 0.2:                  # the ball becomes a fog cube
        d["ball"] = {"type": "cube", "bsdf": {"type": "null"},
                     "to_world": T().translate([0, 0.5, 0]).scale(0.5),
                     "interior": {"type": "homogeneous", "sigma_t": 1.5, "albedo": 0.8}}
    if rng.random() < 0.2:                  # a second light, a small sphere
        d["lamp"] = {"type": "sphere", "center": [-1, 1.5, 0.5], "radius": 0.15,
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [4, 6, 8]}}}
    if rng.random() < 0.15:                 # a textured floor
        d["floor"]["bsdf"] = {"type": "diffuse", "reflectance": {
            "type": "checkerboard", "to_uv": T().scale([8, 8, 1])}}
    bsdfs = [d[k]["bsdf"]["type"] for k in ("floor", "ball", "wall") if k in d]
    film = d["sensor"]["film"]
    desc = "%s %s%s%s %s%s, %s%s" % (d["sensor"]["type"], film["rfilter"]["type"],
                                     " crop" if "crop_width" in film else "",
                                     " border" if film.get("sample_border") else "", kind,
                                     " + lamp" if "lamp" in d else "", "/".join(bsdfs),
                                     " (fog)" if "interior" in d["ball"] else "")
    return d, desc, any(b in PASSING for b in bsdfs)


def blocks(image: np.ndarray) -> np.ndarray:
    lum = image[..., :3].mean(-1)
    h, w = (n // 4 * 4 for n in lum.shape)
    return lum[:h, :w].reshape(4, h // 4, 4, w // 4).mean((1, 3))


def check(d: dict, max_depth: int, options: dict, spp: int = 128) -> tuple:
    """(worst block z, bdpt's mean, volpath's, alpha means or None, all finite)."""
    import bdpt_drjit
    scene = mi.load_dict(d, optimize=False)      # as support.load_file
    hide = options.get("hide_emitters", False)
    ref = [np.array(mi.render(scene, spp=512, seed=100 + i, integrator=mi.load_dict(
        {"type": "volpath", "max_depth": max_depth, "hide_emitters": hide}))) for i in range(4)]
    ours = [bdpt_drjit.render(scene, spp=spp, seed=i, max_depth=max_depth, **options).image
            for i in range(4)]
    a, b = np.array([blocks(x) for x in ours]), np.array([blocks(x) for x in ref])
    se2 = (a.var(0, ddof=1) + b.var(0, ddof=1)) / 4 + (0.02 * b.mean(0)) ** 2 + 1e-8
    z = float(np.abs((a.mean(0) - b.mean(0)) / np.sqrt(se2)).max())
    alpha = ((np.mean([x[..., 3].mean() for x in ours]), np.mean([x[..., 3].mean() for x in ref]))
             if ours[0].shape[-1] == 4 else None)
    return z, a.mean(), b.mean(), alpha, all(np.isfinite(x).all() for x in ours)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--options", choices=sorted(OPTIONS), default="default")
    ap.add_argument("--res", type=int, default=RES)
    ap.add_argument("--spp", type=int, default=128)
    a = ap.parse_args()
    mi.set_variant(a.variant)
    globals()["RES"] = a.res
    rng = random.Random(a.seed)
    bad = 0
    for index in range(a.scenes):
        d, desc, passing = scene(rng)
        max_depth = -1 if passing else rng.choice([3, 5, -1])
        options = rng.choice(OPTIONS[a.options])
        try:
            z, ours, ref, alpha, finite = check(d, max_depth, options, a.spp)
        except Exception as e:                  # a refusal or a bug: printed either way
            print("ERR  %2d %s, max_depth %d, %s: %s: %s" % (index, desc, max_depth, options,
                                                            type(e).__name__, str(e)[:200]), flush=True)
            continue
        off_alpha = alpha is not None and abs(alpha[0] - alpha[1]) > ALPHA_TOLERANCE
        flag = "BAD" if z > 6 or not finite or off_alpha else "ok "
        bad += flag == "BAD"
        print("%s  %2d %s, max_depth %d, %s: mean %.4f (volpath %.4f), worst block z %.1f%s"
              % (flag, index, desc, max_depth, options, ours, ref, z,
                 "" if alpha is None else ", alpha %.3f (%.3f)" % alpha), flush=True)
    print("%d of %d scenes flagged" % (bad, a.scenes))


if __name__ == "__main__":
    main()
