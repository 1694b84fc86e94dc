"""``bdpt info``: what the renderer sees in a scene, or what an image's header says."""
from __future__ import annotations

import warnings
from pathlib import Path

from .errors import CLIError, one_line
from .images import read_image
from .scene import (check_sensor_index, integrator_defaults, load_scene, make_renderer,
                    scene_params, scene_path, setup_variant)

_BSDF_NAMES = {
    "SmoothDiffuse": "diffuse", "TwoSidedBRDF": "twosided", "SmoothDielectric": "dielectric",
    "ThinDielectric": "thindielectric", "RoughDielectric": "roughdielectric",
    "SmoothConductor": "conductor", "RoughConductor": "roughconductor",
    "SmoothPlastic": "plastic", "RoughPlastic": "roughplastic", "Principled": "principled",
    "PrincipledThinBSDF": "principledthin", "BlendBSDF": "blendbsdf", "MaskBSDF": "mask",
    "NullBSDF": "null", "BumpMap": "bumpmap", "NormalMap": "normalmap",
    "HairBSDF": "hair", "Polarizer": "polarizer", "Retarder": "retarder",
    "MeasuredBSDF": "measured", "PPLastic": "pplastic"}
# The header entries of 'bdpt render', in the order shown; others follow.
_HEADER_ORDER = ("spp", "spp_requested", "seed", "passes", "render_time", "merged_from",
                 "scene", "scene_params", "sensor", "variant", "bdpt_version")


def _variant_line(mi) -> str:
    variant = mi.variant()
    if variant.startswith("llvm_"):
        import drjit as dr
        try:
            variant += " (LLVM %s)" % ".".join(map(str, dr.detail.llvm_version()))
        except Exception:
            pass
    return "variant:    %s" % variant


def _sensor_lines(scene, chosen: int) -> list:
    from ..emitters import plugin_name
    sensors = scene.sensors()
    if not sensors:
        return ["sensor:     none  [refused: the scene has no sensor]"]
    lines = []
    for i, sensor in enumerate(sensors):
        name = plugin_name(sensor)
        note = "" if len(sensors) == 1 else "  [%d%s]" % (
            i, ": rendered" if i == chosen else "; --sensor %d renders it" % i)
        film, sampler = sensor.film(), sensor.sampler()
        size = tuple(int(x) for x in film.size())
        crop = tuple(int(x) for x in film.crop_size())
        lines.append("sensor:     %s%s" % (name, note))
        lines.append("film:       %s %dx%d%s, %s filter" % (
            film.class_name(), size[0], size[1],
            "" if crop == size else " (crop %dx%d)" % crop, film.rfilter().class_name()))
        lines.append("sampler:    %s, %d spp" % (sampler.class_name(), sampler.sample_count()))
    return lines


def _content_lines(scene) -> list:
    from ..emitters import plugin_name
    emitters = scene.emitters()
    lines = ["emitters:   none  [warning: the image will be black]"] if not emitters else []
    lines += ["emitter:    %s" % plugin_name(e) for e in emitters]
    bsdfs, kinds = set(), {}
    for shape in scene.shapes():
        kinds[shape.class_name()] = kinds.get(shape.class_name(), 0) + 1
        b = shape.bsdf()
        if b is not None:
            ident = b.id()
            bsdfs.add((_BSDF_NAMES.get(b.class_name(), b.class_name()),
                       ident if ident and not ident.startswith("_unnamed") else ""))
    lines.append("bsdfs:      %s" % (", ".join(
        label + (" '%s'" % ident if ident else "") for label, ident in sorted(bsdfs)) or "none"))
    lines.append("shapes:     %d (%s)" % (sum(kinds.values()), ", ".join(
        "%s x%d" % kv for kv in sorted(kinds.items()))))
    return lines


def _verdict(scene, sensor: int, settings: dict) -> str:
    """The definitive answer: what constructing the renderer says."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            make_renderer(scene, sensor, None, 0, False, settings)
        except CLIError as e:
            return "status:     REFUSED: %s" % e
    extra = "".join("; warning: %s" % one_line(w.message) for w in caught)
    return "status:     supported: 'bdpt render' will render it%s" % extra


def scene_info(args) -> list:
    path = scene_path(args.scene)
    mi = setup_variant(args.variant)
    params = scene_params(args)
    scene = load_scene(mi, path, params)
    check_sensor_index(scene, args.sensor)
    lines = ["scene:      %s%s" % (path, (" (%s)" % ", ".join(
        "%s=%s" % kv for kv in sorted(params.items()))) if params else ""), _variant_line(mi)]
    lines += _sensor_lines(scene, args.sensor) + _content_lines(scene)
    settings, integrator_name = integrator_defaults(scene)
    lines.append("integrator: %s in the file (bdpt renders instead%s)" % (
        integrator_name, ", with " + ", ".join("%s=%s" % kv for kv in sorted(settings.items()))
        if settings else ""))
    lines.append(_verdict(scene, args.sensor, settings))
    return lines


def _channel_order(name: str):
    layer, _, short = name.rpartition(".")
    return layer, "RGBAY".find(short) if short in "RGBAY" else 5, short


def image_info(name: str) -> list:
    """An EXR's size, channels and header (spp, seed, time, settings, scene), as
    pbrt's ``imgtool info`` shows them."""
    import numpy as np
    channels, meta = read_image(name)
    names = sorted(channels, key=_channel_order)
    top = [c for c in names if "." not in c]
    layers = sorted({c.rpartition(".")[0] for c in names if "." in c})
    h, w = channels[names[0]].shape[:2]
    bad = sum(int(np.size(v) - np.isfinite(v).sum()) for v in channels.values())
    rows = [("image", name), ("size", "%dx%d" % (w, h)), ("channels", ", ".join(top) or "-"),
            ("average", (", ".join("%s %.6g" % (c, float(np.nanmean(channels[c]))) for c in top)
                         or "-") + (", %d non-finite values" % bad if bad else ""))]
    if layers:
        rows.append(("layers", "%d (%s)" % (len(layers), ", ".join(layers))))
    if not meta:
        rows.append(("header", "nothing from bdpt (not written by 'bdpt render' or 'bdpt merge')"))
    keys = [k for k in _HEADER_ORDER if k in meta] + sorted(k for k in meta if k not in _HEADER_ORDER)
    rows += [(k, "%.6g" % meta[k] if isinstance(meta[k], float) else meta[k]) for k in keys]
    width = max(len(k) for k, _ in rows) + 2
    lines = ["%-*s%s" % (width, k + ":", v) for k, v in rows]
    return lines


def run(args, stop) -> int:
    is_image = args.scene is not None and Path(args.scene).suffix.lower() == ".exr"
    lines = image_info(args.scene) if is_image else scene_info(args)
    stop.check()
    print("\n".join(lines), flush=True)
    return 0
