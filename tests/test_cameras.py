"""Thin lens and orthographic cameras (camera.py), and the principal point offset.

The model: a thin lens's film position, importance and lens point agree with Mitsuba's
``sample_direction`` and ``sample_ray`` on grids (crop windows and principal point
offsets included; Mitsuba issue #1508 reported wrong thin-lens film positions before
3.7), and the density of a primary ray's direction is the Jacobian of ``sample_ray``
-- the same density the light image uses for its MIS weight at the lens point it
chose.  Renders: the Cornell box through a thin lens and an orthographic camera
matches Mitsuba's ``path``; a point-light caustic seen through a thin lens matches
``ptracer``; each single technique up to k = 4 through a thin lens matches ``path``
restricted to that length.  Statistics: stats.py, over independent seeds.
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit
from bdpt_drjit.camera import make_camera
from bdpt_drjit.render import Renderer
from conftest import SCENES
from stats import assert_statistically_equal
from test_agreement import bdpt_images, mitsuba_images, path_images_by_length
T = mi.ScalarTransform4f

# -- the model against Mitsuba's sensors ---------------------------------------------
CROP = {"crop_offset_x": 5, "crop_offset_y": 3, "crop_width": 20, "crop_height": 15}
PP = {"principal_point_offset_x": 0.1, "principal_point_offset_y": -0.05}
LENS = {"aperture_radius": 0.2, "focus_distance": 2.5}
MODELS = {
    "thin lens": ("thinlens", {}, LENS),
    "thin lens, crop, clip": ("thinlens", CROP, dict(LENS, near_clip=1.5, far_clip=4.0)),
    "pinhole, principal point": ("perspective", {}, PP),
    "pinhole, crop and principal point": ("perspective", CROP, PP),
}
THIN_LENS_MODELS = [m for m in MODELS if MODELS[m][0] == "thinlens"]
APERTURE_SAMPLES = [(0.5, 0.5), (0.1, 0.9), (0.93, 0.2), (0.3, 0.35), (0.7, 0.62)]


def sensor(case):
    kind, crop, params = MODELS[case]
    return mi.load_dict({"type": kind, "fov": 50, **params,
                         "to_world": T().look_at(origin=[0.3, 0.5, 3], target=[0, 0, 0],
                                                 up=[0.1, 1, 0]),
                         "film": {"type": "hdrfilm", "width": 40, "height": 24, **crop}})


def points(n, seed):
    it = dr.zeros(mi.Interaction3f, n)
    it.p = mi.Point3f(*np.random.default_rng(seed).uniform(-2.0, 2.0, (3, n)).astype(np.float32))
    return it


def grid(n, aperture):
    """Film samples on an n x n grid, each with the aperture sample ``aperture``."""
    g = (np.arange(n) + 0.5) / n
    u, v = (a.ravel().astype(np.float32) for a in np.meshgrid(g, g))
    return mi.Point2f(u, v), mi.Point2f(np.full(n * n, aperture[0], np.float32),
                                        np.full(n * n, aperture[1], np.float32))


def arr(x):
    return np.array(x, dtype=np.float64)


@pytest.mark.parametrize("case", THIN_LENS_MODELS)
def test_thin_lens_connect_matches_sample_direction(case):
    """Random points through random lens samples: film position, importance, lens
    point and direction as Mitsuba's thinlens ``sample_direction``.  Except outside
    the clip range: Mitsuba 3.9.1's thinlens tests it only to return early when no
    lane passes, and then accepts points its own camera rays (which start on the
    near plane and end on the far one) never reach; the model refuses them."""
    s = sensor(case)
    cam = make_camera(s)
    it = points(20000, 1)
    u = mi.Point2f(*np.random.default_rng(2).uniform(size=(2, 20000)).astype(np.float32))
    ds, imp = s.sample_direction(it, u)
    conn = cam.connect(it.p, u)
    depth = arr((cam.to_local @ it.p).z)
    clipped = (depth < arr(cam.near)) | (depth > arr(cam.far))
    valid = np.array(ds.pdf > 0) & (arr(mi.unpolarized_spectrum(imp)[0]) > 0)
    assert (valid & clipped).any() == ("clip" in case)         # Mitsuba's lapse
    valid &= ~clipped
    assert np.array_equal(np.array(conn.valid), valid)
    assert valid.sum() > 1000
    np.testing.assert_allclose(arr(conn.uv)[:, valid], arr(ds.uv)[:, valid], atol=2e-3)
    np.testing.assert_allclose(arr(conn.importance)[valid],
                               arr(mi.unpolarized_spectrum(imp)[0])[valid], rtol=1e-4)
    np.testing.assert_allclose(arr(conn.p)[:, valid], arr(ds.p)[:, valid], atol=1e-6)
    np.testing.assert_allclose(arr(conn.d)[:, valid], arr(ds.d)[:, valid], atol=1e-5)


@pytest.mark.parametrize("case", MODELS)
@pytest.mark.parametrize("aperture", APERTURE_SAMPLES)
def test_connect_inverts_sample_ray(case, aperture):
    """A point on a camera ray, connected through the ray's own lens sample, lands at
    the ray's film sample (and so does Mitsuba's ``sample_direction``: issue #1508);
    the lens point is the ray's z_0, which lies on the ray behind its origin on the
    near clip plane."""
    s = sensor(case)
    cam = make_camera(s)
    u, ua = grid(24, aperture)
    ray, _ = s.sample_ray(0.0, 0.5, u, ua)
    depth = np.random.default_rng(3).uniform(0.05, 1.0, 576).astype(np.float32)
    p = ray.o + ray.d * mi.Float(depth)
    conn = cam.connect(p, ua)
    assert np.array(conn.valid).all()
    res = arr(cam.resolution)[:, :1]
    np.testing.assert_allclose(arr(conn.uv), arr(u) * res, atol=2e-3)
    z0 = arr(cam.origin(ray, ua))
    np.testing.assert_allclose(arr(conn.p), z0, atol=1e-6)
    along = np.sum((arr(ray.o) - z0) * arr(ray.d), axis=0)       # z_0 -> origin along d
    np.testing.assert_allclose(arr(ray.o), z0 + along * arr(ray.d), atol=1e-5)
    assert (along > 0).all()
    it = dr.zeros(mi.Interaction3f, 576)
    it.p = p
    ds, _ = s.sample_direction(it, ua)
    np.testing.assert_allclose(arr(ds.uv), arr(u) * res, atol=2e-3)


@pytest.mark.parametrize("case", MODELS)
def test_direction_density_is_the_jacobian_of_sample_ray(case):
    """The solid-angle density of a primary ray's direction from its lens point is
    1 / |d(omega) / d(film sample)|, by central differences of Mitsuba's
    ``sample_ray`` at a fixed aperture sample (camera.Camera's derivation); and the
    light image's density at a point of the ray, connected through the same lens
    point (importance * d^2), is the same number."""
    s = sensor(case)
    cam = make_camera(s)
    h = 1e-3
    for aperture in APERTURE_SAMPLES[:3]:
        u, ua = grid(20, aperture)
        u = mi.Point2f(0.05 + 0.9 * u.x, 0.05 + 0.9 * u.y)

        def direction(du, dv):
            return arr(s.sample_ray(0.0, 0.5, mi.Point2f(u.x + du, u.y + dv), ua)[0].d)
        d_u = (direction(h, 0) - direction(-h, 0)) / (2 * h)
        d_v = (direction(0, h) - direction(0, -h)) / (2 * h)
        jacobian_pdf_w = 1.0 / np.linalg.norm(np.cross(d_u, d_v, axis=0), axis=0)
        ray, _ = s.sample_ray(0.0, 0.5, u, ua)
        pdf_w = arr(cam.direction_pdf_w(ray.d))
        np.testing.assert_allclose(pdf_w, jacobian_pdf_w, rtol=2e-3)
        conn = cam.connect(ray.o + ray.d * 0.5, ua)
        np.testing.assert_allclose(arr(conn.importance * dr.square(conn.dist)), pdf_w, rtol=1e-4)


@pytest.mark.parametrize("case", MODELS)
@pytest.mark.parametrize("light_ratio", [1.0, 0.3])
def test_weights_at_the_camera_vertex_sum_to_one(case, light_ratio):
    """MIS with the engine's own camera quantities: a path z_0 -> x of one edge (x on
    an emitter), made by a camera ray from its lens point (s = 0, the walk's chains
    start from ``origin`` and ``direction_pdf_w``) or by connecting x through the same
    lens sample ((1,1), ``connect``).  The two weights sum to one only if both sides
    use the same z_0 and the same density (the lens pdf cancels, camera.Camera)."""
    from bdpt_drjit.mis import Weights
    from bdpt_drjit.settings import Settings
    from bdpt_drjit.strategies import StrategySet
    s = sensor(case)
    cam = make_camera(s)
    rng = np.random.default_rng(4)
    u, _ = grid(24, (0.5, 0.5))
    ua = mi.Point2f(*rng.uniform(size=(2, 576)).astype(np.float32))
    ray, _ = s.sample_ray(0.0, 0.5, u, ua)
    z0 = cam.origin(ray, ua)
    x = mi.Point3f(ray.o + ray.d * mi.Float(rng.uniform(0.2, 2.0, 576).astype(np.float32)))
    n = dr.normalize(mi.Vector3f(*rng.normal(size=(3, 576)).astype(np.float32)))
    pos_pdf_a = mi.Float(rng.uniform(0.05, 5.0, 576).astype(np.float32))
    weights = Weights("power", StrategySet(Settings(), True))
    weights.set_rates(light_ratio, 1.0)
    d_vcm, d_vc = weights.camera_start(cam.direction_pdf_w(ray.d))
    d_vcm, d_vc = weights.after_hit(d_vcm, d_vc, dr.squared_norm(x - z0), dr.abs(dr.dot(n, ray.d)))
    w_hit = weights.emission_hit(d_vcm, d_vc, 1.0, mi.Bool(True), 0.0, pos_pdf_a, 1.0)
    conn = cam.connect(x, ua)
    assert np.array(conn.valid).all()
    w_image = weights.emitter_to_camera(conn.importance * dr.abs(dr.dot(n, conn.d)), pos_pdf_a)
    total = arr(w_hit) + arr(w_image)
    assert arr(w_image).min() < 0.2 and arr(w_image).max() > 0.8    # both strategies matter
    np.testing.assert_allclose(total, 1.0, rtol=1e-4)


# -- renders --------------------------------------------------------------------------
def with_sensor(name: str, sensor_xml: str, res: int, film_xml: str = "") -> mi.Scene:
    """A scene file of scenes/ with its sensor's type, parameters and transform
    replaced (its sampler and film kept; ``film_xml`` added to the film)."""
    text = (SCENES / name).read_text()
    start = text.index('<sensor type="perspective">')
    end = text.index("<sampler", start)
    text = text[:start] + sensor_xml + text[end:]
    text = text.replace('<rfilter type="box"/>', film_xml + '<rfilter type="box"/>', 1)
    return mi.load_string(text, resx=res, resy=res)


def thin_lens(aperture, focus, fov, origin, target, fov_axis="x"):
    return ('<sensor type="thinlens"><float name="aperture_radius" value="%g"/>'
            '<float name="focus_distance" value="%g"/><float name="fov" value="%g"/>'
            '<string name="fov_axis" value="%s"/><transform name="to_world">'
            '<lookat origin="%s" target="%s" up="0, 1, 0"/></transform>'
            % (aperture, focus, fov, fov_axis, origin, target))


def cornell_thin_lens(aperture, res=24, film_xml=""):
    """The Cornell box through a thin lens focused on its back wall (4.9 away)."""
    return with_sensor("cornell-box.xml", thin_lens(aperture, 4.9, 39.3077, "0, 0, 3.9",
                                                    "0, 0, 0", "smaller"), res, film_xml)


ORTHOGRAPHIC = ('<sensor type="orthographic"><transform name="to_world">'
                '<lookat origin="0.3, -0.4, 3.9" target="0, 0, 0" up="0, 1, 0"/>'
                '<scale x="1.2" y="1.2"/></transform>')


def assert_matches(ours, ref, what):
    assert all(np.isfinite(i).all() for i in ours)
    assert_statistically_equal(ours, ref, what=what)


@pytest.mark.parametrize("aperture", [0.08, 0.5])
def test_cornell_box_through_a_thin_lens_matches_path(aperture):
    """0.08: the lens the issue names; 0.5: a blur of several pixels, where a light
    image through the wrong lens point would show."""
    scene = cornell_thin_lens(aperture)
    assert_matches(bdpt_images(scene, 32, max_depth=8),
                   mitsuba_images(scene, "path", 128, max_depth=8), "thin lens %g" % aperture)


def test_thin_lens_crop_window_matches_path():
    scene = cornell_thin_lens(0.5, film_xml='<integer name="crop_offset_x" value="5"/>'
                              '<integer name="crop_offset_y" value="3"/><integer '
                              'name="crop_width" value="14"/><integer name="crop_height" '
                              'value="12"/>')
    assert tuple(scene.sensors()[0].film().crop_size()) == (14, 12)
    assert_matches(bdpt_images(scene, 32, max_depth=8),
                   mitsuba_images(scene, "path", 128, max_depth=8), "thin lens, crop")


def test_cornell_box_through_an_orthographic_camera_matches_path():
    """Seen from below (the light shows directly): no light image, each lane's z_0
    on the film plane."""
    scene = with_sensor("cornell-box.xml", ORTHOGRAPHIC, 24)
    ours = bdpt_images(scene, 32, max_depth=8)
    assert_matches(ours, mitsuba_images(scene, "path", 128, max_depth=8), "orthographic")
    assert np.mean(ours) > 0.05


def test_point_light_caustic_through_a_thin_lens_matches_particle_tracer():
    """Only light tracing (t = 1, through the lens) samples these paths: the point
    light cannot be hit and the glass ball is a delta BSDF.  Focused on the caustic."""
    scene = with_sensor("point-caustic.xml", thin_lens(0.1, 1.345, 60, "0, 0.9, 1.2",
                                                       "0, 0, 0.2"), 24)
    ours = bdpt_images(scene, 32, max_depth=8)
    assert_matches(ours, mitsuba_images(scene, "ptracer", 128, max_depth=8), "caustic, thin lens")
    path = mitsuba_images(scene, "path", 64, seeds=1, max_depth=8)[0]
    assert np.mean(ours) > 2 * path.mean()


@pytest.fixture(scope="module")
def lens_box():
    return cornell_thin_lens(0.5, res=16)


@pytest.fixture(scope="module")
def path_by_length(lens_box):
    """Mitsuba's path restricted to paths of exactly k edges, through the lens."""
    return path_images_by_length(lens_box)


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_every_single_technique_through_a_thin_lens_matches_path(lens_box, path_by_length, k):
    """Each (s,t) alone, unweighted: (s,1) through the lens sample, t >= 2 from the
    camera rays' lens points."""
    for s in range(k + 1):
        imgs = bdpt_images(lens_box, 32, technique=(s, k + 1 - s), max_depth=k)
        assert_matches(imgs, path_by_length[k], "technique (%d,%d)" % (s, k + 1 - s))


