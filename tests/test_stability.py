"""Stability where methods fail: a stress suite the renderer survives with nothing lost.

Each case is a small scene that isolates one failure of some light transport method
(scenes/stress/*.xml, whose comments say who fails there and why), rendered with
SEEDS seeds.  For every case and seed:

  test_finite_and_independent_of_passes
      no NaN and no Inf in the image or in any strategy image, and the same seeds
      rendered in passes of a few spp (``samples_per_pass``) give a statistically
      equal image (different random numbers, the same estimator);
  test_reference
      where a reference exists -- analytic, or Mitsuba's ``path`` / ``ptracer`` where
      that converges -- agreement by stats.py's Welch test on image blocks over seeds;
  test_fireflies
      the largest pixel of one low-spp render (the case's spp, one seed) stays within
      FIREFLY[case] times the largest pixel of the converged image (the mean of all
      2 x SEEDS renders of the case).

Firefly factors.  Each FIREFLY bound is about twice the worst ratio measured over the
case's 16 renders (the measured value is written next to it), and at least 1.5.  A
ratio near 1 means the brightest pixel is a real feature rendered smoothly; noise
adds the relative error of one pixel at that spp (at 8-32 spp: 1.04 for a smooth
analytic image, up to 1.96 where the light comes through glass or a slit).  A real
firefly -- one sample carrying 1/pdf of a path its strategy can barely sample -- is a
factor of 10 to 1000: the Russian-roulette bug below read 10.5 on closed-box-a0.9
(bound 3, 1.43 after the fix).  Seeds are fixed, so ratios and bounds do not flake.

Engine bugs this suite found:
  * a zero-area emitter crashed Renderer construction (1.0 / surface_area in
    emitters.py), case zero-area-emitter -- fixed in 0050381;
  * Russian roulette chose its survival probability from the product of BSDF weights
    without the 1/q of earlier survivals, so survival decayed like albedo^(depth^2/2)
    and rare survivors were fireflies, case closed-box-a0.9 (test_fireflies) -- fixed
    in 0050381;
  * light subpaths applied the shading-normal (adjoint) correction with si.sh_frame, but
    a ``normalmap``/``bumpmap`` BSDF perturbs the normal inside the BSDF: light-traced
    strategies carried the wrong energy on normal-mapped surfaces (strategy (2,1) -32%),
    case normal-map and test_light_tracing_with_shading_normals -- fixed: the adjoint is
    now the radiance-mode BSDF with its directions swapped (records.eval_adjoint).
Limitations found (asserted as measured, not xfail'ed):
  * Mitsuba offsets every spawned ray by (1 + max|p|) * 8.9e-5 world units, an absolute
    floor: in a scene 2e-3 across that is 4.5 % of the scene, and both Mitsuba's
    integrators and this one (which spawns rays the same way) lose scale invariance
    by several percent (test_scale).
  * Performance, not correctness: keeping other scenes alive in the process makes every
    render many times slower (measured 55x with 11 other scenes alive: Dr.Jit's
    dispatch sees every live BSDF/emitter instance; Mitsuba's path slows down too), so
    the suite builds each scene, renders what it needs and drops it (``runs``); and with
    104 emitters each pass costs ~0.45 s more (many-lights splits into 2 passes only).

Renders are tiny (15 x 15 to 24 x 24, 8 to 32 spp): the file runs in about 100 s with
a warm Dr.Jit kernel cache and 150 s cold, on 2 cores; no single test takes 20 s,
the two heaviest cases (many-lights, closed-box-a0.9: ~13 s cold) are marked slow.
"""
from __future__ import annotations

import functools
import gc
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

import mitsuba as mi
import bdpt_drjit
from bdpt_drjit import support
from conftest import scene_path
from stats import assert_statistically_equal

STRESS = Path(scene_path("stress"))
SEEDS = 8                  # per side of every statistical comparison
SEED, REF_SEED = 1000, 2000
T = mi.ScalarTransform4f


def stress(name: str, **params) -> mi.Scene:
    """A scene of scenes/stress/ with XML parameters ($name values) overridden, loaded as
    the API loads it (without Mitsuba's shape merging, which ordered the two lights of
    zero-area-emitter.xml differently from process to process)."""
    return support.load_file(STRESS / name, **{k: str(v) for k, v in params.items()})


def reference(scene, integrator: str, spp: int, sensor=0, seeds=SEEDS, **props):
    """Mitsuba's own integrator: SEEDS independent renders."""
    integ = mi.load_dict({"type": integrator, **props})
    return [np.array(mi.render(scene, integrator=integ, sensor=sensor, spp=spp, seed=REF_SEED + s))
            for s in range(seeds)]


@dataclass
class Result:
    """A render kept as NumPy only (no JIT arrays survive a case)."""
    image: np.ndarray
    strategies: dict
    passes: int


