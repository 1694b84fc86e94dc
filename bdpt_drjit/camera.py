"""Camera stage: one primary ray per lane (pixel x sample), as Mitsuba's own
``ADIntegrator.sample_rays`` makes them, for a range of pixels of the (crop) film.

Only the pinhole ``perspective`` sensor is supported: its position is a delta, so
camera subpaths always start at z_0 = the pinhole and light paths cannot hit the
lens (no t = 0 strategy).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .emitters import UnsupportedPluginError, plugin_name


@dataclass
class CameraRays:
    ray: mi.RayDifferential3f
    weight: mi.Spectrum       # sensor sampling weight (spectral response), 1 in RGB
    pos: mi.Vector2f          # film position to put the sample at
    origin: mi.Point3f        # z_0, the pinhole
    pdf_w: mi.Float           # solid-angle density of the ray's direction over the film


def check_sensor(sensor: mi.Sensor) -> None:
    if sensor.class_name() != "PerspectiveCamera":
        raise UnsupportedPluginError(
            "bdpt: sensor plugin '%s' is not supported; only 'perspective' (a pinhole "
            "camera, whose pdfs bdpt models exactly) is" % plugin_name(sensor))


def select_sensor(scene: mi.Scene, sensor) -> mi.Sensor:
    """The sensor to render (an index into the scene's sensors, or a sensor)."""
    if isinstance(sensor, int):
        sensors = scene.sensors()
        if not sensors:
            raise ValueError("bdpt: the scene has no sensor")
        if not 0 <= sensor < len(sensors):
            raise ValueError("bdpt: sensor index %d is out of range: the scene has %d "
                             "sensor%s" % (sensor, len(sensors), "" if len(sensors) == 1 else "s"))
        sensor = sensors[sensor]
    check_sensor(sensor)
    return sensor


def film_grid(film: mi.Film):
    """Size of the sampled pixel grid (crop plus the filter border if sampled)."""
    size = mi.ScalarVector2u(film.crop_size())
    if film.sample_border():
        size += 2 * film.rfilter().border_size()
    return size


def sample_camera_rays(sensor: mi.Sensor, sampler: mi.Sampler, pixel_offset: int,
                       n_pixels: int, spp: int) -> CameraRays:
    film = sensor.film()
    grid = film_grid(film)
    idx = dr.arange(mi.UInt32, n_pixels * spp) // dr.opaque(mi.UInt32, spp)
    idx += dr.opaque(mi.UInt32, pixel_offset)
    pos = mi.Vector2i()
    pos.y = mi.Int32(idx // grid[0])
    pos.x = mi.Int32(idx) - pos.y * int(grid[0])
    if film.sample_border():
        pos -= film.rfilter().border_size()
    pos += mi.Vector2i(film.crop_offset())
    pos_f = mi.Vector2f(pos) + sampler.next_2d()
    scale = dr.rcp(mi.ScalarVector2f(film.crop_size()))
    offset = -mi.ScalarVector2f(film.crop_offset()) * scale
    aperture = mi.Vector2f(0.0)
    if sensor.needs_aperture_sample():
        aperture = sampler.next_2d()
    time = mi.Float(sensor.shutter_open())
    if sensor.shutter_open_time() > 0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    wavelength_sample = sampler.next_1d() if mi.is_spectral else mi.Float(0.0)
    ray, weight = sensor.sample_ray_differential(time, wavelength_sample,
                                                 dr.fma(pos_f, scale, offset), aperture)
    splat_pos = mi.Vector2f(pos) if film.rfilter().is_box_filter() else pos_f
    pinhole = mi.Point3f(sensor.world_transform().translation())
    return CameraRays(ray=ray, weight=weight, pos=splat_pos, origin=pinhole,
                      pdf_w=direction_pdf_w(sensor, ray))


def direction_pdf_w(sensor: mi.Sensor, ray: mi.Ray3f) -> mi.Float:
    """The camera's solid-angle density of a primary ray's direction (tech. rep. eq.
    31): importance * d^2 = 1 / (A cos^3) from ``sample_direction`` at any point on
    the ray, A the film's area at unit distance."""
    it = dr.zeros(mi.Interaction3f)
    it.p = ray.o + ray.d
    ds, importance = sensor.sample_direction(it, mi.Point2f(0.5))
    return mi.unpolarized_spectrum(importance)[0] * dr.square(ds.dist)
