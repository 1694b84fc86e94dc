"""Shared test fixtures and helpers: scene paths, the shared external scenes, Mitsuba's
own renders, the 16x16 Cornell box.  The statistics are in stats.py."""
import os
import sys
from pathlib import Path

import numpy as np
import pytest

# Fixed unit costs (units.py) for every render of the tests and their subprocesses: an
# "auto" budget's decision then depends on the scene and seed alone, not on this
# machine's calibration.
os.environ.setdefault("BDPT_CALIBRATION", str(Path(__file__).resolve().parent / "calibration.json"))

import bdpt_drjit  # noqa: F401,E402  (selects llvm_ad_rgb, registers "bdpt")
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


def cli_env(env=None) -> dict:
    """The environment of a subprocess (CLI, benchmarks): it imports bdpt_drjit from this
    checkout (not an installed copy, which a subprocess run elsewhere would find), and
    keeps any PYTHONPATH that the tests' own packages came from."""
    full_env = dict(os.environ)
    full_env["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    full_env.update(env or {})
    return full_env


def mitsuba_render(scene, integrator: str, spp: int, seed: int, **props) -> np.ndarray:
    integ = mi.load_dict({"type": integrator, **props})
    return np.array(mi.render(scene, integrator=integ, spp=spp, seed=seed))


_VARIANT_CHECK = r"""
import sys, numpy as np, mitsuba as mi
mi.set_variant(sys.argv[1])
import bdpt_drjit
sc = mi.load_file(sys.argv[2], resx=16, resy=16)
b = [bdpt_drjit.render(sc, spp=32, seed=s, max_depth=4, light_paths=1, connections="all").image.mean()
     for s in range(8)]
p = [np.array(mi.render(sc, integrator=mi.load_dict({'type': sys.argv[3], 'max_depth': 4}),
                        spp=128, seed=50 + s)).mean() for s in range(8)]
se = np.sqrt(np.var(b, ddof=1) / 8 + np.var(p, ddof=1) / 8)
t = abs(np.mean(b) - np.mean(p)) / se
print('%s bdpt %.5f %s %.5f t %.2f' % (sys.argv[1], np.mean(b), sys.argv[3], np.mean(p), t))
sys.exit(0 if t < 5.4 else 1)   # t_{14 dof} quantile at p = 1e-4
"""


def assert_agrees_in_variant(variant: str, scene: str, integrator: str) -> None:
    """bdpt and Mitsuba's ``integrator`` agree (whole-image mean, 8 seeds each) in
    another variant, in a subprocess (a process keeps the variant it renders in).
    Skipped where Mitsuba was installed without that variant (a GPU machine's
    stripped wheel)."""
    import importlib.util
    import subprocess
    if importlib.util.find_spec(f"mitsuba.{variant}") is None:
        pytest.skip(f"Mitsuba's {variant} variant is not installed here")
    p = subprocess.run([sys.executable, "-c", _VARIANT_CHECK, variant, scene, integrator],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr


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


@pytest.fixture(autouse=True)
def fixed_budget(request, monkeypatch):
    """Renders here use full BDPT (light_paths 1, connections "all"), so that every
    strategy is tested, unless a test is marked ``auto_budget`` (the default budget,
    chosen from the pilot's counts and the fixed unit costs above: deterministic too)."""
    if request.node.get_closest_marker("auto_budget") is None:
        from bdpt_drjit.budgets import BDPT, fixed_budget as fixed
        render_module = sys.modules["bdpt_drjit.render"]
        monkeypatch.setattr(render_module, "fixed_budget", lambda s: fixed(s) or BDPT)


@pytest.fixture(scope="module")
def box():
    """The Cornell box at 16x16 (one per test module)."""
    return mi.load_file(scene_path("cornell-box.xml"), resx=16, resy=16)