def render(scene, spp, seed, **kwargs) -> Result:
    r = bdpt_drjit.render(scene, spp=spp, seed=seed, strategy_images=True, **kwargs)
    return Result(r.image, r.strategies, r.passes)


def assert_finite(result: Result, what: str):
    bad = [] if np.isfinite(result.image).all() else ["the image"]
    bad += ["strategy %s" % (k,) for k, v in sorted(result.strategies.items())
            if not np.isfinite(v).all()]
    assert not bad, "%s: NaN or Inf in %s" % (what, ", ".join(bad))


def light_image(result: Result) -> np.ndarray:
    """The light-tracing (t = 1) part of an image: the sum of its strategy images."""
    return sum((v for (s, t), v in result.strategies.items() if t == 1),
               np.zeros_like(result.image))


# ---------------------------------------------------------------------------
# References and scenes built in Python
# ---------------------------------------------------------------------------

def point_on_surface_exact(h: float):
    """scenes/stress/point-on-surface.xml with the light at height h: every pixel is
    albedo / pi * I * Omega / A (Omega: the solid angle of the pixel's floor footprint
    seen from the light, A its area); 0 for h = 0, where every cosine at the floor is 0."""
    def image(scene):
        n = int(scene.sensors()[0].film().crop_size()[0])
        w = math.tan(math.radians(20))           # fov 40, square film, floor 1 away
        e = np.linspace(-w, w, n + 1)
        x1, z1 = np.meshgrid(e[:-1], e[:-1])
        x2, z2 = np.meshgrid(e[1:], e[1:])

        def f(x, z):
            return np.arctan(x * z / (h * np.sqrt(x * x + z * z + h * h)))
        omega = f(x2, z2) - f(x1, z2) - f(x2, z1) + f(x1, z1) if h > 0 else 0 * x1
        value = 0.5 / np.pi * 1.0 * omega / (e[1] - e[0]) ** 2
        return np.repeat(value[..., None], 3, axis=-1)
    return image


def closed_box_exact(albedo: float, max_depth: int, radiance=1.0):
    """scenes/stress/closed-box.xml: L = Le (1 - a^k) / (1 - a); Le k for a = 1."""
    value = (radiance * max_depth if albedo == 1 else
             radiance * (1 - albedo ** max_depth) / (1 - albedo))

    def image(scene):
        w, h = (int(x) for x in scene.sensors()[0].film().crop_size())
        return np.full((h, w, 3), value)
    return image


def _analytic(fn):
    """An analytic reference as SEEDS identical 'renders' (zero variance)."""
    return lambda scene: [fn(scene)] * SEEDS


def many_lights_scene(res=16):
    """Radiometry: 100 very bright tiny lights next to 4 dim large ones (built here,
    not in XML: 104 emitters).  A 3 x 2 x 3 white room; under its ceiling a 10 x 10
    grid of lights 0.01 x 0.01 with radiance 2e4 (power 2 each); on the side walls four
    1 x 1.2 panels with radiance 0.5 (power 1.9 each).  Mitsuba selects emitters
    uniformly (pmf 1/104), so the panels get 4 % of the light samples for 4 % of the
    power, and a tiny light seen directly covers 1e-4 of a pixel: a path tracer sees it
    as rare huge samples (its seed spread hides them: not a reference here), light
    tracing splats it (ptracer converges)."""
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 60,
                    "to_world": T().look_at(origin=[0, 1.0, 3.0], target=[0, 0.9, 0], up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
         "white": {"type": "twosided", "id": "white",
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}}}
    walls = {"floor": T().rotate([1, 0, 0], -90).scale([1.5, 1.5, 1]),
             "ceiling": T().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale([1.5, 1.5, 1]),
             "back": T().translate([0, 1, -1.5]).scale([1.5, 1, 1]),
             "left": T().translate([-1.5, 1, 0]).rotate([0, 1, 0], 90).scale([1.5, 1, 1]),
             "right": T().translate([1.5, 1, 0]).rotate([0, 1, 0], -90).scale([1.5, 1, 1])}
    for name, tf in walls.items():
        d[name] = {"type": "rectangle", "to_world": tf, "bsdf": {"type": "ref", "id": "white"}}
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}
    for i in range(10):
        for j in range(10):
            d["tiny_%d_%d" % (i, j)] = {
                "type": "rectangle", "bsdf": black,
                "to_world": T().translate([-1.2 + 0.26 * i + 0.05 * (j % 2), 1.99, -1.2 + 0.26 * j])
                               .rotate([1, 0, 0], 90).scale(0.005),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 2e4}}}
    for k, (x, z, ang) in enumerate([(-1.49, -0.6, 90), (-1.49, 0.6, 90), (1.49, -0.6, -90), (1.49, 0.6, -90)]):
        d["dim_%d" % k] = {
            "type": "rectangle", "bsdf": black,
            "to_world": T().translate([x, 1.0, z]).rotate([0, 1, 0], ang).scale([0.5, 0.6, 1]),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 0.5}}}
    # Without Mitsuba's shape merging, which orders the 104 emitters differently in
    # every process (support.load_file): the same seeds then give the same samples.
    return mi.load_dict(d, optimize=False)


