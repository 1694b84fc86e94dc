"""The camera: primary rays, and the camera model the strategies need.

Primary rays: one per lane (pixel x sample), as Mitsuba's own
``ADIntegrator.sample_rays`` makes them, for a range of pixels of the (crop) film,
each with its camera vertex z_0 and the density of its direction.

The model: where a point projects on the film, the sensor's importance toward it,
and the density of a primary ray's direction -- what the t = 1 strategies and the
MIS chains' camera end need.  It is Mitsuba's ``sample_direction`` (v3.9.1)
computed from the sensor's own parameters held in opaque variables: Mitsuba's
version bakes the film size into the kernel, which would recompile the light walk
for every film size.  tests/test_camera.py and tests/test_cameras.py check it
against ``sensor.sample_direction`` and ``sensor.sample_ray``.

=============  =====================  ================================  ===========
sensor         z_0 (position pdf)     direction of a primary ray        t = 1 / t = 0
=============  =====================  ================================  ===========
perspective    the pinhole (delta)    1 / (A cos^3), solid angle        yes / no
thinlens       uniform on the lens    1 / (A cos^3) from its lens       yes / left
               disk, 1 / (pi r^2)     point (see ``Camera``)            out of MIS
orthographic   uniform on the film    delta (the view direction)        no / no
               rectangle (near plane)
=============  =====================  ================================  ===========

A is the area of the visible film rectangle (crop window included) at unit distance
from the lens, cos the angle of the direction with the optical axis.  The lens
position pdf of a thin lens cancels from every MIS weight, and the t = 0 strategy
(a light subpath hitting the lens) is not evaluated: see ``Camera``.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .support import UnsupportedPluginError, plugin_name, sensor_refusal

# Mitsuba class names of the supported sensors.
PINHOLE, THIN_LENS, ORTHOGRAPHIC = "PerspectiveCamera", "ThinLensCamera", "OrthographicCamera"


@dataclass
class CameraRays:
    ray: mi.RayDifferential3f
    weight: mi.Spectrum       # sensor sampling weight (spectral response), 1 in RGB
    pos: mi.Vector2f          # film position to put the sample at
    pixel: mi.UInt32          # its crop-window pixel, row-major
    origin: mi.Point3f        # z_0: the pinhole, the lens point, or the point on the
                              # orthographic film plane (Mitsuba's rays start at the
                              # near clip plane, z_0 lies behind it)
    pdf_w: mi.Float           # solid-angle density of the ray's direction over the film
                              # (0 for an orthographic camera: a delta direction)


@dataclass
class CameraConnection:
    """A point connected to the camera (t = 1)."""
    uv: mi.Point2f            # film position in pixels of the crop window
    p: mi.Point3f             # the point on the lens (the pinhole, or the lens sample)
    d: mi.Vector3f            # unit direction from the point toward the lens
    dist: mi.Float
    importance: mi.Float      # We * cos / d^2 over the lens position pdf: the camera's
                              # solid-angle density of the direction from the lens
                              # point (1 / (A cos^3)) divided by d^2
    valid: mi.Bool            # inside the sampled film region and the clip range


class CameraModel:
    """What every camera shares: primary rays over the film and the film's pixels."""

    light_image_possible = True      # can a light vertex be connected to z_0 (t = 1)?

    def __init__(self, sensor: mi.Sensor, border: int = 0, params=None):
        """``border``: pixels around the crop window that camera samples cover (a film
        that samples its filter border), where ``connect`` reaches the film too: every
        strategy then samples the same film region, as the MIS weights assume.
        ``params``: the sensor's ``mi.traverse``, where the caller has it."""
        self.sensor = sensor
        params = mi.traverse(sensor) if params is None else params
        self.to_world = mi.AffineTransform4f(params["to_world"])
        self.to_local = self.to_world.inverse()
        self.resolution = mi.Vector2f(mi.ScalarVector2f(sensor.film().crop_size()))
        self.border = mi.Float(border)
        self.near = mi.Float(params["near_clip"])
        self.far = mi.Float(params["far_clip"])
        dr.make_opaque(self.to_world, self.to_local, self.resolution, self.border, self.near,
                       self.far)

    def pixel_index(self, uv: mi.Point2f) -> mi.UInt32:
        """The crop-window pixel (row-major) of a film position in pixels."""
        x = dr.clip(mi.Int32(dr.floor(uv.x)), 0, mi.Int32(self.resolution.x) - 1)
        y = dr.clip(mi.Int32(dr.floor(uv.y)), 0, mi.Int32(self.resolution.y) - 1)
        return mi.UInt32(y * mi.Int32(self.resolution.x) + x)

    def grid_index(self, uv: mi.Point2f) -> mi.UInt32:
        """The index in sample_rays' pixel grid (crop window plus any sampled filter
        border) of the pixel holding a film position of the crop window."""
        film = self.sensor.film()
        grid = mi.Vector2i(dr.floor(uv)) + dr.opaque(mi.Int32, sampled_border(film))
        return mi.UInt32(grid.y * dr.opaque(mi.Int32, int(film_grid(film)[0])) + grid.x)

    def origin(self, ray: mi.Ray3f, aperture: mi.Point2f) -> mi.Point3f:
        """z_0 of a primary ray made from the aperture sample ``aperture``."""
        raise NotImplementedError

    def direction_pdf_w(self, d_world: mi.Vector3f) -> mi.Float:
        """Solid-angle density of a primary ray's direction (tech. rep. eq. 31)."""
        raise NotImplementedError

    def sample_rays(self, sampler: mi.Sampler, pixel_offset: int, n_pixels: int,
                    spp: int, stride: int = 1) -> CameraRays:
        """One primary ray per lane: pixel (offset + (lane // spp) stride) of the
        sampled grid (crop window, plus the filter border if sampled), film sizes kept
        opaque."""
        sensor, film = self.sensor, self.sensor.film()
        border = sampled_border(film)
        grid_w = dr.opaque(mi.Int32, int(film_grid(film)[0]))
        idx = mi.Int32(dr.arange(mi.UInt32, n_pixels * spp) // dr.opaque(mi.UInt32, spp)
                       * dr.opaque(mi.UInt32, stride) + dr.opaque(mi.UInt32, pixel_offset))
        offset = mi.ScalarVector2i(film.crop_offset())
        corner = mi.Vector2i(dr.opaque(mi.Int32, offset.x - border),
                             dr.opaque(mi.Int32, offset.y - border))
        pos = mi.Vector2i(idx % grid_w, idx // grid_w) + corner
        pos_f = mi.Vector2f(pos) + sampler.next_2d()
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.0)
        time = mi.Float(sensor.shutter_open())
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        wavelength_sample = sampler.next_1d() if mi.is_spectral else mi.Float(0.0)
        crop_offset = mi.Vector2f(corner + border)
        ray, weight = sensor.sample_ray_differential(
            time, wavelength_sample, (pos_f - crop_offset) / self.resolution, aperture)
        pixel = self.pixel_index(pos_f - crop_offset)
        pos = mi.Vector2f(pos) if film.rfilter().is_box_filter() else pos_f
        return CameraRays(ray=ray, weight=weight, pos=pos, pixel=pixel,
                          origin=self.origin(ray, aperture), pdf_w=self.direction_pdf_w(ray.d))

    def film_ray_numbers(self) -> int:
        """How many numbers ``sample_film_rays`` draws per lane: the film position,
        then the aperture, time and wavelength where the sensor samples them."""
        sensor = self.sensor
        return (2 + (2 if sensor.needs_aperture_sample() else 0)
                + (1 if sensor.shutter_open_time() > 0 else 0) + (1 if mi.is_spectral else 0))

    def sample_film_rays(self, sampler, lanes: int) -> CameraRays:
        """One primary ray per lane at a film position drawn uniformly over the crop
        window from the sampler's first two numbers (Metropolis light transport: the
        pixel is a coordinate of the primary sample, mlt.py).  ``pos`` is in pixels of
        the crop window, as the light image's splats' positions are."""
        sensor = self.sensor
        pos = sampler.next_2d() * self.resolution
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.0)
        time = mi.Float(sensor.shutter_open())
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        wavelength_sample = sampler.next_1d() if mi.is_spectral else mi.Float(0.0)
        ray, weight = sensor.sample_ray_differential(
            time, wavelength_sample, pos / self.resolution, aperture)
        return CameraRays(ray=ray, weight=weight, pos=mi.Vector2f(pos),
                          pixel=self.pixel_index(pos), origin=self.origin(ray, aperture),
                          pdf_w=self.direction_pdf_w(ray.d))


