"""The camera: primary rays, and the camera model the strategies need.

Primary rays: one per lane (pixel x sample), as Mitsuba's own
``ADIntegrator.sample_rays`` makes them, for a range of pixels of the (crop) film.

The model (``Camera``): where a point projects on the film, the sensor's importance
toward it, and the density of a primary ray's direction -- what the t = 1
strategies and the MIS chains' camera end need.  It is Mitsuba's
``perspective.sample_direction`` (v3.9.1) computed from the sensor's own
parameters held in opaque variables: Mitsuba's version bakes the film size into
the kernel, which would recompile the light walk for every film size.
tests/test_camera.py checks it against ``sensor.sample_direction``.

Only the pinhole ``perspective`` sensor is supported: its position is a delta, so
camera subpaths always start at z_0 = the pinhole and light paths cannot hit the
lens (no t = 0 strategy).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .support import UnsupportedPluginError, plugin_name, sensor_refusal


@dataclass
class CameraRays:
    ray: mi.RayDifferential3f
    weight: mi.Spectrum       # sensor sampling weight (spectral response), 1 in RGB
    pos: mi.Vector2f          # film position to put the sample at
    origin: mi.Point3f        # z_0, the pinhole
    pdf_w: mi.Float           # solid-angle density of the ray's direction over the film


@dataclass
class CameraConnection:
    """A point connected to the camera (t = 1)."""
    uv: mi.Point2f            # film position in pixels of the crop window
    p: mi.Point3f             # the point on the lens (the pinhole)
    d: mi.Vector3f            # unit direction from the point toward the lens
    dist: mi.Float
    importance: mi.Float      # We * cos / d^2: the camera's solid-angle density of the
                              # direction (1 / (A cos^3)) divided by d^2
    valid: mi.Bool            # inside the film and the clip range


class Camera:
    """The pinhole of a ``perspective`` sensor, from its parameters (opaque)."""

    def __init__(self, sensor: mi.Sensor):
        self.sensor = sensor
        params = mi.traverse(sensor)
        film = sensor.film()
        size, crop = mi.ScalarVector2f(film.size()), mi.ScalarVector2f(film.crop_size())
        self.to_world = mi.AffineTransform4f(params["to_world"])
        self.to_local = self.to_world.inverse()
        self.camera_to_sample = mi.ProjectiveTransform4f(sensor.projection_transform())
        sample_to_camera = self.camera_to_sample.inverse()
        # The visible image rectangle at unit distance (crop included), as the
        # sensor's importance() uses it, and the normalization 1 / its area.
        corners = [sample_to_camera @ mi.Point3f(x, x, 0.0) for x in (0.0, 1.0)]
        ends = [mi.Point2f(c.x, c.y) / c.z for c in corners]
        self.rect_min, self.rect_max = dr.minimum(*ends), dr.maximum(*ends)
        extent = self.rect_max - self.rect_min
        self.normalization = dr.rcp(extent.x * extent.y)
        pp = mi.Point2f(params["principal_point_offset_x"], params["principal_point_offset_y"])
        self.pp_offset = pp * mi.Vector2f(size / crop)
        self.resolution = mi.Vector2f(crop)
        self.near = mi.Float(params["near_clip"])
        self.far = mi.Float(params["far_clip"])
        dr.make_opaque(self.to_world, self.to_local, self.camera_to_sample, self.rect_min,
                       self.rect_max, self.normalization, self.pp_offset, self.resolution,
                       self.near, self.far)

    def _importance(self, d_local: mi.Vector3f) -> mi.Float:
        """1 / (A cos^3) toward local direction d (0 outside the image rectangle)."""
        ct = d_local.z
        inv_ct = dr.rcp(ct)
        p = mi.Point2f(d_local.x * inv_ct, d_local.y * inv_ct)
        valid = ((ct > 0) & (p.x >= self.rect_min.x) & (p.y >= self.rect_min.y)
                 & (p.x <= self.rect_max.x) & (p.y <= self.rect_max.y))
        return dr.select(valid, self.normalization * inv_ct * inv_ct * inv_ct, 0.0)

    def direction_pdf_w(self, d_world: mi.Vector3f) -> mi.Float:
        """Solid-angle density of a primary ray's direction (tech. rep. eq. 31)."""
        return self._importance(self.to_local @ d_world)

    def connect(self, p_world: mi.Point3f, active=True) -> CameraConnection:
        """Connect a point to the camera (Mitsuba's ``sample_direction``)."""
        local = self.to_local @ p_world
        active = active & (local.z >= self.near) & (local.z <= self.far)
        screen = self.camera_to_sample @ local
        uv = mi.Point2f(screen.x, screen.y) - self.pp_offset
        active &= (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        dist = dr.norm(local)
        inv_dist = dr.rcp(dist)
        lens = self.to_world.translation()
        importance = self._importance(local * inv_dist) * dr.square(inv_dist)
        return CameraConnection(uv=mi.Point2f(uv * self.resolution), p=lens, d=(lens - p_world) * inv_dist,
                                dist=dist, importance=dr.select(active, importance, 0.0),
                                valid=active & (importance > 0))


    def sample_rays(self, sampler: mi.Sampler, pixel_offset: int, n_pixels: int,
                    spp: int) -> CameraRays:
        """One primary ray per lane: pixel (offset + lane // spp) of the sampled grid
        (crop window, plus the filter border if sampled), film sizes kept opaque."""
        sensor, film = self.sensor, self.sensor.film()
        border = film.rfilter().border_size() if film.sample_border() else 0
        grid_w = dr.opaque(mi.Int32, int(film_grid(film)[0]))
        idx = mi.Int32(dr.arange(mi.UInt32, n_pixels * spp) // dr.opaque(mi.UInt32, spp)
                       + dr.opaque(mi.UInt32, pixel_offset))
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
        pos = mi.Vector2f(pos) if film.rfilter().is_box_filter() else pos_f
        return CameraRays(ray=ray, weight=weight, pos=pos, origin=self.to_world.translation(),
                          pdf_w=self.direction_pdf_w(ray.d))


def check_sensor(sensor: mi.Sensor) -> None:
    refusal = sensor_refusal(sensor)
    if refusal:
        raise UnsupportedPluginError("bdpt: sensor plugin '%s' is not supported: %s"
                                     % (plugin_name(sensor), refusal))


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


def film_grid(film: mi.Film):
    """Size of the sampled pixel grid (crop plus the filter border if sampled)."""
    size = mi.ScalarVector2u(film.crop_size())
    if film.sample_border():
        size += 2 * film.rfilter().border_size()
    return size
