"""The command line's parser.  The renderer's options come from
``bdpt_drjit.settings.PARAMS``: names, choices, bounds and help are declared there."""
from __future__ import annotations

import argparse
import math
import re
import sys

from .. import DEFAULT_VARIANT
from ..settings import MIN_MEMORY_BUDGET, PARAMS, Param
from .errors import CLIError, eprint

PROG = "bdpt"
COMMANDS = ("render", "mlt", "merge", "info", "calibrate")
# Old spellings that still work, with a warning: the names were overloaded.
RENAMED_OPTIONS = {"--strategy-set": "--strategy-subset", "--strategies": "--strategy-images"}


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage dump)."""

    def error(self, message):
        raise CLIError("%s: %s (see '%s --help')" % (self.prog, message, self.prog), 2)


class _Renamed(argparse.Action):
    """An old option spelling: does what the new one does, with a one-line warning."""

    def __init__(self, option_strings, dest, new=None, **kwargs):
        self.new = new
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        eprint("bdpt: warning: %s is deprecated; use %s" % (option_string, self.new))
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)


# -- value parsers ---------------------------------------------------------------
def int_at_least(lowest: int):
    """An argparse type: an integer >= ``lowest``."""
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError("expected an integer, got %r" % text) from None
        if v < lowest:
            raise argparse.ArgumentTypeError(
                "must be %s, got %d" % ("a positive integer" if lowest == 1 else
                                        ">= %d" % lowest, v))
        return v
    return parse


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


# -- options ------------------------------------------------------------------------
def _bytes(lowest: int):
    """An argparse type: 0 (auto) or a byte count >= ``lowest``, e.g. 1073741824, 512M
    or 2G."""
    def parse(text):
        m = re.fullmatch(r"\s*(\d+)\s*([KMGT]?)(?:i?B)?\s*", text, re.I)
        if not m:
            raise argparse.ArgumentTypeError("expected a number of bytes (e.g. 512M or 2G), "
                                             "got %r" % text)
        v = int(m.group(1)) * 1024 ** " KMGT".index(m.group(2).upper() or " ")
        if 0 < v < lowest:
            raise argparse.ArgumentTypeError("must be 0 (auto) or at least %d bytes (%d MiB), got %s"
                                             % (lowest, lowest >> 20, text))
        return v
    return parse


def _param_option(p: Param) -> dict:
    """add_argument keywords for a renderer parameter (None = not given)."""
    doc = re.sub(r"``([^`]*)``", r"\1", p.doc).replace("%", "%%")
    kw = {"dest": p.name, "default": None, "help": "%s (default: %s)" % (doc, p.default_text)}
    if p.kind is bool:
        kw["action"] = "store_false" if p.default else "store_true"
        kw["help"] = "%s%s (%s by default)" % ("turn off %s: " % p.name if p.default else "",
                                               doc, "on" if p.default else "off")
    elif p.name == "technique":
        kw.update(type=_technique, metavar="s,t")
    elif p.choices is not None:
        kw["choices"] = p.choices
    elif p.name == "memory_budget":
        kw.update(type=_bytes(MIN_MEMORY_BUDGET), metavar="BYTES")
    elif p.kind is int:
        kw.update(type=int_at_least(p.minimum) if p.minimum is not None else int, metavar="N")
    return kw


def add_renderer_options(p) -> None:
    g = p.add_argument_group("renderer settings (not given: the scene's bdpt integrator's, "
                             "its max_depth and rr_depth for other integrators, else the "
                             "default shown)")
    actions = {param.flag: g.add_argument(param.flag, **_param_option(param))
               for param in PARAMS}
    actions["--strategy-images"] = g.add_argument(
        "--strategy-images", action="store_true",
        help="also write every (s,t) strategy: OUT.strategies.exr (layers s<s>t<t>.R/G/B) "
             "and OUT.strategies.png (rows: path length k = s+t-1, columns: s)")
    for old, new in RENAMED_OPTIONS.items():
        action = actions[new]
        g.add_argument(old, dest=action.dest, action=_Renamed, new=new, nargs=action.nargs,
                       const=action.const, type=action.type, choices=action.choices,
                       default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def add_scene_options(p) -> None:
    p.add_argument("-D", dest="defines", action="append", type=_define, default=[],
                   metavar="KEY=VALUE",
                   help="set a scene parameter ($KEY in the XML), e.g. -D resx=64; repeatable")
    p.add_argument("--res", type=_resolution, metavar="WxH",
                   help="film size: sets the scene parameters resx and resy")
    p.add_argument("--sensor", type=int_at_least(0), default=0, metavar="N",
                   help="which of the scene's sensors to render (default 0, the first)")
    p.add_argument("--variant", default=DEFAULT_VARIANT,
                   help="Mitsuba variant (a JIT one: llvm_* or cuda_*; default %(default)s)")


# -- commands -------------------------------------------------------------------------
def _add_scene_and_output(p) -> None:
    """The scene file and the output EXR of a command that renders."""
    p.add_argument("scene", nargs="?", help="scene XML file (default: the Cornell box in scenes/)")
    p.add_argument("-o", "--output", metavar="OUT.exr",
                   help="output EXR (default: <scene name>.exr in the current directory)")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    parser = _Parser(prog=PROG, description="Wavefront bidirectional path tracer "
                     "(Dr.Jit / Mitsuba 3).")
    parser.add_argument("--version", action="version", version="%(prog)s " + __version__)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    r = sub.add_parser("render", help="render a scene to OpenEXR (+ PNG preview)",
                       description="Render a Mitsuba XML scene with BDPT. Writes OUT.exr "
                       "(float32, spp, seed and settings in the header) and a tone-mapped "
                       "sRGB preview OUT.png. Ctrl-C stops after the current pass and "
                       "writes what was rendered (exit status 130; 143 for SIGTERM).")
    _add_scene_and_output(r)
    r.add_argument("--spp", type=int_at_least(1),
                   help="samples per pixel (default: the scene's sampler)")
    r.add_argument("--seed", type=int_at_least(0), default=0, help="random seed (default 0)")
    r.add_argument("--time", type=_positive_float, metavar="SECONDS",
                   help="time budget: stop after the pass that crosses it")
    r.add_argument("--checkpoint", type=_positive_float, metavar="SECONDS",
                   help="rewrite the output every SECONDS while rendering (a failed "
                        "rewrite is reported and rendering goes on)")
    r.add_argument("--cluster", metavar="ADDRESS",
                   help="render the passes on Ray workers: local:N (a Ray cluster of N "
                        "worker processes on this machine), auto (the cluster this machine "
                        "joined with 'ray start') or ray://HOST:PORT; the scene's folder is "
                        "shipped to the workers. Needs pip install 'bdpt-drjit[cluster]'")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    add_scene_options(r)
    add_renderer_options(r)

    t = sub.add_parser("mlt", help="render a scene with Metropolis light transport (mlt, pssmlt)",
                       description="Render a Mitsuba XML scene with Metropolis light "
                       "transport over BDPT samples (thousands of Markov chains as lanes): "
                       "multiplexed MLT (a strategy per chain) or primary sample space MLT. "
                       "Writes OUT.exr and OUT.png. --time or Ctrl-C stop after the current "
                       "iteration and write the image of the iterations done.")
    _add_scene_and_output(t)
    t.add_argument("--integrator", choices=("pssmlt", "mlt"), default="pssmlt",
                   help="pssmlt (default: every strategy per sample) or mlt (multiplexed: "
                   "one strategy per chain and path length; needs a finite --max-depth)")
    t.add_argument("--multiplex", choices=("strategy", "length", "auto"),
                   help="mlt: what a chain fixes besides its path length: its strategy "
                   "(as pbrt), all strategies of its length, or auto (default: length "
                   "where the bootstrap finds the light spread over many strategies)")
    t.add_argument("--no-two-stage", dest="two_stage", action="store_false", default=None,
                   help="mlt: the chains' target is the luminance (default: over the "
                   "brightness of the record's pixel, from a first stage)")
    t.add_argument("--direct-samples", type=int_at_least(-1), metavar="N",
                   help="paths of 1 and 2 edges by N independent samples per pixel per "
                   "iteration instead of the chains (default 0: automatic, where they carry "
                   ">= 25%% of the light; -1: none)")
    t.add_argument("--mutations-per-pixel", "--spp", dest="mutations_per_pixel",
                   type=int_at_least(1), help="mean mutations per pixel (default: the "
                   "scene's sample count)")
    t.add_argument("--large-step-probability", type=float, metavar="P",
                   help="probability of a large step (default 0.3; mlt: 0.1 where a chain "
                   "has a strategy, 0.3 where it has every strategy of its length)")
    t.add_argument("--bootstrap-samples", type=int_at_least(1), metavar="N",
                   help="independent samples estimating b and seeding the chains (default 0: "
                   "max(100000, 8 x chains))")
    t.add_argument("--no-large-step-mis", dest="large_step_mis", action="store_false",
                   default=None, help="weight large steps as chain states only (no "
                   "Kelemen MIS; the image's sum is then b N at every iteration)")
    t.add_argument("--chains", type=int_at_least(0), metavar="N",
                   help="Markov chains (default 0: min(262144, max(4096, mutations / 16)), at most "
                   "2x the bootstrap's effective sample size)")
    t.add_argument("--max-depth", type=int_at_least(-1), help="longest path in edges (-1: unbounded)")
    t.add_argument("--rr-depth", type=int_at_least(1), help="vertex where Russian roulette starts")
    t.add_argument("--mis", choices=("power", "balance", "uniform"), help="MIS heuristic")
    t.add_argument("--no-light-image", dest="light_image", action="store_false", default=None,
                   help="leave out the t = 1 strategies (MIS renormalizes over the rest)")
    t.add_argument("--hide-emitters", action="store_true", default=None,
                   help="hide emitters seen directly by the camera")
    t.add_argument("--seed", type=int_at_least(0), default=0, help="random seed (default 0)")
    t.add_argument("--time", type=_positive_float, metavar="SECONDS",
                   help="time budget: stop after the iteration that crosses it")
    t.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    add_scene_options(t)

    m = sub.add_parser("merge", help="combine renders made with different seeds",
                       description="Average EXR renders of the same scene made with "
                       "different seeds, weighted by their spp (from the header).")
    m.add_argument("inputs", nargs="+", metavar="IN.exr")
    m.add_argument("-o", "--output", required=True, metavar="OUT.exr")
    m.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")

    i = sub.add_parser("info", help="what the renderer sees in a scene, or an image's header",
                       description="For a scene: list its sensors, film, emitters and BSDFs, "
                       "and whether bdpt can render it (and if not, why). For an .exr "
                       "written by 'bdpt render' or 'bdpt merge': its size, channels and "
                       "header (spp, seed, time, settings, scene).")
    i.add_argument("scene", nargs="?", metavar="SCENE.xml|IMAGE.exr",
                   help="scene XML file (default: the Cornell box) or an OpenEXR image")
    add_scene_options(i)

    c = sub.add_parser("calibrate", help="measure this machine's unit costs for the budget "
                       "decision",
                       description="Measure what a ray of each walk, a stored light vertex, "
                       "a connection and a ray of Mitsuba's path cost on this machine in the "
                       "variant, and store them (bdpt_drjit/units.py says where). An 'auto' "
                       "budget prices the pilot's counts with them; a render measures them "
                       "itself on first use.")
    c.add_argument("--variant", default=DEFAULT_VARIANT,
                   help="Mitsuba variant (a JIT one: llvm_* or cuda_*; default %(default)s)")
    c.add_argument("--repeats", type=int_at_least(1), default=5,
                   help="warm runs whose median is kept (default %(default)s)")
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
        raise CLIError("no command given (render, mlt, merge, info or calibrate)", 2)
    return args
