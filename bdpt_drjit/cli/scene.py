"""What render and info share: the variant, the scene, its sensor, the renderer."""
from __future__ import annotations

import re
from pathlib import Path

from .args import DEFAULT_VARIANT
from .errors import CLIError, one_line


def default_scene() -> Path:
    return Path(__file__).resolve().parents[2] / "scenes" / "cornell-box.xml"


def scene_path(arg) -> Path:
    if arg is None:
        path = default_scene()
        if not path.is_file():
            raise CLIError("no scene given, and the default scene %s is missing" % path)
        return path
    path = Path(arg)
    if not path.exists():
        raise CLIError("scene file not found: %s" % arg)
    if not path.is_file():
        raise CLIError("scene path is not a file: %s" % arg)
    return path


def setup_variant(variant: str):
    """Select the Mitsuba variant (before any rendering) and check the LLVM library.
    bdpt_drjit registers "bdpt" for the new variant itself (a variant callback)."""
    from .. import _llvm
    _llvm.prepare()
    import mitsuba as mi
    available = list(mi.variants())
    if variant not in available:
        raise CLIError("unknown Mitsuba variant %r; available: %s" % (variant, ", ".join(available)))
    if not variant.startswith(("llvm_", "cuda_")):
        raise CLIError("variant %s is not a JIT variant; bdpt needs an llvm_* or cuda_* "
                       "variant (e.g. --variant %s)" % (variant, DEFAULT_VARIANT))
    try:
        mi.set_variant(variant)
    except ImportError as e:
        msg = one_line(e)
        if "LLVM" in msg:
            raise CLIError("cannot use variant %s: %s. %s" % (variant, msg.rstrip("."), _llvm.FIX)) from None
        if "CUDA" in msg:
            raise CLIError("cannot use variant %s: no usable CUDA GPU/driver (%s)"
                           % (variant, msg)) from None
        raise CLIError("cannot use variant %s: %s" % (variant, msg)) from None
    from ..render import check_variant
    try:
        check_variant()
    except RuntimeError as e:          # LLVMError included
        raise CLIError(one_line(e)) from None
    return mi


def scene_params(args) -> dict:
    params = dict(args.defines)
    if args.res:
        params["resx"], params["resy"] = str(args.res[0]), str(args.res[1])
    return params


def load_scene(mi, path: Path, params: dict):
    from ..support import load_file         # after the variant is set (variant())
    try:
        return load_file(path, **params)
    except Exception as e:  # Mitsuba raises RuntimeError for every parse problem
        unused = re.findall(r"\$(\w+)=", str(e)) if "unused parameters" in str(e) else []
        if unused:
            raise CLIError("scene %s has no parameter %s (set with -D/--res); only parameters "
                           "declared with <default name=...> or used as $name can be set"
                           % (path, ", ".join("$" + u for u in unused))) from None
        raise CLIError("cannot load scene %s: %s" % (path, one_line(e))) from None


def check_sensor_index(scene, index: int) -> None:
    count = len(scene.sensors())
    if count and index >= count:
        raise CLIError("--sensor %d: the scene has %d sensor%s (indices 0 to %d)"
                       % (index, count, "" if count == 1 else "s", count - 1), 2)


def integrator_defaults(scene) -> tuple[dict, str]:
    """Renderer settings the scene's own integrator asks for (max_depth, rr_depth, or
    everything if it is a ``bdpt`` integrator), and its description."""
    integ = scene.integrator()
    if integ is None:
        return {}, "none"
    settings = getattr(integ, "settings", None)
    if isinstance(settings, dict):
        return dict(settings), "vcm" if str(integ).startswith("VCM") else "bdpt"
    text = str(integ)
    out = {}
    m = re.search(r"\bmax_depth\s*=\s*(-?\d+)", text)
    if m and int(m.group(1)) >= -1:
        out["max_depth"] = int(m.group(1))
    m = re.search(r"\brr_depth\s*=\s*(\d+)", text)
    if m and int(m.group(1)) >= 1:
        out["rr_depth"] = int(m.group(1))
    return out, integ.class_name()


def make_renderer(scene, sensor, spp, seed, strategy_images, settings, unit_costs=None):
    from ..support import UnsupportedPluginError
    from ..render import Renderer
    try:
        return Renderer(scene, sensor=sensor, spp=spp, seed=seed,
                        strategy_images=strategy_images, unit_costs=unit_costs, **settings)
    except UnsupportedPluginError as e:
        raise CLIError("the scene uses an unsupported plugin: %s" % one_line(e)) from None
    except (ValueError, RuntimeError) as e:
        raise CLIError(one_line(e)) from None