# -- the orthographic camera's strategies ---------------------------------------------
@pytest.mark.auto_budget
def test_orthographic_auto_budget_never_spends_light_subpaths_on_nothing():
    """Without a light image, light subpaths only serve connections: the optimizer's
    candidates with light subpaths and no connections are gone, and the render works."""
    scene = with_sensor("cornell-box.xml", ORTHOGRAPHIC, 16)
    r = Renderer(scene, spp=32, seed=1, max_depth=8)
    assert r.pilot is not None
    assert all(b.light_ratio == 0 or b.connects for b in r.pilot.candidates)
    assert any(b.light_ratio > 0 for b in r.pilot.candidates)
    while not r.done:
        r.run_pass()
    result = r.result()
    assert np.isfinite(result.image).all() and result.image.mean() > 0.05
    budget = result.stats["budget"]
    assert "connections=0" not in budget or "light_paths=0" in budget, budget


@pytest.mark.parametrize("settings", [{"strategy_subset": "lt"}, {"technique": "2,1"}])
def test_orthographic_camera_refuses_light_tracing(settings):
    scene = with_sensor("cornell-box.xml", ORTHOGRAPHIC, 8)
    with pytest.raises(ValueError, match="'orthographic' sensor: its direction is a delta"):
        bdpt_drjit.render(scene, spp=1, **settings)


