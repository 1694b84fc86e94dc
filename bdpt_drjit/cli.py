"""The ``bdpt`` command line: render, merge and inspect scenes.

    bdpt render [SCENE.xml] [-o out.exr] [--spp N] [--max-depth N] [--seed N]
                [--time SECONDS] [--checkpoint SECONDS] [--res WxH] [-D key=value ...]
                [--variant llvm_ad_rgb] [--mis power|balance|uniform] [--rr-depth N]
                [--technique s,t] [--strategy-set all|pt|lt] [--no-light-image] [--hide-emitters]
                [--samples-per-pass N] [--strategies] [--quiet]
    bdpt merge a.exr b.exr ... -o out.exr
    bdpt info [SCENE.xml] [-D key=value ...]

``python -m bdpt_drjit ...`` is the same command.  ``bdpt SCENE.xml ...`` is short
for ``bdpt render SCENE.xml ...``.

Rendering is progressive: the renderer works in passes, and the command stops
cleanly after the current pass on Ctrl-C (SIGINT) or SIGTERM, or once the
``--time`` budget is used up, and writes the image of the passes done.  The EXR
header records what the image is: ``spp`` (int), ``seed``, ``passes``,
``render_time``, ``scene``, ``bdpt_version`` and the settings, so that ``bdpt
merge`` can combine independent renders (different seeds) weighted by their spp.
Files are replaced atomically, so an interrupted write never leaves a broken file.

Errors in the input (missing or malformed scene, unsupported plugins, bad
options, an unwritable output, no usable LLVM) are reported as one line on
stderr with a non-zero exit status; set ``BDPT_DEBUG=1`` for a traceback.
"""
from __future__ import annotations

import argparse
import math
import os
import re
import signal
import sys
import tempfile
import time
import warnings
from pathlib import Path

PROG = "bdpt"
DEFAULT_VARIANT = "llvm_ad_rgb"
COMMANDS = ("render", "merge", "info")
# With --time or --checkpoint and no --samples-per-pass, passes are kept small
# (at most spp/16 samples per pixel and about this many lanes, fewer on the CPU
# where a lane costs more) so there are many.
_TIMED_PASS_LANES = {"llvm": 1 << 16, "cuda": 1 << 20}
_SUPPORTED_EMITTERS = {"AreaLight": "area", "PointLight": "point", "SpotLight": "spot",
                       "ConstantBackgroundEmitter": "constant", "EnvironmentMapEmitter": "envmap",
                       "DirectionalEmitter": "directional"}
_SUPPORTED_SENSORS = {"PerspectiveCamera": "perspective"}
_BSDF_NAMES = {
    "SmoothDiffuse": "diffuse", "TwoSidedBRDF": "twosided", "SmoothDielectric": "dielectric",
    "ThinDielectric": "thindielectric", "RoughDielectric": "roughdielectric",
    "SmoothConductor": "conductor", "RoughConductor": "roughconductor",
    "SmoothPlastic": "plastic", "RoughPlastic": "roughplastic", "Principled": "principled",
    "PrincipledThinBSDF": "principledthin", "BlendBSDF": "blendbsdf", "MaskBSDF": "mask",
    "NullBSDF": "null", "BumpMap": "bumpmap", "NormalMap": "normalmap",
    "HairBSDF": "hair", "Polarizer": "polarizer", "Retarder": "retarder",
    "MeasuredBSDF": "measured", "PPLastic": "pplastic"}
_SENSOR_NAMES = {"PerspectiveCamera": "perspective", "ThinLensCamera": "thinlens",
                 "OrthographicCamera": "orthographic", "RadianceMeter": "radiancemeter",
                 "IrradianceMeter": "irradiancemeter", "DistantSensor": "distant",
                 "BatchSensor": "batch"}


class CLIError(Exception):
    """A problem with the user's input: reported as one line, exit status ``code``."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage dump)."""

    def error(self, message):
        raise CLIError("%s: %s (see '%s --help')" % (self.prog, message, self.prog), 2)


# -- small helpers ---------------------------------------------------------------
def _one_line(exc_or_text) -> str:
    """An exception's message on one line, without 'bdpt: ' or '[file.cpp:123] '."""
    text = str(exc_or_text)
    text = re.sub(r"\[[\w./-]+\.(?:cpp|h|py):\d+\]\s*", "", text)
    text = re.sub(r"\s*\n\s*-?\s*", "; ", text.strip())
    text = re.sub(r"^(bdpt:\s*)+", "", text)
    text = re.sub(r"\s+", " ", text)
    return text.strip("; ") or exc_or_text.__class__.__name__


