"""Randomised rendered scenes with their true rims: the learned detector's synthetic training data
and the held-back rendered test set.

Each scene is a small camera (`size_px`, 20 deg field of view) looking down, up to
`max_tilt_deg` off nadir, at a random field of craters near the point (0, 0) deg, drawn through
the project's renderer (`pipeline.core.sensors.render`). Domain randomisation (Tobin et al. 2017,
"Domain randomization for transferring deep neural networks from simulation to the real world",
IROS): ground sample distance, crater density and size-frequency slope, crater degradation (each
crater's normalised age kappa t / R^2, `pipeline.core.body.crater_shape`; most real craters are
old: Fassett & Thomson 2014), the Sun's elevation and azimuth, albedo and a smooth albedo pattern,
roughness and its Hurst exponent, exposure, read and shot noise, optics blur. Everything is drawn
from the scene's own generator (`scene_rng(seed, index)`), so a scene is reproducible alone.

Truth: every crater whose rim ellipse (the rendered crest, `height_map.rim_crests`, imaged through
`conics.rim_conics`) has its centre inside the image: centre (u, v) px (pixel (0, 0) the corner of
the first pixel), semi-axes, angle, and the incidence at the crater (deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from pipeline.core.body import illumination
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.sensors import conics, exposure, height_map, render
from pipeline.core.sensors.camera import PixelCamera, sun_direction_image

SCENE_TAG = 0x5CE7E  # the scenes' streams within a seed


@dataclass(frozen=True)
class SceneOptions:
    """Ranges of the randomised scene (px: apparent sizes; deg: angles)."""

    size_px: int = 256
    fov_deg: float = 20.0
    gsd_m: tuple[float, float] = (5.0, 80.0)  # log-uniform
    max_tilt_deg: float = 20.0
    min_diam_px: float = 4.0
    max_diam_px: float = 220.0
    n_ge10_px: tuple[float, float] = (4.0, 90.0)  # craters >= 10 px per 256^2 px, log-uniform
    sfd_slope: tuple[float, float] = (1.6, 2.6)  # cumulative N(>D) ~ D^-slope
    fresh_share: float = 0.25  # craters with tau < 1e-3
    degradation: tuple[float, float] = (1e-3, 0.15)  # log-uniform tau of the others
    sun_elevation_deg: tuple[float, float] = (8.0, 62.0)
    albedo: tuple[float, float] = (0.07, 0.16)
    albedo_pattern: tuple[float, float] = (0.0, 0.25)  # RMS of the smooth relative pattern
    roughness_deg: tuple[float, float] = (1.0, 8.0)
    hurst: tuple[float, float] = (0.7, 0.95)
    read_noise_e: tuple[float, float] = (5.0, 80.0)
    full_well_e: tuple[float, float] = (4e3, 4e4)
    exposure: tuple[float, float] = (1.7, 4.5)  # full well at this many times the mean I/F
    blur_px: tuple[float, float] = (0.0, 1.3)


@dataclass(frozen=True)
class Scene:
    """A rendered scene: image (H, W) uint8, the Sun's unit image direction (2,), and the true
    rims (m,): centre (m, 2) px, semi-axes px, angle rad, incidence deg, degradation tau."""

    image: np.ndarray
    sun_dir_image: np.ndarray
    centre_px: np.ndarray
    semi_major_px: np.ndarray
    semi_minor_px: np.ndarray
    angle_rad: np.ndarray
    incidence_deg: np.ndarray
    degradation: np.ndarray


def scene_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of scene `index` of a data set drawn with `seed`."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(
        seed, spawn_key=(SCENE_TAG, index))))


def _log_uniform(rng: np.random.Generator, lo_hi: tuple[float, float], n: int | None = None
                 ) -> np.ndarray:
    lo, hi = np.log(lo_hi[0]), np.log(lo_hi[1])
    return np.exp(rng.uniform(lo, hi, n))


def _pose(rng: np.random.Generator, opts: SceneOptions, altitude_m: float
          ) -> tuple[np.ndarray, np.ndarray]:
    """Camera position (3,) m MCMF above (0, 0) deg and dcm_cam_from_mcmf (3, 3): boresight
    tilted by up to max_tilt_deg from nadir, random roll."""
    tilt = np.radians(opts.max_tilt_deg) * np.sqrt(rng.uniform())
    az, roll = rng.uniform(0, 2 * np.pi, 2)
    up = np.array([1.0, 0.0, 0.0])
    east, north = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    bore = -np.cos(tilt) * up + np.sin(tilt) * (np.cos(az) * east + np.sin(az) * north)
    ground = MOON_RADIUS_M * up
    r_cam = ground - altitude_m * bore
    x = np.cross(bore, up if abs(bore @ up) < 0.99 else east)
    x /= np.linalg.norm(x)
    y = np.cross(bore, x)
    x, y = np.cos(roll) * x + np.sin(roll) * y, -np.sin(roll) * x + np.cos(roll) * y
    return r_cam, np.stack([x, y, bore])


def _craters(rng: np.random.Generator, opts: SceneOptions, gsd_m: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crater centres (N, 3) m MCMF on the sphere around (0, 0) deg, diameters (N,) m and
    normalised ages (N,), over a square ~1.8x the footprint (casters and cut rims)."""
    s = opts.size_px
    span_m = 1.8 * s * gsd_m
    slope = rng.uniform(*opts.sfd_slope)
    n10 = float(_log_uniform(rng, opts.n_ge10_px)) * (span_m / (s * gsd_m)) ** 2 * (s / 256) ** 2
    lo, hi = opts.min_diam_px, opts.max_diam_px
    n = int(rng.poisson(n10 * (lo / 10.0) ** -slope))
    # truncated Pareto in diameter (px): N(>D) ~ D^-slope on [lo, hi]
    u = rng.uniform(size=n)
    d_px = lo * (1 - u * (1 - (hi / lo) ** -slope)) ** (-1 / slope)
    xy = rng.uniform(-span_m / 2, span_m / 2, (n, 2))
    theta = xy / MOON_RADIUS_M
    c = MOON_RADIUS_M * np.stack([np.cos(theta[:, 0]) * np.cos(theta[:, 1]),
                                  np.sin(theta[:, 0]) * np.cos(theta[:, 1]),
                                  np.sin(theta[:, 1])], -1)
    tau = np.where(rng.uniform(size=n) < opts.fresh_share, 0.0,
                   _log_uniform(rng, opts.degradation, n))
    return c, d_px * gsd_m, tau


