"""Shared test helpers: scene paths, the shared external scenes, statistics."""
import os
from pathlib import Path

import numpy as np
import pytest

import bdpt_drjit  # noqa: F401  (selects llvm_ad_rgb, registers "bdpt")
import mitsuba as mi

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"
SHARED = Path(os.environ.get("BDPT_SHARED", ROOT.parent / "shared"))
EXTERNAL = SHARED / "scenes" / "external"


def scene_path(name: str) -> str:
    return str(SCENES / name)


def external(*parts) -> Path:
    """A scene under ../shared/scenes/external, or skip the test with a clear reason."""
    path = EXTERNAL.joinpath(*parts)
    if not path.exists():
        pytest.skip("external scene %s not found: these tests need the project's ../shared "
                    "folder (set BDPT_SHARED to its location)" % path)
    return path


def mitsuba_render(scene, integrator: str, spp: int, seed: int, **props) -> np.ndarray:
    integ = mi.load_dict({"type": integrator, **props})
    return np.array(mi.render(scene, integrator=integ, spp=spp, seed=seed))


def seed_stats(images):
    """Mean image and standard error of the mean, from independent renders."""
    a = np.stack(images)
    return a.mean(axis=0), a.std(axis=0, ddof=1) / np.sqrt(len(images))


def _t_threshold(dof: float, p: float) -> float:
    """Two-sided Student-t quantile |t| exceeded with probability p (bisection on
    the regularized incomplete beta function, to avoid a SciPy dependency)."""
    import math

    def tail(t):  # P(|T| > t) = I_{dof/(dof+t^2)}(dof/2, 1/2), by numeric integration
        x = dof / (dof + t * t)
        n = 2000   # substitution u = sqrt(y): integrand (1-u^2)^(-1/2) u^(dof-1), smooth
        a, b = dof / 2, 0.5
        um = math.sqrt(x)
        h = um / n
        acc = sum((1 - ((i + 0.5) * h) ** 2) ** (b - 1) * ((i + 0.5) * h) ** (2 * a - 1)
                  for i in range(n)) * h * 2
        return acc / math.exp(math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b))
    lo, hi = 0.0, 100.0
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if tail(mid) > p else (lo, mid)
    return hi


def specular_pixels(scene, jitter=16):
    """Boolean (H, W) mask of pixels in which some primary ray hits a surface with a
    delta BSDF lobe (glass, mirror): there a light tracer cannot see anything."""
    import drjit as dr
    sensor = scene.sensors()[0]
    w, h = (int(x) for x in sensor.film().crop_size())
    n = w * h * jitter
    idx = dr.arange(mi.UInt32, n)
    pix = idx // jitter
    rng = np.random.default_rng(0)
    u = mi.Point2f(*rng.uniform(size=(2, n)).astype(np.float32))
    pos = mi.Point2f(mi.Float(pix % w) + u.x, mi.Float(pix // w) + u.y)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos / mi.ScalarVector2f(w, h), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    delta = si.is_valid() & mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.Delta)
    return np.array(delta).reshape(h, w, jitter).any(axis=2)


def assert_statistically_equal(a_imgs, b_imgs, blocks=4, p_false=1e-4, what="", mask=None):
    """Two estimators agree: block means (the whole image and blocks x blocks regions)
    compared by Welch's t-test, the variance of each side estimated from its
    independent seeds.  Each comparison may false-alarm with probability ``p_false``
    (the threshold comes from the t distribution at Welch's degrees of freedom, so a
    few seeds do not inflate the false-alarm rate); with ~17 comparisons per call and
    the suite's few dozen calls, the whole suite false-alarms with probability < 1%.
    Seeds are fixed, so a passing test stays passing."""
    a = np.stack(a_imgs).mean(axis=-1)
    b = np.stack(b_imgs).mean(axis=-1)
    if mask is not None:                 # compare only where mask is True
        a, b = np.where(mask, a, np.nan), np.where(mask, b, np.nan)
    h, w = a.shape[1:]
    regions = [(slice(None), slice(None))]
    for i in range(blocks):
        for j in range(blocks):
            regions.append((slice(i * h // blocks, (i + 1) * h // blocks),
                            slice(j * w // blocks, (j + 1) * w // blocks)))
    worst = 0.0
    for r in regions:
        if np.isnan(a[(0,) + r]).all():
            continue
        ma = np.nanmean(a[(slice(None),) + r], axis=(1, 2))
        mb = np.nanmean(b[(slice(None),) + r], axis=(1, 2))
        va, vb = ma.var(ddof=1) / len(ma), mb.var(ddof=1) / len(mb)
        diff = abs(ma.mean() - mb.mean())
        se = np.sqrt(va + vb)
        if se == 0:
            assert diff < 1e-6, "%s: region %s differs by %g with zero variance" % (what, r, diff)
            continue
        dof = (va + vb) ** 2 / ((va ** 2 / (len(ma) - 1) if va else 0) + (vb ** 2 / (len(mb) - 1) if vb else 0))
        t_max = _t_threshold(dof, p_false)
        t = diff / se
        worst = max(worst, t / t_max)
        assert t < t_max, ("%s: region %s means %.5g vs %.5g (se %.3g, t=%.1f > %.1f at %.0f dof)"
                           % (what, r, ma.mean(), mb.mean(), se, t, t_max, dof))
    return worst


def assert_matches_reference(imgs, ref, ref_var=None, ref_spp=1, blocks=4, p_false=1e-4,
                             rel_floor=1e-3, what=""):
    """Independent renders agree with a fixed reference image: block means (the whole
    image and blocks x blocks regions) by a one-sample t-test on the renders' seeds.
    The reference's own error enters as its per-sample variance image over ``ref_spp``
    samples, plus ``rel_floor`` of its value: references rendered by another Mitsuba
    version differ by ~1e-4 where a render has no variance at all (a constant
    background seen directly)."""
    a = np.stack(imgs).mean(axis=-1)
    r_img = np.asarray(ref)[..., :3].mean(axis=-1)
    v_img = None if ref_var is None else np.asarray(ref_var)[..., :3].mean(axis=-1)
    h, w = r_img.shape
    regions = [(slice(None), slice(None))]
    for i in range(blocks):
        for j in range(blocks):
            regions.append((slice(i * h // blocks, (i + 1) * h // blocks),
                            slice(j * w // blocks, (j + 1) * w // blocks)))
    t_max = _t_threshold(len(a) - 1, p_false)
    for reg in regions:
        m = a[(slice(None),) + reg].mean(axis=(1, 2))
        r = r_img[reg].mean()
        var = m.var(ddof=1) / len(m) + (rel_floor * r) ** 2
        if v_img is not None:
            var += v_img[reg].mean() / (ref_spp * v_img[reg].size)
        t = abs(m.mean() - r) / max(np.sqrt(var), 1e-12)
        assert t < t_max, ("%s: region %s mean %.5g vs reference %.5g (t=%.1f > %.1f)"
                           % (what, reg, m.mean(), r, t, t_max))