def _eprint(*parts) -> None:
    print(*parts, file=sys.stderr, flush=True)


def _fmt_time(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    if seconds < 60:
        return "%.1f s" % seconds
    if seconds < 3600:
        return "%dm%02ds" % divmod(int(round(seconds)), 60)
    h, rest = divmod(int(round(seconds)), 3600)
    return "%dh%02dm" % (h, rest // 60)


def _fmt_rate(x: float) -> str:
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= scale:
            return "%.3g %s" % (x / scale, unit)
    return "%.3g " % x


def _int_arg(lowest: int, expected: str, bound: str):
    """An argparse type: an integer >= ``lowest``; the two messages name the rule."""
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError("expected %s, got %r" % (expected, text)) from None
        if v < lowest:
            raise argparse.ArgumentTypeError("must be %s, got %d" % (bound, v))
        return v
    return parse


_positive_int = _int_arg(1, "a positive integer", "a positive integer")
_nonneg_int = _int_arg(0, "an integer >= 0", ">= 0")
_max_depth = _int_arg(-1, "an integer", "-1 (unbounded) or >= 0")


def _positive_float(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError("expected a number of seconds, got %r" % text) from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError("must be a positive number of seconds, got %s" % text)
    return v


def _resolution(text):
    m = re.fullmatch(r"\s*(\d+)\s*[xX,]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise argparse.ArgumentTypeError("expected WIDTHxHEIGHT (e.g. 640x480), got %r" % text)
    return int(m.group(1)), int(m.group(2))


def _define(text):
    key, sep, value = text.partition("=")
    key = key.strip().lstrip("$")
    if not sep or not re.fullmatch(r"[A-Za-z_][\w]*", key):
        raise argparse.ArgumentTypeError("expected key=value (a scene parameter), got %r" % text)
    return key, value.strip()


def _technique(text):
    m = re.fullmatch(r"\s*\(?\s*(\d+)\s*,\s*(\d+)\s*\)?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError("expected s,t (e.g. 1,2), got %r" % text)
    s, t = int(m.group(1)), int(m.group(2))
    if t < 1:
        raise argparse.ArgumentTypeError("needs t >= 1 (there is no t = 0 strategy), got %s" % text)
    return s, t


# -- argument parsing --------------------------------------------------------------
def _add_scene_options(p) -> None:
    p.add_argument("-D", dest="defines", action="append", type=_define, default=[],
                   metavar="KEY=VALUE",
                   help="set a scene parameter ($KEY in the XML), e.g. -D resx=64; repeatable")
    p.add_argument("--res", type=_resolution, metavar="WxH",
                   help="film size: sets the scene parameters resx and resy")
    p.add_argument("--variant", default=DEFAULT_VARIANT,
                   help="Mitsuba variant (a JIT one: llvm_* or cuda_*; default %(default)s)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROG, description="Wavefront bidirectional path tracer "
                     "(Dr.Jit / Mitsuba 3).")
    from . import __version__
    parser.add_argument("--version", action="version", version="%(prog)s " + __version__)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    r = sub.add_parser("render", help="render a scene to OpenEXR (+ PNG preview)",
                       description="Render a Mitsuba XML scene with BDPT. Writes OUT.exr "
                       "(float32 RGB, spp and seed in the header) and a tone-mapped "
                       "sRGB preview OUT.png. Ctrl-C stops after the current pass and "
                       "writes what was rendered.")
    r.add_argument("scene", nargs="?", help="scene XML file (default: the Cornell box in scenes/)")
    r.add_argument("-o", "--output", metavar="OUT.exr",
                   help="output EXR (default: <scene name>.exr in the current directory)")
    r.add_argument("--spp", type=_positive_int, help="samples per pixel (default: the scene's sampler)")
    r.add_argument("--max-depth", type=_max_depth, metavar="N",
                   help="longest path in edges, -1 = unbounded (default: the scene's "
                        "integrator max_depth, else -1)")
    r.add_argument("--rr-depth", type=_positive_int, metavar="N",
                   help="subpath vertex where Russian roulette starts (default 5)")
    r.add_argument("--seed", type=_nonneg_int, default=0, help="random seed (default 0)")
    r.add_argument("--mis", choices=("power", "balance", "uniform", "lafortune"),
                   help="MIS heuristic (default power)")
    r.add_argument("--strategy-set", dest="strategy_set", choices=("all", "pt", "lt"),
                   help="strategy subset: all (default), pt (path tracing + NEE), lt (light tracing)")
    r.add_argument("--technique", type=_technique, metavar="s,t",
                   help="render only strategy (s,t), unweighted")
    r.add_argument("--no-light-image", dest="light_image", action="store_false", default=None,
                   help="leave out the light-tracing (t=1) strategies")
    r.add_argument("--hide-emitters", action="store_true", default=None,
                   help="hide emitters seen directly by the camera")
    r.add_argument("--samples-per-pass", type=_nonneg_int, metavar="N",
                   help="spp per pass (0 = as many as fit the memory budget; with --time "
                        "or --checkpoint the default is small, about spp/16)")
    r.add_argument("--time", type=_positive_float, metavar="SECONDS",
                   help="time budget: stop after the pass that crosses it")
    r.add_argument("--checkpoint", type=_positive_float, metavar="SECONDS",
                   help="rewrite the output every SECONDS while rendering")
    r.add_argument("--strategies", action="store_true",
                   help="also write every (s,t) strategy: OUT.strategies.exr (layers "
                        "s<s>t<t>.R/G/B) and OUT.strategies.png (rows: path length k = "
                        "s+t-1, columns: s)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    _add_scene_options(r)
    r.set_defaults(func=cmd_render)

    m = sub.add_parser("merge", help="combine renders made with different seeds",
                       description="Average EXR renders of the same scene made with "
                       "different seeds, weighted by their spp (from the header).")
    m.add_argument("inputs", nargs="+", metavar="IN.exr")
    m.add_argument("-o", "--output", required=True, metavar="OUT.exr")
    m.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    m.set_defaults(func=cmd_merge)

    i = sub.add_parser("info", help="what the renderer sees in a scene",
                       description="List a scene's sensor, film, emitters and BSDFs, and "
                       "whether bdpt can render it (and if not, why).")
    i.add_argument("scene", nargs="?", help="scene XML file (default: the Cornell box)")
    _add_scene_options(i)
    i.set_defaults(func=cmd_info)
    return parser


def parse_args(argv):
    argv = list(argv)
    # `bdpt scene.xml ...` is `bdpt render scene.xml ...`.
    if argv and argv[0] not in COMMANDS and not argv[0].startswith("-"):
        argv = ["render"] + argv
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        raise CLIError("no command given (render, merge or info)", 2)
    return args


# -- scene, variant and output checks ---------------------------------------------------
def default_scene() -> Path:
    import bdpt_drjit
    return Path(bdpt_drjit.__file__).resolve().parent.parent / "scenes" / "cornell-box.xml"


def _scene_path(arg) -> Path:
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


def _check_writable(paths) -> None:
    """Fail now, before rendering, if any output cannot be written."""
    checked = set()
    for path in paths:
        path = Path(path)
        if path.is_dir():
            raise CLIError("cannot write %s: it is a directory" % path)
        parent = path.parent
        if parent in checked:
            continue
        if not parent.exists():
            raise CLIError("cannot write %s: directory %s does not exist" % (path, parent))
        if not parent.is_dir():
            raise CLIError("cannot write %s: %s is not a directory" % (path, parent))
        try:
            fd, tmp = tempfile.mkstemp(prefix=".bdpt-write-test.", dir=parent)
            os.close(fd)
            os.unlink(tmp)
        except OSError as e:
            raise CLIError("cannot write %s: %s" % (path, e.strerror or e)) from None
        checked.add(parent)


def _output_path(arg, scene: Path) -> Path:
    out = Path(arg) if arg else Path.cwd() / (scene.stem + ".exr")
    if out.suffix == "":
        out = out.with_name(out.name + ".exr")
    if out.suffix.lower() != ".exr":
        raise CLIError("output %s must be an OpenEXR file ending in .exr (a PNG preview "
                       "is written beside it)" % out)
    return out


def setup_variant(variant: str):
    """Select the Mitsuba variant (before any rendering) and check the LLVM library."""
    from . import _llvm
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
        msg = _one_line(e)
        if "LLVM" in msg:
            raise CLIError("cannot use variant %s: %s. %s" % (variant, msg.rstrip("."), _llvm.FIX)) from None
        if "CUDA" in msg:
            raise CLIError("cannot use variant %s: no usable CUDA GPU/driver (%s)"
                           % (variant, msg)) from None
        raise CLIError("cannot use variant %s: %s" % (variant, msg)) from None
    from .render import check_variant
    try:
        check_variant()
    except _llvm.LLVMError as e:
        raise CLIError(_one_line(e)) from None
    except RuntimeError as e:
        raise CLIError(_one_line(e)) from None
    import bdpt_drjit
    bdpt_drjit.register()          # the "bdpt" integrator, for this variant
    return mi


def _scene_params(args) -> dict:
    params = dict(args.defines)
    if args.res:
        params["resx"], params["resy"] = str(args.res[0]), str(args.res[1])
    return params


def load_scene(mi, path: Path, params: dict):
    try:
        return mi.load_file(str(path), **params)
    except Exception as e:  # Mitsuba raises RuntimeError for every parse problem
        msg = _one_line(e)
        unused = re.findall(r"\$(\w+)=", str(e)) if "unused parameters" in str(e) else []
        if unused:
            raise CLIError("scene %s has no parameter %s (set with -D/--res); only parameters "
                           "declared with <default name=...> or used as $name can be set"
                           % (path, ", ".join("$" + u for u in unused))) from None
        raise CLIError("cannot load scene %s: %s" % (path, msg)) from None


def _integrator_defaults(scene) -> tuple[dict, str]:
    """Renderer settings the scene's own integrator asks for (max_depth, rr_depth, or
    everything if it is a ``bdpt`` integrator), and its description."""
    integ = scene.integrator()
    if integ is None:
        return {}, "none"
    settings = getattr(integ, "settings", None)
    if isinstance(settings, dict):
        return dict(settings), "bdpt"
    text = str(integ)
    out = {}
    m = re.search(r"\bmax_depth\s*=\s*(-?\d+)", text)
    if m and int(m.group(1)) >= -1:
        out["max_depth"] = int(m.group(1))
    m = re.search(r"\brr_depth\s*=\s*(\d+)", text)
    if m and int(m.group(1)) >= 1:
        out["rr_depth"] = int(m.group(1))
    return out, integ.class_name()


def _make_renderer(scene, spp, seed, strategy_images, settings):
    from .emitters import UnsupportedPluginError
    from .render import Renderer
    try:
        return Renderer(scene, spp=spp, seed=seed, strategy_images=strategy_images, **settings)
    except UnsupportedPluginError as e:
        raise CLIError("the scene uses an unsupported plugin: %s" % _one_line(e)) from None
    except (ValueError, RuntimeError) as e:
        raise CLIError(_one_line(e)) from None


# -- images ---------------------------------------------------------------------------
def tonemap(image) -> "np.ndarray":
    """Linear HDR (H, W, C) -> 8-bit sRGB (H, W, 3): clip to [0, 1], sRGB curve."""
    import numpy as np
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    a = a[:, :, :3] if a.shape[2] >= 3 else np.repeat(a[:, :, :1], 3, axis=2)
    a = np.clip(np.nan_to_num(a, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    srgb = np.where(a <= 0.0031308, 12.92 * a, 1.055 * np.power(a, 1 / 2.4) - 0.055)
    return np.clip(srgb * 255.0 + 0.5, 0, 255).astype(np.uint8)


def write_png(path, rgb8) -> None:
    """Write an (H, W, 3) uint8 sRGB array as PNG, atomically."""
    import mitsuba as mi
    import numpy as np
    from .exr import atomic_path
    with atomic_path(path) as tmp:
        mi.Bitmap(np.ascontiguousarray(rgb8)).write(tmp, mi.Bitmap.FileFormat.PNG)


def contact_sheet(strategies: dict, gap: int = 2) -> "np.ndarray":
    """Tone-mapped strategy images on a grid: row k = s + t - 1, column s."""
    import numpy as np
    if not strategies:
        raise ValueError("no strategy images")
    h, w = next(iter(strategies.values())).shape[:2]
    kmax = max(s + t - 1 for s, t in strategies)
    smax = max(s for s, _ in strategies)
    rows, cols = kmax, smax + 1
    sheet = np.full((gap + rows * (h + gap), gap + cols * (w + gap), 3), 48, np.uint8)
    for (s, t), img in strategies.items():
        k = s + t - 1
        if k < 1:
            continue
        y, x = gap + (k - 1) * (h + gap), gap + s * (w + gap)
        sheet[y:y + h, x:x + w] = tonemap(img)
    return sheet


# -- progress ----------------------------------------------------------------------------
class Progress:
    """A progress bar on stderr: redrawn in place on a terminal, a line every few
    seconds otherwise (the first one right after the first pass)."""

    def __init__(self, renderer, budget=None, enabled=True, stream=None):
        self.r = renderer
        self.budget = budget
        self.stream = stream or sys.stderr
        self.enabled = enabled and len(renderer.plan) > 1
        self.tty = self.enabled and self.stream.isatty()
        self.last = None
        self.first_pass = None
        self.drawn = False

    def line(self, elapsed: float) -> str:
        r = self.r
        total = len(r.plan)
        frac = r.passes_done / total
        width = 24
        fill = int(round(frac * width))
        rate = r.spp_done * r.pixels / elapsed if elapsed > 0 else 0.0
        if r.passes_done >= 2 and self.first_pass is not None:
            per_pass = (elapsed - self.first_pass) / (r.passes_done - 1)
        else:
            per_pass = elapsed / max(1, r.passes_done)
        left = per_pass * (total - r.passes_done)
        if self.budget is not None:
            left = min(left, max(0.0, self.budget - elapsed))
        return ("[%s%s] %d/%d passes, %d/%d spp, %ssamples/s, %s left"
                % ("#" * fill, "-" * (width - fill), r.passes_done, total, r.spp_done,
                   r.spp, _fmt_rate(rate), _fmt_time(left)))

    def update(self, elapsed: float) -> None:
        if self.first_pass is None:
            self.first_pass = elapsed
        if not self.enabled:
            return
        if self.tty:
            interval = 0.1
        else:
            interval = max(1.0, min(30.0, elapsed / 10))
        if self.last is not None and elapsed - self.last < interval and not self.r.done:
            return
        self.last = elapsed
        text = "bdpt: " + self.line(elapsed)
        if self.tty:
            self.stream.write("\r" + text + "\033[K")
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
        self.drawn = True

    def finish(self) -> None:
        if self.tty and self.drawn:
            self.stream.write("\n")
            self.stream.flush()
        self.drawn = False


class _StopRequest:
    """SIGINT/SIGTERM handlers that ask the render loop to stop after this pass; a
    second signal aborts at once (KeyboardInterrupt), writing nothing more."""

    def __init__(self, announce=True):
        self.signal = None
        self.announce = announce
        self._old = {}

    def _handler(self, signum, frame):
        if self.signal is not None:
            raise KeyboardInterrupt
        self.signal = signum
        if self.announce:
            _eprint("\nbdpt: %s: stopping after the current pass (again to abort)"
                    % signal.Signals(signum).name)

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old[sig] = signal.signal(sig, self._handler)
            except (ValueError, OSError):    # not the main thread
                pass
        return self

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            signal.signal(sig, old)
        return False


# -- commands -------------------------------------------------------------------------------
def cmd_render(args) -> int:
    import numpy as np

    scene_path = _scene_path(args.scene)
    out = _output_path(args.output, scene_path)
    png = out.with_suffix(".png")
    outputs = [out, png]
    if args.strategies:
        outputs += [out.with_suffix(".strategies.exr"), out.with_suffix(".strategies.png")]
    _check_writable(outputs)

    mi = setup_variant(args.variant)
    params = _scene_params(args)
    scene = load_scene(mi, scene_path, params)

    settings, _ = _integrator_defaults(scene)
    chose_pass_size = args.samples_per_pass is not None or "samples_per_pass" in settings
    cli_settings = {"max_depth": args.max_depth, "rr_depth": args.rr_depth, "mis": args.mis,
                    "technique": args.technique, "light_image": args.light_image,
                    "hide_emitters": args.hide_emitters, "strategy_subset": args.strategy_set,
                    "samples_per_pass": args.samples_per_pass}
    settings.update({k: v for k, v in cli_settings.items() if v is not None})
    settings.setdefault("samples_per_pass", 0)
    timed = args.time is not None or args.checkpoint is not None

    renderer = _make_renderer(scene, args.spp, args.seed, args.strategies, settings)
    if timed and not chose_pass_size and renderer.plan[0][1] == renderer.pixels:
        # Many small passes, so that the budget and checkpoints are honoured closely;
        # never more per pass than the memory budget allows.
        auto = renderer.plan[0][2]
        per_pass = max(1, min(renderer.spp // 16, auto,
                              _TIMED_PASS_LANES[args.variant.split("_")[0]] // renderer.pixels))
        if per_pass != auto:
            settings["samples_per_pass"] = per_pass
            renderer = _make_renderer(scene, args.spp, args.seed, args.strategies, settings)

    from . import __version__
    technique = renderer.settings.technique
    film_size = tuple(int(x) for x in renderer.sensor.film().crop_size())
    meta = {"spp": 0, "seed": args.seed, "bdpt_version": __version__,
            "scene": str(scene_path.resolve()),
            "scene_params": ",".join("%s=%s" % kv for kv in sorted(params.items())),
            "passes": 0, "render_time": 0.0, "variant": args.variant,
            "spp_requested": renderer.spp,
            "max_depth": renderer.settings.max_depth, "rr_depth": renderer.settings.rr_depth,
            "mis": renderer.settings.mis, "light_image": int(renderer.settings.light_image),
            "hide_emitters": int(renderer.settings.hide_emitters),
            "technique": "all" if technique is None else "%d,%d" % technique,
            "samples_per_pass": renderer.plan[0][2]}

    def write_outputs():
        res = renderer.result()
        meta.update(spp=res.spp, passes=res.passes, render_time=float(res.time))
        from .exr import write_exr, write_layers
        write_exr(out, res.image, meta)
        write_png(png, tonemap(res.image))
        if args.strategies:
            layers = {"s%dt%d" % st: img for st, img in sorted(res.strategies.items())}
            write_layers(out.with_suffix(".strategies.exr"), layers, meta, image=res.image)
            if res.strategies:
                write_png(out.with_suffix(".strategies.png"), contact_sheet(res.strategies))
        return res

    if not args.quiet:
        depth = renderer.settings.max_depth
        _eprint("bdpt: rendering %s (%dx%d, %d spp in %d pass%s, max_depth %s%s, seed %d, %s)"
                % (scene_path.name, film_size[0], film_size[1], renderer.spp,
                   len(renderer.plan), "" if len(renderer.plan) == 1 else "es",
                   "unbounded" if depth < 0 else depth,
                   "" if technique is None else ", technique %d,%d" % technique,
                   args.seed, args.variant))

    progress = Progress(renderer, budget=args.time, enabled=not args.quiet)
    stop_reason = None
    with _StopRequest(announce=not args.quiet) as stop:
        t0 = time.perf_counter()
        last_checkpoint = t0
        while not renderer.done:
            renderer.run_pass()
            now = time.perf_counter()
            progress.update(now - t0)
            if stop.signal is not None and not renderer.done:
                stop_reason = "interrupted"
                break
            if args.time is not None and now - t0 >= args.time and not renderer.done:
                stop_reason = "time"
                break
            if (args.checkpoint is not None and not renderer.done
                    and now - last_checkpoint >= args.checkpoint):
                write_outputs()
                last_checkpoint = time.perf_counter()
        wall = time.perf_counter() - t0
        progress.finish()
        res = write_outputs()

    if not np.all(np.isfinite(res.image)):
        _eprint("bdpt: warning: the image has %d non-finite values"
                % int(np.size(res.image) - np.isfinite(res.image).sum()))
    written = [str(out), str(png)]
    if args.strategies:
        written += [str(out.with_suffix(".strategies.exr")), str(out.with_suffix(".strategies.png"))]
    if stop_reason == "interrupted":
        _eprint("bdpt: interrupted (%s) after %d of %d spp (%d of %d passes); wrote the "
                "image of the passes done" % (signal.Signals(stop.signal).name, res.spp,
                                              renderer.spp, res.passes, len(renderer.plan)))
    elif stop_reason == "time":
        _eprint("bdpt: time budget of %s used up after %d of %d spp"
                % (_fmt_time(args.time), res.spp, renderer.spp))
    rate = res.spp * renderer.pixels / wall if wall > 0 else 0.0
    print("bdpt: %dx%d, %d spp (%d pass%s) in %s, %ssamples/s -> %s"
          % (film_size[0], film_size[1], res.spp, res.passes, "" if res.passes == 1 else "es",
             _fmt_time(wall), _fmt_rate(rate),
             ", ".join(written)), flush=True)
    return 0


def _seeds(value) -> list:
    """The seeds an image was rendered with (an int, or a list written by merge)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return [int(value)]
    out = []
    for part in re.split(r"[,\s]+", str(value).strip("[]() ")):
        if part:
            out.append(int(part) if re.fullmatch(r"-?\d+", part) else part)
    return out


def cmd_merge(args) -> int:
    import numpy as np
    from .exr import read_channels, write_channels

    if len(args.inputs) < 2:
        raise CLIError("merge needs at least two images")
    out = _output_path(args.output, Path("merged"))
    png = out.with_suffix(".png")
    _check_writable([out, png])

    images = []
    for name in args.inputs:
        path = Path(name)
        if not path.is_file():
            raise CLIError("image not found: %s" % name)
        try:
            channels, meta = read_channels(path)
        except Exception as e:
            raise CLIError("cannot read %s as OpenEXR: %s" % (name, _one_line(e))) from None
        spp = meta.get("spp")
        if not isinstance(spp, int) or isinstance(spp, bool) or spp <= 0:
            raise CLIError("%s has no spp in its header (not written by 'bdpt render'?); "
                           "cannot weight it" % name)
        if "seed" not in meta:
            raise CLIError("%s has no seed in its header; cannot check that the renders "
                           "are independent" % name)
        images.append((name, channels, meta, spp, _seeds(meta["seed"])))

    name0, ch0, meta0, _, _ = images[0]
    shape0 = next(iter(ch0.values())).shape
    for name, ch, meta, _, _ in images[1:]:
        shape = next(iter(ch.values())).shape
        if shape != shape0:
            raise CLIError("cannot merge images of different sizes: %s is %dx%d, %s is %dx%d"
                           % (name0, shape0[1], shape0[0], name, shape[1], shape[0]))
        if set(ch) != set(ch0):
            raise CLIError("cannot merge: %s has channels %s, %s has %s"
                           % (name0, ",".join(sorted(ch0)), name, ",".join(sorted(ch))))
    seen = {}
    for name, _, _, _, seeds in images:
        for s in seeds:
            if s in seen:
                raise CLIError("cannot merge %s and %s: both were rendered with seed %s, so "
                               "their noise is identical (render again with another --seed)"
                               % (seen[s], name, s))
            seen[s] = name
    for key in ("scene", "scene_params", "max_depth", "technique", "mis", "light_image",
                "hide_emitters", "variant"):
        values = {str(m.get(key)) for _, _, m, _, _ in images if key in m}
        if len(values) > 1 and not args.quiet:
            _eprint("bdpt: warning: the images differ in %s (%s); merging anyway"
                    % (key, ", ".join(sorted(values))))

    total = sum(spp for *_, spp, _ in images)
    merged = {}
    for c in ch0:
        acc = np.zeros(shape0, np.float64)
        for _, ch, _, spp, _ in images:
            acc += spp * ch[c].astype(np.float64)
        merged[c] = (acc / total).astype(np.float32)

    meta = {k: v for k, v in meta0.items()}
    all_seeds = [s for *_, seeds in images for s in seeds]
    meta.update(spp=total, seed=",".join(str(s) for s in all_seeds),
                passes=sum(int(m.get("passes", 0)) for _, _, m, _, _ in images),
                render_time=float(sum(float(m.get("render_time", 0.0)) for _, _, m, _, _ in images)),
                merged_from=len(images))
    meta.pop("spp_requested", None)
    write_channels(out, merged, meta)
    wrote = [str(out)]
    top = {c: v for c, v in merged.items() if "." not in c}
    if top:
        from .exr import assemble_channels
        write_png(png, tonemap(assemble_channels(top)))
        wrote.append(str(png))
    if not args.quiet:
        print("bdpt: merged %d images (%s spp = %d spp, seeds %s) -> %s"
              % (len(images), " + ".join(str(spp) for *_, spp, _ in images), total,
                 meta["seed"], ", ".join(wrote)), flush=True)
    return 0


def cmd_info(args) -> int:
    scene_path = _scene_path(args.scene)
    mi = setup_variant(args.variant)
    params = _scene_params(args)
    scene = load_scene(mi, scene_path, params)
    from .emitters import plugin_name

    lines = ["scene:      %s%s" % (scene_path, (" (%s)" % ", ".join(
        "%s=%s" % kv for kv in sorted(params.items()))) if params else "")]
    variant = mi.variant()
    if variant.startswith("llvm_"):
        import drjit as dr
        try:
            variant += " (LLVM %s)" % ".".join(map(str, dr.detail.llvm_version()))
        except Exception:
            pass
    lines.append("variant:    %s" % variant)
    problems = []

    sensors = scene.sensors()
    if not sensors:
        lines.append("sensor:     none  [refused: the scene has no sensor]")
        problems.append("the scene has no sensor")
    for i, sensor in enumerate(sensors):
        cls = sensor.class_name()
        name = _SENSOR_NAMES.get(cls, cls)
        film = sensor.film()
        size = tuple(int(x) for x in film.size())
        crop = tuple(int(x) for x in film.crop_size())
        sampler = sensor.sampler()
        ok = cls in _SUPPORTED_SENSORS
        note = ("" if ok or i > 0 else
                "  [refused: only 'perspective' (pinhole) sensors are supported]")
        if i > 0:
            note = "  [not rendered: bdpt renders the first sensor]"
        lines.append("sensor:     %s%s" % (name, note))
        lines.append("film:       %s %dx%d%s, %s filter" % (
            film.class_name(), size[0], size[1],
            "" if crop == size else " (crop %dx%d)" % crop,
            film.rfilter().class_name()))
        lines.append("sampler:    %s, %d spp" % (sampler.class_name(), sampler.sample_count()))
        if not ok and i == 0:
            problems.append("sensor plugin '%s' is not supported" % name)

    emitters = scene.emitters()
    if not emitters:
        lines.append("emitters:   none  [warning: the image will be black]")
    for e in emitters:
        name = plugin_name(e)
        ok = e.class_name() in _SUPPORTED_EMITTERS
        lines.append("emitter:    %s%s" % (name, "" if ok else
                                            "  [refused: supported: area, point, spot, constant, envmap, directional]"))
        if not ok:
            problems.append("emitter plugin '%s' is not supported" % name)

    bsdfs = {}
    shapes = scene.shapes()
    for shape in shapes:
        b = shape.bsdf()
        if b is None:
            continue
        cls = b.class_name()
        label = _BSDF_NAMES.get(cls, cls)
        ident = b.id()
        key = (label, ident)
        bsdfs[key] = bsdfs.get(key, 0) + 1
    lines.append("bsdfs:      %s" % (", ".join(
        "%s%s" % (label, " '%s'" % ident if ident and not ident.startswith("_unnamed") else "")
        for (label, ident) in sorted(bsdfs)) or "none"))
    shape_kinds = {}
    for shape in shapes:
        shape_kinds[shape.class_name()] = shape_kinds.get(shape.class_name(), 0) + 1
    lines.append("shapes:     %d (%s)" % (len(shapes), ", ".join(
        "%s x%d" % kv for kv in sorted(shape_kinds.items()))))
    settings, integrator_name = _integrator_defaults(scene)
    lines.append("integrator: %s in the file (bdpt renders instead%s)" % (
        integrator_name, ", with " + ", ".join("%s=%s" % kv for kv in sorted(settings.items()))
        if settings else ""))

    # The definitive answer: what constructing the renderer says.
    verdict = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            _make_renderer(scene, None, 0, False, settings)
        except CLIError as e:
            verdict = str(e)
    if verdict is None and problems:
        verdict = "; ".join(problems)
    if verdict:
        lines.append("status:     REFUSED: %s" % verdict)
    else:
        extra = "".join("; warning: %s" % _one_line(w.message) for w in caught)
        lines.append("status:     supported: 'bdpt render' will render it%s" % extra)
    print("\n".join(lines), flush=True)
    return 0


# -- entry point ----------------------------------------------------------------------------
def _showwarning(message, category, filename, lineno, file=None, line=None):
    _eprint("bdpt: warning: %s" % _one_line(message))


def main(argv=None) -> int:
    """Run the command line; returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    old_showwarning = warnings.showwarning
    warnings.showwarning = _showwarning
    try:
        args = parse_args(argv)
        return args.func(args)
    except CLIError as e:
        _eprint("bdpt: error: %s" % e)
        return e.code
    except KeyboardInterrupt:
        _eprint("\nbdpt: aborted; nothing more was written")
        return 130
    except BrokenPipeError:
        return 1
    except Exception as e:
        if os.environ.get("BDPT_DEBUG"):
            raise
        _eprint("bdpt: error: %s: %s (set BDPT_DEBUG=1 for a traceback)"
                % (type(e).__name__, _one_line(e)))
        return 1
    finally:
        warnings.showwarning = old_showwarning


if __name__ == "__main__":
    sys.exit(main())
