"""Statistics of the tests: estimators compared over independent seeds.

Every comparison is a t-test on block means (the whole image and blocks x blocks
regions); the threshold is the two-sided Student-t quantile from ``scipy.stats``."""
import numpy as np
from scipy.stats import t as student_t


def seed_stats(images):
    """Mean image and standard error of the mean, from independent renders."""
    a = np.stack(images)
    return a.mean(axis=0), a.std(axis=0, ddof=1) / np.sqrt(len(images))


def t_threshold(dof: float, p: float) -> float:
    """Two-sided Student-t quantile: |T| exceeds it with probability p at ``dof``
    degrees of freedom."""
    return float(student_t.isf(p / 2, dof))


def regions(h: int, w: int, blocks: int) -> list:
    """The whole image, then blocks x blocks regions of an (h, w) image, as slices."""
    out = [(slice(None), slice(None))]
    for i in range(blocks):
        for j in range(blocks):
            out.append((slice(i * h // blocks, (i + 1) * h // blocks),
                        slice(j * w // blocks, (j + 1) * w // blocks)))
    return out


def welch_dof(va: float, vb: float, na: int, nb: int) -> float:
    """Welch-Satterthwaite degrees of freedom of a difference of two means whose
    squared standard errors are va and vb, from na and nb samples."""
    return (va + vb) ** 2 / ((va ** 2 / (na - 1) if va else 0) + (vb ** 2 / (nb - 1) if vb else 0))


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
    worst = 0.0
    for r in regions(*a.shape[1:], blocks):
        if np.isnan(a[(0,) + r]).all():
            continue
        ma = np.nanmean(a[(slice(None),) + r], axis=(1, 2))
        mb = np.nanmean(b[(slice(None),) + r], axis=(1, 2))
        va, vb = ma.var(ddof=1) / len(ma), mb.var(ddof=1) / len(mb)
        diff = abs(ma.mean() - mb.mean())
        se = np.sqrt(va + vb)
        if se == 0:
            # Deterministic on both sides (e.g. a constant sky seen through nothing):
            # equal up to float32 rounding of the two films' sums (1.25e-6 at ~0.3, ~40 ulp, seen).
            assert diff < 1e-6 + 1e-5 * abs(mb.mean()), "%s: region %s differs by %g with zero variance" % (what, r, diff)
            continue
        dof = welch_dof(va, vb, len(ma), len(mb))
        t_max = t_threshold(dof, p_false)
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
    t_max = t_threshold(len(a) - 1, p_false)
    for reg in regions(*r_img.shape, blocks):
        m = a[(slice(None),) + reg].mean(axis=(1, 2))
        r = r_img[reg].mean()
        var = m.var(ddof=1) / len(m) + (rel_floor * r) ** 2
        if v_img is not None:
            var += v_img[reg].mean() / (ref_spp * v_img[reg].size)
        t = abs(m.mean() - r) / max(np.sqrt(var), 1e-12)
        assert t < t_max, ("%s: region %s mean %.5g vs reference %.5g (t=%.1f > %.1f)"
                           % (what, reg, m.mean(), r, t, t_max))