class Camera(CameraModel):
    """A ``perspective`` (pinhole) or ``thinlens`` sensor, from its parameters (opaque).

    Thin lens.  A primary ray joins a lens point a, uniform on the disk of radius r
    (area pdf 1 / (pi r^2)), to a point f on the focal plane z = F (F the focus
    distance), uniform over the film rectangle scaled to that plane (area A F^2).
    Given a, the direction w = (f - a) / |f - a| has the solid-angle density
        p(w) = 1 / (A F^2) * |f - a|^2 / cos = 1 / (A F^2) * (F / cos)^2 / cos
             = 1 / (A cos^3),
    cos = w_z (Veach eq. 8.10 from area on the focal plane to solid angle at a):
    the pinhole's density, with the angle measured at the lens point
    (tests/test_cameras.py checks it against the Jacobian of Mitsuba's sample_ray).
    A point p seen from lens point a lands on the film where the ray a -> p meets
    the focal plane, projected through the lens centre (Mitsuba's sample_direction).

    MIS.  Every strategy this renderer evaluates samples z_0 with the same density:
    the camera subpaths (t >= 2) by sample_ray's aperture sample, the light image
    (t = 1) by the lens sample of ``connect``, both 1 / (pi r^2).  The factor is
    common to the denominator and numerator of every weight (Veach eq. 9.13 sums
    p_j over the strategies of one path), so it cancels: the chains start as for a
    pinhole, with the direction density from the lane's own lens point, and the t = 1
    weight uses the camera's density of the light vertex from the lens point that
    ``connect`` chose (importance * cos, as for the pinhole).  The t = 0 strategy (a
    light subpath hitting the lens) is left out, as pbrt-v4 does: it would carry the
    lens pdf only in its own density, and the chains treat z_0 as unhittable (d_vc =
    0 at the camera start), so the weights of the strategies that remain sum to one.
    """

    def __init__(self, sensor: mi.Sensor, border: int = 0):
        params = mi.traverse(sensor)
        super().__init__(sensor, border, params)
        film = sensor.film()
        size, crop = mi.ScalarVector2f(film.size()), mi.ScalarVector2f(film.crop_size())
        self.lens = sensor.class_name() == THIN_LENS
        self.camera_to_sample = mi.ProjectiveTransform4f(sensor.projection_transform())
        sample_to_camera = self.camera_to_sample.inverse()
        # The visible image rectangle at unit distance (crop included): its area A is
        # the importance's normalization.  A principal point offset shifts the
        # rectangle (sample_ray adds it to the film sample), leaving its area.
        corners = [sample_to_camera @ mi.Point3f(x, x, 0.0) for x in (0.0, 1.0)]
        extent = dr.abs(mi.Point2f(corners[1].x, corners[1].y) / corners[1].z
                        - mi.Point2f(corners[0].x, corners[0].y) / corners[0].z)
        self.normalization = dr.rcp(extent.x * extent.y)
        pp = mi.Point2f(0.0)
        if not self.lens:     # Mitsuba's thinlens has no principal point offset
            pp = mi.Point2f(params["principal_point_offset_x"], params["principal_point_offset_y"])
        self.pp_offset = pp * mi.Vector2f(size / crop)
        self.aperture_radius = mi.Float(params["aperture_radius"] if self.lens else 0.0)
        self.focus_distance = mi.Float(params["focus_distance"] if self.lens else 1.0)
        dr.make_opaque(self.camera_to_sample, self.normalization, self.pp_offset,
                       self.aperture_radius, self.focus_distance)

    def lens_point(self, sample: mi.Point2f) -> mi.Point3f:
        """The lens point (local) of an aperture sample, as Mitsuba's thinlens maps it."""
        if not self.lens:
            return mi.Point3f(0.0)
        a = mi.warp.square_to_uniform_disk_concentric(sample) * self.aperture_radius
        return mi.Point3f(a.x, a.y, 0.0)

    def origin(self, ray, aperture) -> mi.Point3f:
        if not self.lens:
            return self.to_world.translation()
        return self.to_world @ self.lens_point(aperture)

    def direction_pdf_w(self, d_world: mi.Vector3f) -> mi.Float:
        """Solid-angle density of a primary ray's direction, 1 / (A cos^3) (the class
        docstring), for directions of primary rays (inside the film by construction)."""
        ct = (self.to_local @ d_world).z
        return dr.select(ct > 0, self.normalization * dr.rcp(ct * ct * ct), 0.0)

    def connect(self, p_world: mi.Point3f, sample: mi.Point2f, active=True) -> CameraConnection:
        """Connect a point to the camera through the lens point of ``sample`` (Mitsuba's
        ``sample_direction``)."""
        p_world = mi.Point3f(p_world)     # (a Vector3f would be transformed as one)
        local = self.to_local @ p_world
        active = active & (local.z >= self.near) & (local.z <= self.far)
        a = self.lens_point(sample)
        v = local - a
        dist = dr.norm(v)
        inv_dist = dr.rcp(dist)
        ct = v.z * inv_dist
        # The film position: where the ray a -> p crosses the focal plane, projected
        # through the lens centre; a pinhole projects p itself.
        seen = a + v * (self.focus_distance * dr.rcp(v.z)) if self.lens else local
        screen = self.camera_to_sample @ seen
        uv = mi.Point2f(screen.x, screen.y) - self.pp_offset
        # The film region the camera samples: the crop window and its sampled border.
        lo, hi = -self.border / self.resolution, 1.0 + self.border / self.resolution
        active &= (ct > 0) & dr.all((uv >= lo) & (uv <= hi))
        importance = self.normalization * dr.rcp(ct * ct * ct) * dr.square(inv_dist)
        lens = self.to_world @ a
        return CameraConnection(uv=mi.Point2f(uv * self.resolution), p=lens,
                                d=(lens - p_world) * inv_dist, dist=dist,
                                importance=dr.select(active, importance, 0.0),
                                valid=active & (importance > 0))


