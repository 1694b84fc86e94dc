"""The integrator's parameters, declared once.

``PARAMS`` is the single declaration: ``Settings`` (the validated values the engine
reads), the Mitsuba plugin's properties and its reference table, the command line's
options with their choices and bounds, and the README's table all come from it
(tests/test_settings.py checks the README against it).  Names follow Mitsuba's
(``max_depth``, ``rr_depth``, ``hide_emitters``, ``samples_per_pass``).
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

from . import aovs

HEURISTICS = ("power", "balance", "uniform", "lafortune")
# Strategy subsets of the same engine, to show what MIS buys: "pt" = path tracing
# with next-event estimation (s <= 1, MIS between the two), "lt" = light tracing
# (t = 1: one strategy per path length, weight 1).
# "ppm" = progressive photon mapping: merging alone (merge.py), at the first camera
# vertex that scatters smoothly, and emitters seen through delta lobes only.
STRATEGY_SUBSETS = ("all", "pt", "lt", "ppm")
# Heuristics that merging (vertex merging, merge.py) can join: the ratio heuristics.
MERGING_HEURISTICS = ("power", "balance", "uniform")
FIRST_HITS = ("auto", "all", "light_image")
MIN_MEMORY_BUDGET = 1 << 20


@dataclass(frozen=True)
class Param:
    """One integrator parameter: its Mitsuba name, type, default and documentation."""
    name: str
    kind: type
    default: object
    doc: str
    choices: tuple | None = None
    minimum: int | None = None

    @property
    def flag(self) -> str:
        """The command-line option (``--max-depth``; booleans whose default is true
        are switched off with ``--no-...``)."""
        base = self.name.replace("_", "-")
        return "--no-" + base if self.kind is bool and self.default else "--" + base

    @property
    def default_text(self) -> str:
        if self.kind is bool:
            return "true" if self.default else "false"
        if self.name == "memory_budget":
            return "auto"
        return str(self.default) if self.default != "" else "none"


PARAMS = (
    Param("max_depth", int, -1, "Longest path, in edges (1: emitters seen directly; "
          "2: direct light). -1 = unbounded, ended by Russian roulette.", minimum=-1),
    Param("rr_depth", int, 5, "Subpath vertex at which Russian roulette starts.", minimum=1),
    Param("mis", str, "power", "MIS heuristic: ``power`` (exponent 2), ``balance``, "
          "``uniform`` (every strategy able to make a path weighs the same) or "
          "``lafortune`` (Lafortune & Willems' specularity weights; no light image).",
          choices=HEURISTICS),
    Param("light_image", bool, True, "Include the t = 1 (light tracing) strategies, "
          "splatted onto the film; without them MIS renormalizes over the rest, and the "
          "paths only they sample (a point light's caustics) are missing: a warning "
          "says so."),
    Param("hide_emitters", bool, False, "Hide emitters seen directly by the camera, as "
          "Mitsuba's path and volpath do: a camera ray passes the area emitters it meets "
          "first, which show what lies behind them; an emitter seen through a null lobe "
          "alone (a mask's holes) is hidden too."),
    Param("technique", str, "all", "Render the single strategy ``\"s,t\"`` without MIS "
          "weighting (for tests and for studying strategies)."),
    Param("strategy_subset", str, "all", "``all``; ``pt`` = path tracing with next-event "
          "estimation only (s <= 1), ``lt`` = light tracing only (t = 1): the same engine "
          "without MIS's other strategies.", choices=STRATEGY_SUBSETS),
    Param("merging", bool, False, "Vertex merging (VCM, Georgiev et al. 2012): every camera "
          "surface vertex that scatters smoothly also merges with the pass's light vertices "
          "within ``radius``, as one more set of MIS strategies.  Consistent, not unbiased "
          "(the bias shrinks with the radius over passes); medium vertices connect but do "
          "not merge.  The ``vcm`` integrator is ``bdpt`` with merging on."),
    Param("radius", str, "auto", "Merging radius of the first pass, in world units; "
          "``auto`` (or 0): 1.5 pixel footprints at the distance of the scene's centre "
          "(SmallVCM's default, 0.003 x the scene's radius, is about 1 of them in the "
          "Cornell box at 512x512).  With ``auto`` budgets the decision may merge at a "
          "quarter of it (optimizer.MERGE_RADII)."),
    Param("radius_alpha", float, 0.75, "Radius reduction of progressive merging: pass i "
          "(1-based) merges within r_1 i^((alpha - 1) / 2); 1 keeps the radius fixed "
          "(then merging is biased, not consistent)."),
    Param("light_paths", str, "auto", "Light subpaths per camera sample (a number >= 0; "
          "0 = path tracing with next-event estimation), or ``auto``: chosen for "
          "efficiency from a pilot pass, its counted work priced by the machine's unit "
          "costs (budgets.py, units.py)."),
    Param("connections", str, "auto", "Connections per camera vertex: ``all`` (every "
          "vertex of its light subpath), a count M (M vertices drawn from all the "
          "pass's light vertices; 0 = none), or ``auto`` (chosen with light_paths)."),
    Param("first_hits", str, "auto", "Which strategies render paths whose first camera "
          "vertex scatters smoothly: ``all``, or ``light_image`` alone (light tracing "
          "wherever the camera sees a diffuse or glossy surface, unbiased in any scene: "
          "the camera walk goes on only behind delta surfaces), or ``auto`` (chosen with "
          "light_paths; ``all`` when light_paths and connections are fixed).",
          choices=FIRST_HITS),
    Param("aovs", str, "", "AOVs written beside the image, in Mitsuba's ``aov`` "
          "syntax: ``\"albedo:albedo,nn:sh_normal,dd:depth\"`` (types: albedo, depth, "
          "position, uv, geo_normal, sh_normal, dp_du, dp_dv, prim_index, shape_index; "
          "aovs.py).  Their channels follow the image's."),
    Param("samples_per_pass", int, 0, "Samples per pixel per pass; 0 chooses it so that "
          "a pass fits ``memory_budget``.", minimum=0),
    Param("memory_budget", int, 0, "Bytes a pass may use for its wavefront state and "
          "stored light vertices (at least 1 MiB); 0 = auto: 2 GiB on the CPU, a quarter "
          "of the GPU's memory (2-12 GiB) under CUDA, where a pass's fixed cost asks for "
          "large passes (backend.py).", minimum=0),
)
PARAM = {p.name: p for p in PARAMS}
# Old names that still work, with a DeprecationWarning.
RENAMED = {"strategies": "strategy_subset"}
# Mitsuba 0.5/0.6 ``bdpt`` parameters: the ones with a meaning here, and what to
# do about the rest.
LEGACY = {"maxDepth": "max_depth", "rrDepth": "rr_depth", "lightImage": "light_image",
          "hideEmitters": "hide_emitters"}
LEGACY_REFUSED = {
    "sampleDirect": "next-event estimation (s = 1) is always one of bdpt's strategies; "
                    "use strategy_subset or technique to choose strategies",
    "strictNormals": "bdpt always gives zero weight where shading and geometric normals "
                     "disagree (as Mitsuba 0.5 did with strictNormals=true); remove it",
}


def parse_technique(text):
    """``"s,t"``, ``(s, t)``, ``"all"`` or None -> (s, t) or None."""
    if text is None or text in ("", "all"):
        return None
    if isinstance(text, (tuple, list)):
        s, t = text
        return int(s), int(t)
    try:
        s, t = (int(x) for x in str(text).replace("(", "").replace(")", "").split(","))
    except ValueError:
        raise ValueError("bdpt: technique must be written \"s,t\" (e.g. \"1,2\"), got %r"
                         % (text,)) from None
    return s, t


def canonical_name(key: str) -> str:
    """A parameter's current name, from a current, renamed or legacy one; raises
    ValueError for names that are unknown or refused."""
    if key in PARAM:
        return key
    if key in RENAMED:
        warnings.warn("bdpt: parameter '%s' is now called '%s'" % (key, RENAMED[key]),
                      DeprecationWarning, stacklevel=3)
        return RENAMED[key]
    if key in LEGACY:
        return LEGACY[key]
    if key in LEGACY_REFUSED:
        raise ValueError("bdpt: Mitsuba 0.5 parameter '%s' has no equivalent: %s"
                         % (key, LEGACY_REFUSED[key]))
    raise ValueError("bdpt: unknown parameter '%s' (known: %s)" % (key, ", ".join(PARAM)))


def _auto_or_number(value, name: str, what: str, auto):
    """"auto" (as ``auto``) or a finite number >= 0; else an error naming ``name``."""
    if str(value) == "auto":
        return auto
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = -1.0
    if not number >= 0 or number == float("inf"):
        raise ValueError("bdpt: %s must be 'auto' or a number >= 0 (%s), got %r"
                         % (name, what, value))
    return number


def parse_light_paths(value):
    """``light_paths``: "auto" or a ratio >= 0."""
    return _auto_or_number(value, "light_paths", "light subpaths per camera sample", "auto")


def parse_connections(value):
    """``connections``: "auto", "all" or a count >= 0."""
    if str(value) in ("auto", "all"):
        return str(value)
    try:
        count = int(str(value))
    except ValueError:
        count = -1
    if count < 0:
        raise ValueError("bdpt: connections must be 'auto', 'all' or a count >= 0, got %r"
                         % (value,))
    return count


def parse_radius(value) -> float:
    """``radius``: "auto" (0) or a length >= 0."""
    return _auto_or_number(value, "radius", "a length in world units", 0.0)


def _convert(p: Param, value):
    if p.name == "radius":
        return parse_radius(value)
    if p.name == "technique":
        return parse_technique(value)
    if p.name == "light_paths":
        return parse_light_paths(value)
    if p.name == "connections":
        return parse_connections(value)
    if p.kind is bool:
        if isinstance(value, str):
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError("bdpt: %s must be true or false, got %r" % (p.name, value))
            return value.lower() in ("true", "1")
        return bool(value)
    try:
        value = p.kind(value)
    except (TypeError, ValueError):
        raise ValueError("bdpt: %s must be a%s %s, got %r" % (
            p.name, "n" if p.kind is int else "",
            "number" if p.kind is float else p.kind.__name__, value)) from None
    if p.choices is not None and value not in p.choices:
        raise ValueError("bdpt: unknown %s %r for %s (choose one of %s)"
                         % ("heuristic" if p.name == "mis" else "value", value, p.name,
                            ", ".join(p.choices)))
    if p.minimum is not None and value < p.minimum:
        raise ValueError("bdpt: %s must be >= %d, got %d" % (p.name, p.minimum, value))
    if p.name == "memory_budget" and 0 < value < MIN_MEMORY_BUDGET:
        raise ValueError("bdpt: memory_budget must be 0 (auto) or at least %d bytes (1 MiB), "
                         "got %d" % (MIN_MEMORY_BUDGET, value))
    return value


@dataclass
class Settings:
    """Validated integrator parameters (see ``PARAMS`` for their meaning)."""
    max_depth: int = PARAM["max_depth"].default
    rr_depth: int = PARAM["rr_depth"].default
    mis: str = PARAM["mis"].default
    light_image: bool = PARAM["light_image"].default
    hide_emitters: bool = PARAM["hide_emitters"].default
    technique: tuple | None = None
    strategy_subset: str = PARAM["strategy_subset"].default
    merging: bool = PARAM["merging"].default
    radius: object = PARAM["radius"].default
    radius_alpha: float = PARAM["radius_alpha"].default
    light_paths: object = PARAM["light_paths"].default
    connections: object = PARAM["connections"].default
    first_hits: str = PARAM["first_hits"].default
    aovs: str = PARAM["aovs"].default
    samples_per_pass: int = PARAM["samples_per_pass"].default
    memory_budget: int = PARAM["memory_budget"].default

    def __post_init__(self):
        for p in PARAMS:
            setattr(self, p.name, _convert(p, getattr(self, p.name)))
        if self.mis == "lafortune":  # L&W's scheme has no light image (t = 1)
            self.light_image = False
        if self.strategy_subset == "pt":
            self.light_image = False
        if self.strategy_subset == "ppm":     # merging alone
            self.merging, self.light_image = True, False
        if self.merging:
            self._check_merging()
        if self.strategy_subset == "lt" and not self.light_image:
            raise ValueError("bdpt: strategy_subset='lt' (light tracing) needs light_image")
        if self.technique is not None:
            self._check_technique()
        aovs.parse(self.aovs)                  # fail early on a bad list
        forced = self._forced_budget_reason()
        if forced and (self.light_paths != "auto" or self.connections != "auto"
                       or self.first_hits != "auto"):
            raise ValueError("bdpt: light_paths, connections and first_hits are fixed by %s; "
                             "leave them 'auto'" % forced)
        if self.first_hits == "light_image" and (not self.light_image or self.light_paths == 0):
            raise ValueError("bdpt: first_hits='light_image' needs the light image "
                             "(light_image = true and light_paths > 0)")

    def _check_merging(self):
        """What merging cannot be combined with, said plainly."""
        if not 0.0 < self.radius_alpha <= 1.0:
            raise ValueError("bdpt: radius_alpha must be in (0, 1], got %g" % self.radius_alpha)
        if self.mis not in MERGING_HEURISTICS:
            raise ValueError("bdpt: merging needs a ratio heuristic (%s): mis '%s' has no "
                             "densities, so merged paths would have no weight"
                             % (", ".join(MERGING_HEURISTICS), self.mis))
        if self.technique is not None:
            raise ValueError("bdpt: technique renders one (s,t) strategy; merging is not one "
                             "of them (turn merging off)")
        if self.strategy_subset in ("pt", "lt"):
            raise ValueError("bdpt: strategy_subset '%s' has no merging (turn merging off, "
                             "or use strategy_subset 'ppm' for merging alone)"
                             % self.strategy_subset)
        if self.light_paths == 0:
            raise ValueError("bdpt: merging needs light subpaths (light_paths > 0)")
        if self.first_hits == "light_image":
            raise ValueError("bdpt: first_hits='light_image' leaves smooth first hits to the "
                             "light image; merging needs them (leave first_hits 'auto')")

    def _forced_budget_reason(self) -> str | None:
        """What fixes the budgets (budgets.py), if anything: a single technique, a
        strategy subset and Lafortune's weights each have one fixed budget."""
        if self.technique is not None:
            return "technique"
        if self.strategy_subset != "all":
            return "strategy_subset '%s'" % self.strategy_subset
        if self.mis == "lafortune":
            return "mis 'lafortune'"
        return None

    def _check_technique(self):
        s, t = self.technique
        if s < 0 or t < 1:
            raise ValueError("bdpt: technique (s,t) needs s >= 0 and t >= 1, got %d,%d" % (s, t))
        if 0 <= self.max_depth < s + t - 1:
            raise ValueError("bdpt: technique %d,%d makes paths of %d edges, longer than "
                             "max_depth %d: the image would be black"
                             % (s, t, s + t - 1, self.max_depth))
        if t == 1 and self.strategy_subset == "pt":
            raise ValueError("bdpt: technique %d,1 is a light-tracing strategy, outside "
                             "strategy_subset 'pt'" % s)
        if t >= 2 and self.strategy_subset == "lt":
            raise ValueError("bdpt: technique %d,%d is not a light-tracing strategy, outside "
                             "strategy_subset 'lt'" % (s, t))
        if t == 1 and not self.light_image:
            raise ValueError("bdpt: technique %d,1 is a light-tracing strategy, but "
                             "light_image is false%s" % (s, " (mis='lafortune' has no light "
                                                         "image)" if self.mis == "lafortune" else ""))

    @classmethod
    def from_dict(cls, values: dict) -> "Settings":
        """Settings from keyword values under current, renamed or legacy names."""
        out = {}
        for key, value in values.items():
            out[canonical_name(key)] = value
        return cls(**out)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def rst_table() -> str:
    """The plugin's parameter table (reStructuredText, as Mitsuba's plugin pages)."""
    lines = [".. list-table::", "   :header-rows: 1", "", "   * - Parameter", "     - Type",
             "     - Description"]
    for p in PARAMS:
        kind = {int: "integer", bool: "boolean", str: "string", float: "float"}[p.kind]
        lines += ["   * - %s" % p.name, "     - %s" % kind,
                  "     - %s (Default: %s)" % (p.doc, p.default_text)]
    return "\n".join(lines)


def markdown_rows() -> list[tuple[str, str]]:
    """(name, default) of each parameter, as the README's table shows them."""
    return [(p.name, p.default_text) for p in PARAMS]
