"""``bdpt info``: what the renderer sees in a scene, or what an image's header says."""
from __future__ import annotations

import warnings
from pathlib import Path

from .errors import CLIError, one_line
from .images import read_image
from .scene import (check_sensor_index, integrator_defaults, load_scene, make_renderer,
                    scene_params, scene_path, setup_variant)

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
    from ..support import plugin_name
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
    from ..support import describe
    bsdfs, kinds = set(), {}
    for shape in scene.shapes():
        kinds[shape.class_name()] = kinds.get(shape.class_name(), 0) + 1
        if shape.bsdf() is not None:
            bsdfs.add(describe(shape.bsdf()))
    return ["bsdfs:      %s" % (", ".join(sorted(bsdfs)) or "none"),
            "shapes:     %d (%s)" % (sum(kinds.values()), ", ".join(
                "%s x%d" % kv for kv in sorted(kinds.items())))]


def _verdict_lines(verdicts) -> list:
    """One line per scene element and what bdpt does with it (support.inspect, the
    checks 'bdpt render' runs); identical lines are counted, not repeated."""
    counts = {}
    for v in verdicts:
        counts[v] = counts.get(v, 0) + 1
    width = max(len(v.name) + (5 + len(str(n)) if n > 1 else 0) for v, n in counts.items())
    lines = ["elements:   what bdpt does with each"]
    for v, n in counts.items():
        name = v.name + (" (x%d)" % n if n > 1 else "")
        lines.append("  %-8s %-*s  %s%s" % (v.kind, width, name, v.status,
                                            ": " + v.reason if v.reason else ""))
    return lines


def _verdict(scene, sensor: int, settings: dict, verdicts) -> str:
    """The definitive answer: what constructing the renderer says (its refusal is
    the first REFUSED element above; settings are checked too)."""
    shown = {"bdpt: " + v.message() for v in verdicts}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:   # any unit costs: the verdict does not depend on them
            from ..units import UnitCosts
            make_renderer(scene, sensor, None, 0, False, settings, UnitCosts())
        except CLIError as e:
            return "status:     REFUSED: %s" % e
    extra = "".join("; warning: %s" % one_line(w.message) for w in caught
                    if str(w.message) not in shown)
    from ..support import WARNING
    notes = sum(v.status == WARNING for v in verdicts)
    return "status:     supported: 'bdpt render' will render it%s%s" % (
        " (%d warning%s above)" % (notes, "" if notes == 1 else "s") if notes else "", extra)


def scene_info(args) -> list:
    path = scene_path(args.scene)
    mi = setup_variant(args.variant)
    params = scene_params(args)
    scene = load_scene(mi, path, params)
    check_sensor_index(scene, args.sensor)
    lines = ["scene:      %s%s" % (path, (" (%s)" % ", ".join(
        "%s=%s" % kv for kv in sorted(params.items()))) if params else ""), _variant_line(mi)]
    from ..support import inspect
    verdicts = inspect(scene, scene.sensors()[args.sensor]) if scene.sensors() else []
    lines += _sensor_lines(scene, args.sensor) + _verdict_lines(verdicts) + _content_lines(scene)
    settings, integrator_name = integrator_defaults(scene)
    lines.append("integrator: %s in the file (bdpt renders instead%s)" % (
        integrator_name, ", with " + ", ".join("%s=%s" % kv for kv in sorted(settings.items()))
        if settings else ""))
    lines += _merging_lines(scene, settings)
    lines.append(_units_line(mi.variant()))
    lines.append(_verdict(scene, args.sensor, settings, verdicts))
    return lines


def _units_line(variant: str) -> str:
    """The unit costs an "auto" budget's decision prices its counts with (units.py)."""
    from .. import units
    found = units.load(variant)
    if found is None:
        return ("units:      not measured yet for %s: the first 'auto' render measures them "
                "(or 'bdpt calibrate'), into %s" % (variant, units.path(variant)))
    return "units:      %s (%s)" % (found.describe(), units.path(variant))


def _merging_lines(scene, settings: dict) -> list:
    """What vertex merging (merge.py) will do, where the integrator asks for it."""
    if not (settings.get("merging") or settings.get("strategy_subset") == "ppm") \
            or not scene.sensors():
        return []
    from ..merge import first_radius
    from ..settings import Settings
    try:
        s = Settings.from_dict(settings)
    except ValueError:
        return []            # the verdict line says why
    from ..media import Media
    try:
        media = bool(scene.sensors()) and Media(scene, scene.sensors()[0]).present
    except Exception:       # noqa: BLE001  (the verdict line reports a refused medium)
        media = False
    auto = "auto" in (s.light_paths, s.connections) and s.strategy_subset == "all"
    return ["merging:    on (vertex connection and merging): consistent, not unbiased; "
            "radius r_1 = %.4g, alpha %g" % (first_radius(scene, scene.sensors()[0], s.radius), s.radius_alpha)
            + ("; budgets auto: the pilot keeps merging only where it pays" if auto else "")
            + ("; medium vertices connect but do not merge" if media else
               "; (medium vertices would connect but not merge)")]


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