# ---------------------------------------------------------------------------
# The cases
# ---------------------------------------------------------------------------

@dataclass
class Case:
    """One stress scene and what is known about it."""
    scene: Callable[[], mi.Scene]
    spp: int
    settings: dict
    reference: Callable[[mi.Scene], list] | None    # SEEDS images, or None
    sensor: int = 0
    split: int = 3                 # samples_per_pass of the pass-split renders
    blocks: int = 4                # blocks x blocks regions in the Welch test
    bugs: dict = field(default_factory=dict)        # check -> xfail reason (open engine bugs)
    slow: bool = False             # ~13 s of rendering (cold kernel cache, 2 cores)


def _path(spp, **props):
    return lambda scene: reference(scene, "path", spp, **props)


def _ptracer(spp, sensor=0, **props):
    return lambda scene: reference(scene, "ptracer", spp, sensor=sensor, **props)


def _scaled(scale):
    return lambda: stress("scaled-box.xml", resx=16, resy=16, scale=scale, near=0.01 * scale,
                          far=100 * scale)


def _stress16(name, **params):
    return lambda: stress(name, resx=16, resy=16, **params)


CASES = {
    # -- light tracing fails: the camera sees only a mirror / sits in a glass box --------
    "mirror-view": Case(_stress16("mirror-view.xml"), 16, {"max_depth": 6}, _path(64, max_depth=6)),
    "camera-in-glass": Case(_stress16("camera-in-glass.xml"), 16, {"max_depth": 6},
                            _path(64, max_depth=6)),
    # -- path tracing fails: caustics from a point and a tiny light; enclosed lights -----
    "caustic-point": Case(lambda: mi.load_file(scene_path("point-caustic.xml"), resx=16, resy=16),
                          16, {"max_depth": 8}, _ptracer(64, max_depth=8)),
    "caustic-tiny-area": Case(_stress16("caustic-tiny-area.xml"), 16, {"max_depth": 8},
                              _ptracer(64, max_depth=8)),
    "light-slit": Case(_stress16("light-slit.xml"), 16, {"max_depth": 8}, _ptracer(64, max_depth=8)),
    "sun-caustic": Case(_stress16("sun-caustic.xml"), 16, {"max_depth": 8}, _ptracer(64, max_depth=8)),
    "light-facing-wall": Case(_stress16("light-facing-wall.xml"), 16, {"max_depth": 8},
                              _ptracer(64, max_depth=8)),
    # -- everyone fails: a point-light caustic seen in a mirror (sensor 0: Mitsuba's path
    #    samples exactly the same paths, see the scene), and seen directly (sensor 1) ----
    "sds-mirror": Case(_stress16("sds-mirror.xml"), 16, {"max_depth": 8}, _path(64, max_depth=8)),
    "sds-direct": Case(_stress16("sds-mirror.xml"), 16, {"max_depth": 8},
                       _ptracer(64, sensor=1, max_depth=8), sensor=1),
    # -- geometry ------------------------------------------------------------------------
    "point-on-surface": Case(lambda: stress("point-on-surface.xml", height=0), 8,
                             {"max_depth": 4}, _analytic(point_on_surface_exact(0.0))),
    "point-1e-4-above": Case(lambda: stress("point-on-surface.xml", height=1e-4), 8,
                             {"max_depth": 4}, _analytic(point_on_surface_exact(1e-4))),
    "point-1e-2-above": Case(lambda: stress("point-on-surface.xml", height=1e-2), 8,
                             {"max_depth": 4}, _analytic(point_on_surface_exact(1e-2))),
    "touching": Case(_stress16("touching.xml"), 16, {"max_depth": 6}, _path(64, max_depth=6)),
    "grazing": Case(_stress16("grazing.xml"), 16, {"max_depth": 6}, _path(64, max_depth=6)),
    "zero-area-emitter": Case(_stress16("zero-area-emitter.xml"), 16, {"max_depth": 6},
                              _path(64, max_depth=6)),
    "degenerate-triangle": Case(_stress16("degenerate-triangle.xml"), 16, {"max_depth": 6},
                                _path(64, max_depth=6)),
    "scale-1": Case(_scaled(1), 16, {"max_depth": 6}, _path(64, max_depth=6)),
    "scale-1e4": Case(_scaled(1e4), 16, {"max_depth": 6}, _path(64, max_depth=6)),
    # No reference at 1e-3: Mitsuba's own integrators are off there (test_scale).
    "scale-1e-3": Case(_scaled(1e-3), 16, {"max_depth": 6}, None),
    "flipped-emitter": Case(_stress16("flipped-emitter.xml"), 16, {"max_depth": 6},
                            _path(64, max_depth=6)),
    "smooth-lowpoly": Case(_stress16("smooth-lowpoly.xml"), 16, {"max_depth": 6},
                           _path(64, max_depth=6)),
    "nested-rough-glass": Case(_stress16("nested-rough-glass.xml"), 32, {"max_depth": 5},
                               _ptracer(128, max_depth=5)),
    "normal-map": Case(_stress16("normal-map.xml"), 32, {"max_depth": 3}, _path(128, max_depth=3)),
    # -- radiometry ----------------------------------------------------------------------
    # (passes of 8 spp: with 104 emitters every pass costs ~0.5 s, see the report)
    "many-lights": Case(many_lights_scene, 16, {"max_depth": 5}, _ptracer(64, max_depth=5), split=8,
                        slow=True),
    "black-room": Case(_stress16("black-room.xml"), 8, {"max_depth": 6}, _path(16, max_depth=1)),
    # albedo 1: every path lives to max_depth = 10 unless Russian roulette (from depth 5,
    # survival 0.95) ends it: L = 10 Le exactly.
    "closed-box-a1": Case(lambda: stress("closed-box.xml", albedo=1, max_depth=10), 8,
                          {"max_depth": 10}, _analytic(closed_box_exact(1, 10))),
    "closed-box-a0.9": Case(lambda: stress("closed-box.xml", albedo=0.9, max_depth=20), 8,
                            {"max_depth": 20}, _analytic(closed_box_exact(0.9, 20)), slow=True),
    # -- film: odd and non-square; the caustic (light image) must land on the right pixels
    "film-odd": Case(lambda: stress("film-caustic.xml", resx=19, resy=13), 16, {"max_depth": 8},
                     _ptracer(64, max_depth=8), blocks=3),
}

