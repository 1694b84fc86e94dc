"""The benchmark scene suite: name -> how to load it, its reference, max_depth, and
which method is expected to fail there and why.

Project scenes live in ``scenes/`` (and ``benchmarks/scene_files/sds.xml``); the
external ones (Bitterli's conversions, with Tungsten reference renders) are read from
``../shared/scenes/external`` (or ``$BDPT_SHARED/scenes/external``) and are skipped
with a message when that folder is absent.  They are never copied into the project.

    from benchmarks.scenes import SCENES
    spec = SCENES["point-caustic"]
    ok, why = spec.available()
    w, h, factor = spec.resolution(32)
    scene = spec.load(w, h)
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi

from bdpt_drjit import support

from .common import BENCH, EXTERNAL, ROOT, read_exr


@dataclass(frozen=True)
class BenchScene:
    name: str
    file: Path                   # the scene XML
    max_depth: int
    reference: str               # a method name (rendered and cached), or "exr"
    expected_failure: str        # one sentence: which method fails here, and why
    effect: str = ""             # what the scene tests
    external: bool = False
    exr: Path | None = None      # shipped reference (external scenes)
    exr_size: tuple[int, int] | None = None   # (width, height) of the EXR
    baseline: str = "path"       # the method equal-time ratios are taken against

    def available(self) -> tuple[bool, str]:
        if not self.file.exists():
            hint = (" (these scenes need the project's ../shared folder; set BDPT_SHARED to its "
                    "location)" if self.external else "")
            return False, "scene file %s not found%s" % (self.file, hint)
        if self.reference == "exr" and (self.exr is None or not self.exr.exists()):
            return False, "reference image %s not found" % self.exr
        return True, ""

    def resolution(self, res: int) -> tuple[int, int, int]:
        """(width, height, factor) to render at.  Project scenes are square: (res,
        res, 1).  External scenes: the EXR's size divided by the integer factor (a
        divisor of both sides) that makes the width closest to ``res``; the EXR
        is box-downsampled by that factor to serve as reference."""
        if self.exr_size is None:
            return res, res, 1
        W, H = self.exr_size
        g = math.gcd(W, H)
        divisors = [d for d in range(1, g + 1) if g % d == 0]
        f = min(divisors, key=lambda d: (abs(math.log(W / d / res)), d))
        return W // f, H // f, f

    def load(self, width: int, height: int, max_depth: int | None = None) -> mi.Scene:
        params = dict(resx=width, resy=height,
                      max_depth=self.max_depth if max_depth is None else max_depth)
        if not self.external:
            return support.load_file(self.file, **params)
        # External scenes use a tent pixel filter.  The reference is box-downsampled
        # from a high-resolution render, which equals a box filter at the low
        # resolution, so swap the filter for a box one (in memory, on the fly).
        text = self.file.read_text()
        text = re.sub(r'<rfilter\s+type="[a-z]+"\s*/>', '<rfilter type="box"/>', text)
        fr = mi.file_resolver()
        saved = [fr[i] for i in range(len(fr))]
        fr.prepend(str(self.file.parent))
        try:
            return mi.load_string(text, optimize=False, **params)   # as support.load_file
        finally:
            fr.clear()
            for p in saved:
                fr.append(p)

    def exr_reference(self, factor: int):
        from .common import box_downsample
        return box_downsample(read_exr(self.exr), factor)


def _project(name, file, reference, expected_failure, effect, max_depth=8):
    return BenchScene(name=name, file=ROOT / "scenes" / file, max_depth=max_depth,
                      reference=reference, expected_failure=expected_failure, effect=effect)


def _external(name, folder, max_depth, expected_failure, effect, size):
    d = EXTERNAL / folder
    return BenchScene(name=name, file=d / "scene.xml", max_depth=max_depth, reference="exr",
                      expected_failure=expected_failure, effect=effect, external=True,
                      exr=d / "TungstenRender.exr", exr_size=size)


SCENE_LIST = [
    _project("cornell-diffuse", "cornell-box.xml", "path",
             "None: every method converges, so any disagreement points to an MIS or "
             "weighting bug; path tracing should be the most efficient here.",
             "Classic diffuse Cornell box, light just below the ceiling"),
    _project("cornell-light-up", "cornell-light-up.xml", "bdpt-power",
             "Path tracing is poor: almost no shadow ray reaches the upward-facing light, "
             "so the room is lit through the bright ceiling patch, found by BSDF sampling "
             "only by chance; BDPT's light subpaths start there.",
             "Indirect-only lighting: the light faces the ceiling"),
    _project("glass-caustic-area", "cornell-spheres.xml", "bdpt-power",
             "Path tracing renders the caustic under the glass sphere with fireflies (a "
             "BSDF-sampled ray must hit the small light), and light tracing renders the "
             "spheres' interiors and reflections black.",
             "Glass and mirror spheres, small area light: caustics"),
    _project("point-caustic", "point-caustic.xml", "ptracer",
             "Path tracing cannot render the caustic at all (a ray must hit a point light "
             "after a specular bounce, probability 0); light tracing and BDPT's t=1 "
             "strategies can.",
             "Point light focused by a glass ball onto a floor"),
    _project("camera-behind-glass", "glass-pane.xml", "path",
             "Light tracing (and every t=1 strategy) cannot render it: the pinhole cannot "
             "be reached through the smooth glass pane, so ptracer is black.",
             "Diffuse scene seen through a glass pane"),
    BenchScene(name="sds", file=BENCH / "scene_files" / "sds.xml", max_depth=8, reference="path",
               expected_failure="Every method struggles with the caustic seen in the mirror "
               "(light-glass-floor-mirror-camera): no connection can make it and only "
               "a camera subpath hitting the small light can, so BDPT is no better than "
               "path tracing there and light tracing sees nothing in the mirror.",
               effect="Caustic seen only in a mirror, small area light (SDS paths)"),
    _external("veach-bidir", "veach-bidir", 7,
              "Path tracing is slow: most light reaches the room through the lamp's glossy "
              "reflector and the glass egg (caustics), which BDPT's light subpaths sample "
              "directly; light tracing handles the caustics but not the glossy lamp.",
              "Veach's bidirectional test room (Bitterli)", (1024, 1024)),
    _external("veach-mis", "veach-mis", 3,
              "No method fails outright; it tests MIS between emitter and BSDF sampling on "
              "glossy plates (the weighting scheme matters); light tracing is weak on the "
              "near-specular plates.",
              "Veach's MIS scene: 4 glossy plates, 4 spherical lights (Bitterli)", (1280, 720)),
    _external("cornell-box", "cornell-box", 16,
              "None: a diffuse box where path tracing should win per unit time; the "
              "Tungsten reference has no depth limit, max_depth 16 leaves ~0.3% of the "
              "energy out (an error floor far below the noise).",
              "Bitterli's Cornell box", (1024, 1024)),
]

# Participating media (not in the default modes: ``--scenes`` names them); baseline
# Mitsuba's volpath, since path and ptracer have no media.
MEDIA_SCENE_LIST = [
    BenchScene(name="god-rays", file=ROOT / "scenes" / "media" / "god-rays.xml", max_depth=8,
               reference="volpath", baseline="volpath",
               expected_failure="volpath's next-event estimation draws the sheet of light from "
               "the slit well; the fog the sheet lights (multiple scattering) is noisy for it.",
               effect="Fog-filled room, small light shining through a slit (god rays)"),
    BenchScene(name="fog-cube", file=ROOT / "scenes" / "media" / "fog-cube.xml", max_depth=8,
               reference="volpath", baseline="volpath",
               expected_failure="None: volpath converges; light subpaths add little.",
               effect="Cornell box with a chromatic homogeneous fog cube"),
    BenchScene(name="cloud", file=ROOT / "scenes" / "media" / "cloud.xml", max_depth=8,
               reference="volpath", baseline="volpath",
               expected_failure="None: volpath converges; heterogeneous media leave distance "
               "densities out of bdpt's weights.",
               effect="Heterogeneous cloud under a sky and a sphere light"),
    BenchScene(name="volumetric-caustic-point", file=ROOT / "scenes" / "media" / "volumetric-caustic.xml",
               max_depth=8, reference="bdpt-power", baseline="volpath",
               expected_failure="volpath cannot render the cone at all (a camera path would have "
               "to hit a point light through glass): its error stops falling at that bias.",
               effect="Point light focused by a glass ball into fog"),
    BenchScene(name="volumetric-caustic", file=ROOT / "scenes" / "media" / "volumetric-caustic-sphere.xml",
               max_depth=8, reference="bdpt-power", baseline="volpath",
               expected_failure="volpath renders the cone of light a glass ball focuses into fog "
               "with fireflies: a camera path must hit the small light through the ball.",
               effect="Sphere light focused by a glass ball into fog (mitsuba3 #181)"),
]

SCENES = {s.name: s for s in SCENE_LIST + MEDIA_SCENE_LIST}

# Scenes for the strategy pyramid (per-(s,t) contact sheet).
PYRAMID_SCENES = ("veach-bidir", "glass-caustic-area")


if __name__ == "__main__":
    for s in SCENE_LIST:
        ok, why = s.available()
        print("%-20s max_depth=%-3d ref=%-11s %s\n    %s" % (s.name, s.max_depth, s.reference,
                                                           "" if ok else "[missing: %s]" % why,
                                                           s.expected_failure))