class OrthographicCamera(CameraModel):
    """An ``orthographic`` sensor: parallel rays, each from its own point z_0 on the film
    plane (uniform over the film rectangle), all in one direction.  The direction is a
    delta, so no light vertex can be connected to z_0 (no t = 1 strategy) and no
    light subpath can hit it (no t = 0): the chains start with d_vcm = d_vc = 0 and
    MIS renormalizes over s = 0, s = 1 and connections.  Mitsuba's rays start on the
    near clip plane, which is where z_0 lies."""

    light_image_possible = False

    def origin(self, ray, aperture) -> mi.Point3f:
        return mi.Point3f(ray.o)

    def direction_pdf_w(self, d_world: mi.Vector3f) -> mi.Float:
        return dr.zeros(mi.Float, dr.width(d_world))     # a delta: no density

    def connect(self, p_world, sample, active=True):
        raise RuntimeError("bdpt: an orthographic camera cannot be connected to (t = 1): "
                           "its direction is a delta")


def make_camera(sensor: mi.Sensor, border: int = 0) -> CameraModel:
    """The camera model of a supported sensor (``check_sensor`` first); ``border``:
    ``CameraModel``'s."""
    check_sensor(sensor)
    model = OrthographicCamera if sensor.class_name() == ORTHOGRAPHIC else Camera
    return model(sensor, border)