# Firefly bounds (module docstring): about twice the worst measured ratio, at least 1.5.
FIREFLY = {                      # bound       measured (worst of 16 renders)
    "nested-rough-glass": 3.0,    #             1.47
    "mirror-view": 2.2,           #             1.09
    "camera-in-glass": 4.0,       #             1.96
    "caustic-point": 3.0,         #             1.47
    "caustic-tiny-area": 2.5,     #             1.22
    "light-slit": 3.8,            #             1.89
    "sun-caustic": 7.0,           #             3.39
    "light-facing-wall": 2.4,     #             1.19
    "sds-mirror": 2.2,            #             1.06
    "sds-direct": 3.6,            #             1.78
    "point-on-surface": 1.5,      #             1 (black: every render is exactly 0)
    "point-1e-4-above": 2.1,      #             1.04 (NEE alone: irradiance peaks at 1e8)
    "point-1e-2-above": 2.2,      #             1.07
    "touching": 2.6,              #             1.26
    "grazing": 2.6,               #             1.29
    "zero-area-emitter": 2.3,     #             1.07-1.12
    "degenerate-triangle": 2.2,   #             1.09
    "scale-1": 2.2,               #             1.09
    "scale-1e4": 2.2,             #             1.09
    "scale-1e-3": 2.2,            #             1.09
    "flipped-emitter": 2.2,       #             1.10
    "smooth-lowpoly": 2.2,        #             1.09
    "normal-map": 2.1,            #             1.05
    "many-lights": 2.5,           #             1.23
    "black-room": 2.3,            #             1.10
    "closed-box-a1": 2.6,         #             1.25
    "closed-box-a0.9": 3.0,       #             1.43 (10.5 before the Russian-roulette fix)
    "film-odd": 2.1,              #             1.04
}


@dataclass
class Runs:
    """What ``runs`` renders once per case; several tests then use it."""
    results: list                  # SEEDS Results, automatic passes
    split: list                    # the same seeds in passes of case.split spp
    reference: list | None         # SEEDS reference images

    @property
    def images(self):
        return [r.image for r in self.results]

    @property
    def split_images(self):
        return [r.image for r in self.split]

    @property
    def all_images(self):
        return self.images + self.split_images

    @property
    def converged(self):
        return np.mean(self.all_images, axis=0)

    @property
    def firefly_ratio(self) -> float:
        top = self.converged.max()
        if top == 0:                       # a black image: any light at all is a firefly
            return 1.0 if all(img.max() == 0 for img in self.all_images) else math.inf
        return max(img.max() for img in self.all_images) / top


@functools.lru_cache(maxsize=None)
def runs(name: str) -> Runs:
    """Every render of a case, once.  The scene is dropped afterwards: live scenes slow
    down every later render of the process (module docstring)."""
    case = CASES[name]
    scene = case.scene()
    results, split = [], []
    for s in range(SEEDS):
        results.append(render(scene, case.spp, SEED + s, sensor=case.sensor, **case.settings))
        split.append(render(scene, case.spp, SEED + s, sensor=case.sensor,
                            samples_per_pass=case.split, **case.settings))
    ref = case.reference(scene) if case.reference else None
    del scene
    gc.collect()
    return Runs(results, split, ref)


