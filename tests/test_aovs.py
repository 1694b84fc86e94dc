"""AOVs written by bdpt itself (bdpt_drjit/aovs.py): Mitsuba's ``aov`` integrator
cannot nest bdpt, so ``aovs`` gives a denoiser its albedo, normals and depth beside
the image, matching what ``aov`` writes around ``path``."""
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit
from bdpt_drjit.exr import read_channels
from conftest import ROOT, SCENES
from stats import assert_statistically_equal

SPEC = "al:albedo,nn:sh_normal,gn:geo_normal,dd:depth,pp:position,uv:uv"
GROUPS = {"albedo": (0, 3), "sh_normal": (3, 6), "geo_normal": (6, 9), "depth": (9, 10),
          "position": (10, 13), "uv": (13, 15)}


@pytest.fixture(scope="module")
def box():
    return mi.load_file(str(SCENES / "cornell-box.xml"), resx=16, resy=16)


def test_aovs_match_mitsubas_aov_integrator(box):
    ours = [bdpt_drjit.render(box, spp=16, seed=s, max_depth=3, aovs=SPEC).image[..., 3:]
            for s in range(6)]
    integrator = mi.load_dict({"type": "aov", "aovs": SPEC, "img": {"type": "path"}})
    theirs = [np.array(mi.render(box, integrator=integrator, spp=16, seed=50 + s))[..., 3:]
              for s in range(6)]
    assert ours[0].shape == theirs[0].shape == (16, 16, 15)
    for kind, (a, b) in GROUPS.items():
        assert_statistically_equal([x[..., a:b] for x in ours], [x[..., a:b] for x in theirs],
                                   what=kind)


def test_channels_and_image_unchanged(box):
    plain = bdpt_drjit.render(box, spp=4, seed=3, max_depth=3, strategy_subset="pt")
    res = bdpt_drjit.render(box, spp=4, seed=3, max_depth=3, strategy_subset="pt",
                            aovs="al:albedo,dd:depth,si:shape_index")
    assert res.channels == ["R", "G", "B", "al.R", "al.G", "al.B", "dd.T", "si.I"]
    assert np.array_equal(res.image[..., :3], plain.image)       # path tracing: bit-identical
    shapes = box.shapes()
    index = res.image[..., -1]
    # Every value is 0 (nothing hit) or a pixel's average of 1 + places in scene.shapes().
    assert index.min() >= 0 and index.max() <= len(shapes)
    # The centre pixel sees one surface: its shape's place, counted from 1.
    ray, _ = box.sensors()[0].sample_ray(0.0, 0.5, mi.Point2f(0.5, 0.5), mi.Point2f(0.5))
    hit = box.ray_intersect(ray).shape
    place = [i + 1 for i, s in enumerate(shapes) if dr.all(mi.ShapePtr(s) == hit)]
    assert index[8, 8] == place[0]


@pytest.mark.parametrize("spec, message", [
    ("a:duv_dx", "ray differentials"), ("a:wobble", "unknown type 'wobble'"),
    ("albedo", "not a <name>:<type> pair")])
def test_bad_aov_lists_are_refused(box, spec, message):
    with pytest.raises(ValueError, match=message):
        bdpt_drjit.render(box, spp=1, aovs=spec)


def test_plugin_and_cli_name_the_channels(box, tmp_path):
    integrator = mi.load_dict({"type": "bdpt", "max_depth": 3, "aovs": "nn:sh_normal"})
    assert integrator.aov_names() == ["nn.X", "nn.Y", "nn.Z"]
    assert np.array(mi.render(box, integrator=integrator, spp=2)).shape == (16, 16, 6)
    out = tmp_path / "box.exr"
    subprocess.run([sys.executable, "-m", "bdpt_drjit", "render", str(SCENES / "cornell-box.xml"),
                    "--res", "8x8", "--spp", "2", "--aovs", "al:albedo,dd:depth", "-o", str(out)],
                   check=True, cwd=ROOT, capture_output=True, timeout=300)
    channels, _ = read_channels(str(out))
    assert {"R", "G", "B", "al.R", "al.G", "al.B", "dd.T"} <= set(channels)