def check_sensor(sensor: mi.Sensor) -> None:
    refusal = sensor_refusal(sensor)
    if refusal:
        raise UnsupportedPluginError("bdpt: sensor plugin '%s' is not supported: %s"
                                     % (plugin_name(sensor), refusal))


def check_settings(camera: CameraModel, settings) -> None:
    """Refuse strategies the camera cannot have: an orthographic camera has no light
    image (t = 1), so light tracing alone would leave the film black."""
    if camera.light_image_possible:
        return
    name = plugin_name(camera.sensor)
    if settings.strategy_subset == "lt":
        raise ValueError("bdpt: strategy_subset 'lt' (light tracing) cannot render through "
                         "the '%s' sensor: its direction is a delta, so no light path "
                         "reaches its film" % name)
    if settings.technique is not None and settings.technique[1] == 1:
        raise ValueError("bdpt: technique %d,1 (light tracing) cannot render through the "
                         "'%s' sensor: its direction is a delta, so no light path reaches "
                         "its film" % (settings.technique[0], name))


def select_sensor(scene: mi.Scene, sensor) -> mi.Sensor:
    """The sensor to render (an index into the scene's sensors, or a sensor)."""
    if isinstance(sensor, (int, np.integer)):
        sensors = scene.sensors()
        if not sensors:
            raise ValueError("bdpt: the scene has no sensor")
        if not 0 <= sensor < len(sensors):
            raise ValueError("bdpt: sensor index %d is out of range: the scene has %d "
                             "sensor%s (indices 0 to %d)" % (sensor, len(sensors),
                             "" if len(sensors) == 1 else "s", len(sensors) - 1))
        sensor = sensors[int(sensor)]
    check_sensor(sensor)
    return sensor


def sampled_border(film: mi.Film) -> int:
    """Pixels of filter border sampled around the crop window (0 unless the film
    samples its border)."""
    return film.rfilter().border_size() if film.sample_border() else 0


def film_grid(film: mi.Film):
    """Size of the sampled pixel grid (crop plus the filter border if sampled)."""
    return mi.ScalarVector2u(film.crop_size()) + 2 * sampled_border(film)