def _params(check):
    """The cases as pytest parameters, xfail'ed (strict) where an open engine bug is known."""
    out = []
    for name, case in CASES.items():
        reason = case.bugs.get(check)
        marks = [pytest.mark.xfail(reason=reason, strict=True)] if reason else []
        marks += [pytest.mark.slow] if case.slow else []
        out.append(pytest.param(name, marks=marks, id=name))
    return out


@pytest.mark.parametrize("name", _params("finite"))
def test_finite_and_independent_of_passes(name):
    """No NaN or Inf in any image or strategy image, for every seed; passes of a few
    spp give a statistically equal image."""
    case, r = CASES[name], runs(name)
    for s, (one, many) in enumerate(zip(r.results, r.split)):
        assert_finite(one, "%s seed %d" % (name, s))
        assert_finite(many, "%s seed %d (passes of %d spp)" % (name, s, case.split))
        assert one.passes == 1 and many.passes == math.ceil(case.spp / case.split)
    assert_statistically_equal(r.images, r.split_images, blocks=case.blocks,
                               what="%s: passes of %d spp vs one pass" % (name, case.split))


@pytest.mark.parametrize("name", _params("reference"))
def test_reference(name):
    """Agreement with the analytic answer or with Mitsuba's path / ptracer."""
    case, r = CASES[name], runs(name)
    if r.reference is None:
        pytest.skip("%s has no reference (test_scale says why)" % name)
    assert_statistically_equal(r.all_images, r.reference, blocks=case.blocks,
                               what="%s vs reference" % name)


@pytest.mark.parametrize("name", _params("fireflies"))
def test_fireflies(name):
    """The largest pixel of one low-spp render is at most FIREFLY[name] times the
    largest pixel of the converged image (module docstring)."""
    ratio = runs(name).firefly_ratio
    assert ratio <= FIREFLY[name], (
        "%s: the largest pixel of a %d-spp render is %.3g x the converged image's largest "
        "(bound %.3g)" % (name, CASES[name].spp, ratio, FIREFLY[name]))


# ---------------------------------------------------------------------------
# What each failure case is about: who fails, and what BDPT keeps
# ---------------------------------------------------------------------------

def _t1_images(result: Result):
    return {k: v for k, v in result.strategies.items() if k[1] == 1}


@pytest.mark.parametrize("name", ["mirror-view", "camera-in-glass"])
def test_light_tracing_sees_nothing(name):
    """The camera sees only a mirror / sits inside a glass box: no light vertex can be
    connected to the pinhole, so every t = 1 strategy image is exactly 0 (and Mitsuba's
    ptracer renders black), while BDPT's image is lit (and matches path: test_reference)."""
    r = runs(name)
    for res in r.results:
        t1 = _t1_images(res)
        assert t1 and all(v.max() == 0 for v in t1.values()), sorted(t1)
        assert res.image.mean() > 0.05
    scene = CASES[name].scene()
    assert reference(scene, "ptracer", 4, seeds=1, max_depth=6)[0].max() == 0


@pytest.mark.parametrize("name, ratio", [
    ("caustic-point", 0.05),       # measured 0.0005: path cannot sample the caustic at all
    ("caustic-tiny-area", 0.05),   # measured 0.0004: BSDF-sampled hits of the r=0.005 disk
])
def test_path_tracing_misses_caustics(name, ratio):
    """Mitsuba's path tracer (the same spp, 16 seeds pooled) sees a fraction of the
    caustic that BDPT renders (and ptracer confirms: test_reference): the centre 4 x 4
    pixels, where the caustic lands."""
    r = runs(name)
    scene = CASES[name].scene()
    path = np.mean(reference(scene, "path", CASES[name].spp, seeds=16, max_depth=8), axis=0)
    ours = r.converged
    assert path[6:10, 6:10].mean() < ratio * ours[6:10, 6:10].mean(), (
        path[6:10, 6:10].mean(), ours[6:10, 6:10].mean())


@pytest.mark.parametrize("name, factor", [
    ("light-slit", 1.5),           # measured 2.8
    ("light-facing-wall", 4.0),    # measured 11.3
])
def test_path_tracing_is_noisy_for_enclosed_lights(name, factor):
    """A light seen only through a slit, or only via the wall it faces: next-event
    estimation almost never reaches it, so Mitsuba's path tracer at the same spp has a
    seed-to-seed spread of its 4 x 4 block means at least ``factor`` times BDPT's
    (median over blocks)."""
    r = runs(name)
    scene = CASES[name].scene()
    path = reference(scene, "path", CASES[name].spp, seeds=SEEDS, max_depth=8)

    def spread(images):
        b = np.stack(images).mean(-1).reshape(len(images), 4, 4, 4, 4).mean(axis=(2, 4))
        return b.std(axis=0, ddof=1) / np.maximum(b.mean(axis=0), 1e-9)
    measured = np.median(spread(path) / spread(r.images))
    assert measured > factor, measured


