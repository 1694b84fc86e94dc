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


def assert_statistically_equal(a_imgs, b_imgs, blocks=4, z_max=4.5, what=""):
    """Two estimators agree: compare block means (blocks x blocks regions of the
    image, and the whole image) with a z-test whose variance comes from the seeds
    of both.  Block means pool pixels so the central limit theorem applies; the
    threshold 4.5 keeps the family-wise false alarm rate below 1e-4 for the
    ~20 comparisons per call."""
    a = np.stack(a_imgs).mean(axis=-1)
    b = np.stack(b_imgs).mean(axis=-1)
    h, w = a.shape[1:]
    regions = [(slice(None), slice(None))]
    for i in range(blocks):
        for j in range(blocks):
            regions.append((slice(i * h // blocks, (i + 1) * h // blocks),
                            slice(j * w // blocks, (j + 1) * w // blocks)))
    worst = 0.0
    for r in regions:
        ma = a[(slice(None),) + r].mean(axis=(1, 2))
        mb = b[(slice(None),) + r].mean(axis=(1, 2))
        se = np.sqrt(ma.var(ddof=1) / len(ma) + mb.var(ddof=1) / len(mb))
        diff = abs(ma.mean() - mb.mean())
        if se == 0:
            assert diff < 1e-6, "%s: region %s differs by %g with zero variance" % (what, r, diff)
            continue
        z = diff / se
        worst = max(worst, z)
        assert z < z_max, ("%s: region %s means %.5g vs %.5g (se %.3g, z=%.1f)"
                           % (what, r, ma.mean(), mb.mean(), se, z))
    return worst