def test_info_reports_the_cameras_supported(tmp_path):
    from test_cli import ok, run_cli
    text = (SCENES / "cornell-box.xml").read_text()
    start = text.index('<sensor type="perspective">')
    end = text.index("<sampler", start)
    for name, xml in [("thinlens", thin_lens(0.08, 4.9, 39.3, "0, 0, 3.9", "0, 0, 0")),
                      ("orthographic", ORTHOGRAPHIC)]:
        path = tmp_path / ("%s.xml" % name)
        path.write_text(text[:start] + xml + text[end:])
        out = ok(run_cli("info", path, "-D", "resx=8", "-D", "resy=8")).stdout
        assert "sensor:     %s" % name in out
        assert "status:     supported" in out, out


def test_a_new_lens_or_film_recompiles_no_walk():
    """The lens's radius and focus distance are opaque, like the film size: another
    thin lens or film compiles no walk (test_kernels.py's rule; both scenes are loaded
    first, as there: a scene loaded later adds instances to Dr.Jit's call domains,
    which changes every kernel that calls a BSDF or emitter).  The thin lens's camera
    rays (~470 operations: Mitsuba's sample_ray with its disk warp) bake the film size
    and aperture as the pinhole's do; the walks have 850-2400."""
    from test_kernels import compiled, launches
    first = cornell_thin_lens(0.08, res=24)
    other = with_sensor("cornell-box.xml", thin_lens(0.3, 3.0, 45, "0.2, 0, 3.9", "0, 0, 0"),
                        res=40)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        launches(lambda: bdpt_drjit.render(first, spp=4, seed=1))
        big = [e for e in compiled(launches(lambda: bdpt_drjit.render(other, spp=5, seed=2)))
               if e.get("operation_count", 0) > 600]
    assert not big, ["%d ops" % e["operation_count"] for e in big]