def test_specular_diffuse_specular_is_not_sampled():
    """Everyone fails: the point-light caustic seen in a mirror (scenes/stress/sds-mirror.xml
    lists which strategy would need what).  BDPT's image stays finite and stable
    (test_finite..., test_fireflies) and equals Mitsuba's path tracer (test_reference:
    with a plane as the only diffuse surface the two sample exactly the same paths), and
    the paths it cannot sample are really missing: the caustic seen directly (sensor 1)
    is the brightest thing in the scene, and in the mirror there is no trace of it."""
    mirror, direct = runs("sds-mirror"), runs("sds-direct")
    for res in mirror.results:                     # no light-traced path reaches the pinhole
        assert all(v.max() == 0 for v in _t1_images(res).values())
    caustic = direct.converged.max()
    assert caustic > 20 * mirror.converged.max(), (caustic, mirror.converged.max())   # measured 90x
    # ... and it is a caustic: light tracing (t = 1) carries it in the direct view.
    lt = np.mean([light_image(res) for res in direct.results], axis=0)
    assert lt.max() > 0.9 * caustic


def test_black_scene_is_lit_only_by_visible_emitters():
    """Albedo 0 everywhere: every strategy of k >= 2 edges is exactly 0 for every seed,
    and the image equals what the camera sees of the emitters (test_reference: Mitsuba's
    path with max_depth = 1)."""
    for res in runs("black-room").results + runs("black-room").split:
        for (s, t), v in res.strategies.items():
            if s + t - 1 >= 2:
                assert v.max() == 0, (s, t)
        assert res.image.max() > 1.0


def test_scale():
    """The same room at scales 1, 1e4 and 1e-3 (scenes/stress/scaled-box.xml): the image
    cannot depend on the scale.  The three cases use the same seeds, hence the same
    random numbers, so their renders can be compared seed by seed (paired), which is far
    more sensitive than comparing means.

    1e4: no dependence (measured, 4 x 4 blocks of every seed: 0.45 % at most; whole
    images 6e-5), and statistically equal to scale 1 (Mitsuba's path: test_reference).
    1e-3: Mitsuba's absolute ray offset, 8.9e-5 world units (4.5 % of this 2e-3 room, 90 %
    of the sphere light's radius, 30 % of the mirror ball's), moves every spawned ray;
    Mitsuba's own path tracer and this renderer, which spawns its rays the same way, then
    both deviate from their scale-1 images (measured on the 16 renders pooled: BDPT
    -2.3 % on the whole image and -12 % in the worst block, the mirror ball's; Mitsuba's
    path +0.7 % and +11.7 %).  That is Mitsuba's limitation, not an engine bug; the test
    bounds it (5 % whole, 20 % per block) so that anything worse shows."""
    one, huge, tiny = runs("scale-1"), runs("scale-1e4"), runs("scale-1e-3")

    def blocks(images):
        return np.stack(images).mean(-1).reshape(len(images), 4, 4, 4, 4).mean(axis=(2, 4))
    np.testing.assert_allclose(blocks(huge.all_images), blocks(one.all_images), rtol=0.02)
    np.testing.assert_allclose(np.mean(huge.all_images, axis=(1, 2, 3)),
                               np.mean(one.all_images, axis=(1, 2, 3)), rtol=1e-3)
    assert_statistically_equal(huge.all_images, one.reference, what="scale 1e4 vs path at scale 1")

    dev = blocks(tiny.all_images).mean(0) / blocks(one.all_images).mean(0) - 1
    whole = np.mean(tiny.all_images) / np.mean(one.all_images) - 1
    assert abs(whole) < 0.05, whole
    assert np.abs(dev).max() < 0.20, dev


@pytest.mark.parametrize("name", [
    "smooth-lowpoly",
    "normal-map",
])
def test_light_tracing_with_shading_normals(name):
    """Light tracing alone, technique (2,1) unweighted, against Mitsuba's path tracer
    restricted to paths of 2 edges (path(max_depth=2) - path(max_depth=1)): direct light
    splatted from surfaces whose shading normals differ from the geometric ones needs
    Veach's adjoint correction with the normal the BSDF really uses.

    smooth-lowpoly: interpolated vertex normals up to 35 degrees off: passes.
    normal-map: the normalmap BSDF tilts the normal (up to 63 degrees) INSIDE the BSDF;
    records.adjoint_correction uses si.sh_frame, which is the unperturbed frame, so the
    light-traced strategies are wrong on the normal-mapped floor and wall (measured:
    t = 17 and 21 on two blocks; the full image: +13 % on the floor, -7 % on the wall at
    max_depth 2).  Mitsuba's ptracer has the same error.  The proposed fix (report):
    evaluate the adjoint from the radiance-mode BSDF with the directions swapped,
    f(wo -> wi) |cos_s(wi)| |cos_g(wo)| / |cos_g(wi)|, which needs no normal at all."""
    scene = CASES[name].scene()
    ours = [bdpt_drjit.render(scene, spp=32, seed=SEED + s, max_depth=2, technique=(2, 1)).image
            for s in range(SEEDS)]
    k2 = [a - b for a, b in zip(reference(scene, "path", 256, max_depth=2),
                                [np.array(mi.render(scene, spp=256, seed=3000 + s,
                                                    integrator=mi.load_dict({"type": "path", "max_depth": 1})))
                                 for s in range(SEEDS)])]
    assert_statistically_equal(ours, k2, what="%s: technique (2,1) vs path, k = 2" % name)


