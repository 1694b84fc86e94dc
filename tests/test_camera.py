"""The camera model (camera.Camera) is Mitsuba's perspective sensor: where a point
projects, the importance toward it and the density of a primary ray's direction agree
with ``sensor.sample_direction`` and ``sensor.sample_ray``, crop windows and principal
point offsets included.

One difference, with a principal point offset: Mitsuba's ``importance()`` tests the
direction against the film rectangle *without* the offset, while ``sample_ray`` and
``sample_direction``'s film position shift it; so Mitsuba returns importance 0 for
points in a strip its own camera rays see (its ptracer leaves that strip dark).  The
model uses the shifted rectangle, the one primary rays cover (checked against the
Jacobian of ``sample_ray`` in tests/test_cameras.py).  Thin lens and orthographic
cameras: tests/test_cameras.py."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit  # noqa: F401  (sets the variant)
from bdpt_drjit.camera import Camera

T = mi.ScalarTransform4f


def sensor(**film):
    d = {"type": "perspective", "fov": 50,
         "to_world": T().look_at(origin=[0.3, 0.5, 3], target=[0, 0, 0], up=[0.1, 1, 0]),
         "film": {"type": "hdrfilm", "width": 40, "height": 24, **film}}
    if "pp" in film:
        film.pop("pp")
        d["principal_point_offset_x"], d["principal_point_offset_y"] = 0.1, -0.05
        d["film"].pop("pp")
    return mi.load_dict(d)


CASES = {"plain": {}, "crop": {"crop_offset_x": 5, "crop_offset_y": 3, "crop_width": 20,
                               "crop_height": 15}, "principal point": {"pp": True}}


@pytest.mark.parametrize("case", CASES)
def test_connect_matches_sample_direction(case):
    s = sensor(**CASES[case])
    cam = Camera(s)
    rng = np.random.default_rng(1)
    p = mi.Point3f(*rng.uniform(-2.0, 2.0, size=(3, 20000)).astype(np.float32))
    it = dr.zeros(mi.Interaction3f, 20000)
    it.p = p
    ds, imp = s.sample_direction(it, mi.Point2f(0.5))
    conn = cam.connect(p, mi.Point2f(0.5))
    on_film = np.array(ds.pdf > 0)          # Mitsuba's clip range and film position tests
    assert np.array_equal(np.array(conn.valid), on_film)
    valid = on_film & (np.array(mi.unpolarized_spectrum(imp)[0]) > 0)
    # Mitsuba's unshifted importance rectangle (module docstring) cuts only with an offset.
    assert (valid != on_film).any() == (case == "principal point")
    assert valid.sum() > 2000
    np.testing.assert_allclose(np.array(conn.uv)[:, valid], np.array(ds.uv)[:, valid], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.array(conn.importance)[valid],
                               np.array(mi.unpolarized_spectrum(imp)[0])[valid], rtol=1e-5)
    np.testing.assert_allclose(np.array(conn.d)[:, valid], np.array(ds.d)[:, valid], atol=1e-6)
    np.testing.assert_allclose(np.array(conn.p)[:, 0], np.array(ds.p)[:, 0], atol=1e-6)


@pytest.mark.parametrize("case", CASES)
def test_direction_density_of_primary_rays(case):
    """The solid-angle density of a primary ray's direction is importance * d^2 at
    any point along the ray."""
    s = sensor(**CASES[case])
    cam = Camera(s)
    rng = np.random.default_rng(2)
    u = mi.Point2f(*rng.uniform(0.01, 0.99, size=(2, 5000)).astype(np.float32))
    ray, _ = s.sample_ray(0.0, 0.5, u, mi.Point2f(0.5))
    it = dr.zeros(mi.Interaction3f, 5000)
    it.p = ray.o + ray.d * 2.0
    ds, imp = s.sample_direction(it, mi.Point2f(0.5))
    expected = np.array(mi.unpolarized_spectrum(imp)[0] * dr.square(ds.dist))
    ours = np.array(cam.direction_pdf_w(ray.d))
    assert (ours > 0).all()
    seen = expected > 0                     # all but Mitsuba's strip (module docstring)
    assert seen.mean() > 0.75
    np.testing.assert_allclose(ours[seen], expected[seen], rtol=1e-4)