def _albedo_field(rng: np.random.Generator, shape: tuple[int, int], rms: float) -> np.ndarray:
    """Smooth positive relative albedo (H, W) float32, mean ~1 and RMS ~rms: Gaussian-filtered
    white noise at a random scale, exponentiated."""
    if rms <= 0:
        return np.ones(shape, np.float32)
    scale = float(_log_uniform(rng, (8.0, 96.0)))
    step = max(int(scale // 4), 1)  # filtered on a coarse grid, then interpolated
    coarse = (-(-shape[0] // step) + 1, -(-shape[1] // step) + 1)
    g = ndimage.gaussian_filter(rng.standard_normal(coarse).astype(np.float32), scale / step,
                                mode="wrap")
    g = ndimage.zoom(g, step, order=1, grid_mode=False)[:shape[0], :shape[1]]
    g *= np.float32(rms / max(float(g.std()), 1e-9))
    return np.exp(g - 0.5 * rms * rms).astype(np.float32)


def render_scene(rng: np.random.Generator, opts: SceneOptions | None = None) -> Scene:
    """One randomised scene (module docstring)."""
    opts = opts or SceneOptions()
    s = opts.size_px
    f = (s / 2) / np.tan(np.radians(opts.fov_deg) / 2)
    cam = PixelCamera(s, s, f, f, s / 2, s / 2)
    gsd = float(_log_uniform(rng, opts.gsd_m))
    r_cam, dcm = _pose(rng, opts, gsd * f)
    c, d, tau = _craters(rng, opts, gsd)
    elev = np.radians(rng.uniform(*opts.sun_elevation_deg))
    az = rng.uniform(0, 2 * np.pi)
    up, east, north = np.eye(3)
    u_sun = np.sin(elev) * up + np.cos(elev) * (np.cos(az) * east + np.sin(az) * north)
    terrain = height_map.TerrainOptions(
        albedo=float(rng.uniform(*opts.albedo)),
        roughness_rms_slope_deg=float(rng.uniform(*opts.roughness_deg)),
        roughness_hurst=float(rng.uniform(*opts.hurst)), threads=1)
    frame = render.render_frame(cam, r_cam, dcm, u_sun, c, d, rng, terrain=terrain,
                                sensor=exposure.SensorOptions(shot_noise=False, read_noise_e=0.0),
                                degradation=tau)
    rad = frame.radiance_if * _albedo_field(rng, (s, s), float(rng.uniform(*opts.albedo_pattern)))
    lit = rad[rad > 0]
    mean_if = float(lit.mean()) if lit.size else terrain.albedo * 0.5
    sensor = exposure.SensorOptions(
        if_full_well=mean_if * float(rng.uniform(*opts.exposure)),
        full_well_e=float(_log_uniform(rng, opts.full_well_e)),
        read_noise_e=float(_log_uniform(rng, opts.read_noise_e)),
        blur_sigma_px=float(rng.uniform(*opts.blur_px)))
    _, _, image = exposure.expose(rad, rng, sensor)
    crest, rim_r = height_map.rim_crests(c, d, MOON_RADIUS_M, terrain, tau)
    ell = conics.ellipse_from_conic(conics.rim_conics(crest, rim_r, r_cam, dcm, cam.k))
    u, v = ell.centre_px[:, 0], ell.centre_px[:, 1]
    keep = ell.valid & (u >= 0) & (u < s) & (v >= 0) & (v < s)
    inc = np.degrees(np.atleast_1d(illumination.crater_illumination_angles(
        c[keep].reshape(-1, 3), r_cam, 1.5e11 * u_sun).incidence_rad))
    sun_img = sun_direction_image(cam, r_cam, dcm, u_sun)
    return Scene(image, np.asarray(sun_img, float), ell.centre_px[keep],
                 ell.semi_major_px[keep], ell.semi_minor_px[keep], ell.angle_rad[keep], inc,
                 tau[keep])