# ---------------------------------------------------------------------------
# Film: crop windows, reconstruction filters (odd sizes: the film-odd case)
# ---------------------------------------------------------------------------

def _film_caustic(rfilter="box", **film):
    """scenes/stress/film-caustic.xml with the sensor's film replaced (crop window,
    filter, border sampling); same view as the file's (fov 60 along x)."""
    scene = stress("film-caustic.xml")
    f = {"type": "hdrfilm", "width": 24, "height": 24, "pixel_format": "rgb",
         "rfilter": {"type": rfilter}}
    f.update(film)
    sensor = mi.load_dict({"type": "perspective", "fov": 60,
                           "to_world": T().look_at(origin=[0, 0.9, 0], target=[0, 0, 0], up=[0, 0, -1]),
                           "film": f})
    return scene, sensor


@functools.lru_cache(maxsize=None)
def film_runs(**film):
    """SEEDS renders of film-caustic.xml with this film (scalars only: cached)."""
    scene, sensor = _film_caustic(**film)
    out = [render(scene, 16, SEED + s, sensor=sensor, max_depth=4) for s in range(SEEDS)]
    del scene, sensor
    gc.collect()
    return out


@pytest.mark.parametrize("x, y, w, h", [
    (5, 7, 11, 9),      # inside, cutting through the caustic
    (0, 12, 24, 12),    # the lower half: shares the full film's left, right and bottom edges
    (17, 0, 7, 24),     # a strip on the right edge
])
def test_crop_window_gives_the_full_render_cropped(x, y, w, h):
    """A crop window (crop_offset_x/y, crop_width/height) renders the same pixels as the
    full film, cropped: compared statistically (different sample sets), for the image and
    for its light-traced part alone (whose splats are normalized by the number of light
    paths: a crop traces fewer), block by block and on the crop's outermost ring of pixels,
    where a darkened border would show."""
    full = film_runs()
    crop = film_runs(crop_offset_x=x, crop_offset_y=y, crop_width=w, crop_height=h)
    assert crop[0].image.shape[:2] == (h, w)
    cut = (slice(y, y + h), slice(x, x + w))
    ring = np.ones((h, w), bool)
    ring[1:-1, 1:-1] = False
    for what, f in [("image", lambda r: r.image), ("light image", light_image)]:
        a = [f(r) for r in crop]
        b = [f(r)[cut] for r in full]
        assert all(np.isfinite(i).all() for i in a)
        assert_statistically_equal(a, b, blocks=2, what="crop %s: %s" % ((x, y, w, h), what))
        assert_statistically_equal(a, b, blocks=1, mask=ring,
                                   what="crop %s: %s, border ring" % ((x, y, w, h), what))


def _lit_plane(**film):
    """A diffuse plane filling a 20x14 view, lit by a point light near it: every pixel,
    those on the film's edges included, gets light by both path tracing (s = 1) and
    light tracing (t = 1), and nothing else (max_depth 2)."""
    f = {"type": "hdrfilm", "width": 20, "height": 14, "pixel_format": "rgb"}
    f.update(film)
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40, "film": f,
                   "to_world": T().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0])},
        "plane": {"type": "rectangle", "to_world": T().scale(5), "bsdf": {"type": "diffuse"}},
        "light": {"type": "point", "position": [0.3, 0.2, 1.0],
                  "intensity": {"type": "rgb", "value": [5.0, 5.0, 5.0]}}})


@pytest.mark.parametrize("film", [
    {"rfilter": {"type": "gaussian"}},
    {"rfilter": {"type": "lanczos"}},
    {"rfilter": {"type": "gaussian"}, "sample_border": True},
    {"rfilter": {"type": "tent"}, "crop_offset_x": 3, "crop_offset_y": 2, "crop_width": 13,
     "crop_height": 9},
], ids=["gaussian", "lanczos", "gaussian, sampled border", "tent, crop window"])
def test_light_image_edges_agree_with_camera_samples(film):
    """Light tracing alone (t = 1) and path tracing alone (s <= 1) give the same pixels
    on the film's outermost ring, with filters wider than a pixel (film.py: splats
    carry raw filter weights and each pixel is divided by its filter's integral over
    the sampled region, as develop normalizes camera samples).  Failed before: splat
    footprints were normalized to one where they landed, as in Mitsuba's ptracer, and
    light tracing's edge pixels read 15% below path tracing's with a Gaussian filter
    (t = -3 to -11 per pixel); a sampled border also lay outside what t = 1 reached."""
    scene = _lit_plane(**film)
    lt = [render(scene, 64, SEED + s, max_depth=2, strategy_subset="lt").image
          for s in range(SEEDS)]
    pt = [render(scene, 64, REF_SEED + s, max_depth=2, strategy_subset="pt").image
          for s in range(SEEDS)]
    h, w = lt[0].shape[:2]
    ring = np.ones((h, w), bool)
    ring[1:-1, 1:-1] = False
    assert all(np.isfinite(i).all() for i in lt + pt)
    assert_statistically_equal(lt, pt, blocks=1, mask=ring, what="%s: the edge ring" % film)
    assert_statistically_equal(lt, pt, blocks=2, what="%s: the image" % film)


def _tap_sum_range(rfilter: str) -> tuple:
    """The least and largest sum of a filter's weights over the pixel centres around
    a film position, over the position's offset within its pixel, relative to the
    filter's integral: 1 for a partition of unity (box, tent)."""
    f = mi.load_dict({"type": rfilter})
    u = np.linspace(-f.radius(), f.radius(), 8193)
    integral = np.trapezoid(np.array(f.eval(mi.Float(u.astype(np.float32)))), u)
    taps = np.arange(-8, 9) + 0.5
    sums = [np.array(f.eval(mi.Float((taps - p).astype(np.float32)))).sum()
            for p in np.linspace(0.0, 1.0, 257)]
    return min(sums) / integral, max(sums) / integral


def test_filters_preserve_light_image_energy():
    """Box, tent and Gaussian filters (and a Gaussian with border sampling) give the
    light image (all t = 1 strategies, summed over pixels) the same total, up to
    noise.  A splat at film position p gives pixel j its raw weight w_j(p) over the
    filter's integral (film.py), as develop weights a camera sample, so a splat's
    weights sum to one on average over p, and exactly for every p only for a
    partition of unity (box, tent); a Gaussian's sum ripples by ~1.4% with p's offset
    in its pixel, in Mitsuba's camera samples as here.  film-caustic.xml keeps the
    caustic 7 pixels away from every edge (2e-4 of the light image's energy lies in
    the outer 6 pixels)."""
    def totals(film):
        return [np.full((1, 1, 3), light_image(r).sum(axis=(0, 1))) for r in film_runs(**film)]
    box = totals({})
    assert box[0].min() > 0
    # Without border sampling every filter sees the same light paths (the same random
    # numbers), so the totals agree seed by seed within the filter's ripple (and the
    # 2e-4 at the edges).
    for rfilter in ["tent", "gaussian"]:
        low, high = _tap_sum_range(rfilter)
        ratio = np.array(totals({"rfilter": rfilter})) / np.array(box)
        assert (ratio > low * low - 1e-3).all() and (ratio < high * high + 1e-3).all(), \
            (rfilter, ratio.min(), ratio.max(), low, high)
    for film in [{"rfilter": "tent"}, {"rfilter": "gaussian"},
                 {"rfilter": "gaussian", "sample_border": True}]:
        other = totals(film)
        assert all(np.isfinite(t).all() for t in other)
        assert_statistically_equal(other, box, blocks=1, what="light image energy, %s" % film)


@pytest.mark.auto_budget
def test_a_vertex_cache_with_no_stored_vertex_reads_no_record():
    """At max_depth 2 no light vertex is stored, yet the pilot may choose a vertex
    cache (connections=2).  Its picks read record 0 of the empty pool, memory that
    earlier passes had filled: the camera walk of pass 5 crashed (a segfault; 64x64,
    2048 spp, ~1.2M lanes per pass, Cornell box).  An empty pool now yields no pick.
    The unit costs are pinned where the pilot chooses one (the tests' units of
    2026-11-26; with other prices it may path-trace)."""
    from bdpt_drjit.render import Renderer
    from bdpt_drjit.units import UnitCosts
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=64, resy=64)
    r = Renderer(scene, spp=2048, seed=1, max_depth=2, unit_costs=UnitCosts(
        camera_ray=1.25e-7, light_ray=1.45e-7, stored_vertex=8e-8, connection=2.3e-7,
        path_ray=1.2e-7, grid_vertex=1.9e-7, merge_step=5.6e-8))
    while not r.done:
        r.run_pass()
    res = r.result()
    assert res.stats["budget"].endswith("connections=2"), res.stats["budget"]
    assert np.all(np.isfinite(res.image))
