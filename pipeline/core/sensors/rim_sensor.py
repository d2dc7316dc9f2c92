"""The physical camera sensor: what a crater detector in a real image delivers, per frame.

Replaces the paper's abstract sensor (Eq. 9 visibility, Eq. 10-11 noise) when chosen:
- the world is not the catalogue: each crater's true centre and diameter differ from its catalogue
  entry by a fixed, seeded error (`world_craters`), the same in every frame;
- each true rim is projected into an image ellipse (`pipeline.core.sensors.conics`), measured with
pixel
  noise on its centre and semi-axes;
- a crater is detected with a probability that depends on its apparent diameter in pixels, the
  solar incidence and the emission angle at the crater (`detection_probability`);
- the bearing comes from the measured ellipse (its centre, or the centre corrected for the
  projection bias), the range from a per-crater ranging source, the ellipse's apparent size
  (with the catalogue diameter), or nothing.

The ellipse fit is modelled in the undistorted image (a detector undistorts its edge points before
fitting); distortion moves where a crater falls on the detector, which decides whether its rim is
inside the image. SI units, angles in rad, pixels in px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.body.synthetic import SITE_TIER_ID_BASE
from pipeline.core.sensors import conics
from pipeline.core.sensors.camera import PixelCamera

_U64 = np.uint64


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """The splitmix64 finaliser (Steele, Lea & Flood, OOPSLA 2014): a bijective 64-bit mix of
    uint64 values (in place on one fresh array: the whole catalogue's draws are 10 M values)."""
    with np.errstate(over="ignore"):
        x = np.asarray(x, dtype=np.uint64) + _U64(0x9E3779B97F4A7C15)
        x ^= x >> _U64(30)
        x *= _U64(0xBF58476D1CE4E5B9)
        x ^= x >> _U64(27)
        x *= _U64(0x94D049BB133111EB)
        x ^= x >> _U64(31)
        return x


def crater_normals(seed: int, crater_id: np.ndarray, n: int) -> np.ndarray:
    """Standard normals (N, n) that depend only on (seed, crater id, component): a crater keeps
    its draws whatever frame, order or subset it appears in (Box-Muller on hashed uniforms)."""
    ids = np.asarray(crater_id).astype(np.uint64)
    base = _splitmix64(ids ^ _splitmix64(np.full(ids.shape, seed, dtype=np.uint64)))
    k = np.arange(2 * n, dtype=np.uint64)
    with np.errstate(over="ignore"):
        bits = _splitmix64(base[:, None] + k[None, :] * _U64(0xD1B54A32D192ED03))
    bits >>= _U64(11)
    u = bits.astype(np.float64)
    u += 0.5
    u /= 2.0**53  # in (0, 1)
    radius = np.log(u[:, 0::2])  # sqrt(-2 log u1) cos(2 pi u2), in place (N x n values)
    radius *= -2.0
    np.sqrt(radius, out=radius)
    turn = 2.0 * np.pi * u[:, 1::2]
    np.cos(turn, out=turn)
    radius *= turn
    return radius


@dataclass(frozen=True)
class CatalogueErrors:
    """1-sigma differences between the world and the catalogue; the site tier's craters
    (numbered from `SITE_TIER_ID_BASE`) have a flight map's errors instead: a common offset of
    the whole tier (its absolute error) and per-crater relative errors."""

    horizontal_m: float  # per horizontal axis of the crater centre
    height_m: float  # of the centre off the reference sphere
    diameter_share: float  # relative diameter error
    site_horizontal_m: float = 0.0  # the tier's common offset, per horizontal axis
    site_height_m: float = 0.0  # the tier's common offset, vertical
    site_relative_m: float = 0.0  # each tier crater's own error, per axis

    @property
    def zero(self) -> bool:
        return (self.horizontal_m == self.height_m == self.diameter_share == 0.0
                and self.site_horizontal_m == self.site_height_m == self.site_relative_m == 0.0)


@dataclass(frozen=True)
class World:
    """The true craters, row by row with a catalogue: centres (N, 3) (m, the catalogue's frame)
    and diameters (N,) (m)."""

    r_mcmf_m: np.ndarray
    diam_m: np.ndarray


def world_craters(c_cat_m: np.ndarray, diam_cat_m: np.ndarray, crater_id: np.ndarray,
                  errors: CatalogueErrors, seed: int) -> World:
    """The true craters of catalogue entries (centres (N, 3) m, Moon-centred; diameters (N,) m):
    each entry plus its fixed, seeded error (east/north horizontal, up, relative diameter); the
    site tier's entries plus the tier's common offset (one seeded draw) and their own relative
    error. The catalogue itself when every error is zero."""
    if errors.zero:
        return World(c_cat_m, diam_cat_m)
    z = crater_normals(seed, crater_id, 4)
    up = c_cat_m / np.linalg.norm(c_cat_m, axis=-1, keepdims=True)
    east, north = conics.tangent_basis(up)
    c_true = (c_cat_m + errors.horizontal_m * (z[:, :1] * east + z[:, 1:2] * north)
              + errors.height_m * z[:, 2:3] * up)
    diam = diam_cat_m * np.maximum(1.0 + errors.diameter_share * z[:, 3], 0.05)
    tier = np.asarray(crater_id) >= SITE_TIER_ID_BASE
    if tier.any():
        z0 = crater_normals(seed, np.array([SITE_TIER_ID_BASE]), 3)[0]  # the tier's offset
        c_tier = c_cat_m[tier] + (
            (errors.site_horizontal_m * z0[0] + errors.site_relative_m * z[tier, :1]) * east[tier]
            + (errors.site_horizontal_m * z0[1] + errors.site_relative_m * z[tier, 1:2])
            * north[tier]
            + (errors.site_height_m * z0[2] + errors.site_relative_m * z[tier, 2:3]) * up[tier])
        c_true[tier] = c_tier
        diam[tier] = diam_cat_m[tier]
    return World(c_true, diam)


@dataclass(frozen=True)
class Detectability:
    """Parameters of `detection_probability` (defaults and their sources there)."""

    min_diameter_px: float = 10.0  # nothing smaller is detected
    full_diameter_px: float = 20.0  # from here on the size does not limit detection
    max_diameter_share: float = 0.5  # nothing wider than this share of the image side
    incidence_rise_deg: tuple[float, float] = (10.0, 30.0)  # contrast appears, then complete
    incidence_fall_deg: tuple[float, float] = (80.0, 88.0)  # shadow fills, then swallows
    emission_fall_deg: tuple[float, float] = (45.0, 75.0)  # foreshortening
    p_max: float = 0.95  # best-case detection probability (recall)


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """0 below lo, 1 above hi, the cubic 3t^2 - 2t^3 between (C1-smooth)."""
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def detection_probability(diameter_px: np.ndarray, incidence_rad: np.ndarray,
                          emission_rad: np.ndarray, image_side_px: float,
                          d: Detectability = Detectability()) -> np.ndarray:
    """Probability (N,) that a crater of apparent diameter (px) under solar incidence and
    emission angles (rad) is detected: p_max x size x lighting x view, each a smoothstep.

    - size: 0 below min_diameter_px, rising to 1 at full_diameter_px; 0 above
      max_diameter_share of the image. Crater detection algorithms reach high recall only from
      ~10 px in diameter (Silburt et al. 2019, Icarus 317, DeepMoon: recall falls sharply below
      ~10-15 px; Christian, Derksen & Watkins 2021, J. Astronaut. Sci. 68, on the rim pixels a fit
      needs).
    - lighting: craters show by their shadows. Under a high Sun (incidence < 10-30 deg) the
      contrast vanishes; near the terminator (incidence > 80-88 deg) shadow fills them; none on
      the night side. Crater mapping prefers incidences of ~50-80 deg (Wilhelms 1987, USGS PP
      1348; Robbins 2019, JGR Planets 124, chose images at 60-80 deg incidence).
    - view: foreshortening narrows rims beyond ~45 deg emission; none past ~75 deg.
    - p_max 0.95: the best recall reported by classical and learned detectors on lunar
      imagery (Silburt et al. 2019; DeLatte et al. 2019, Adv. Space Res. 64, review).
    """
    inc = np.degrees(incidence_rad)
    size = _smoothstep(diameter_px, d.min_diameter_px, d.full_diameter_px) * (
        diameter_px <= d.max_diameter_share * image_side_px)
    light = (_smoothstep(inc, *d.incidence_rise_deg)
             * (1.0 - _smoothstep(inc, *d.incidence_fall_deg)))
    view = 1.0 - _smoothstep(np.degrees(emission_rad), *d.emission_fall_deg)
    return d.p_max * size * light * view


@dataclass(frozen=True)
class EllipseMeasurement:
    """Measured rim ellipses of N craters (undistorted image, px) and what follows from them."""

    centre_px: np.ndarray  # (N, 2)
    semi_major_px: np.ndarray  # (N,)
    semi_minor_px: np.ndarray  # (N,)
    angle_rad: np.ndarray  # (N,)
    conic: np.ndarray  # (N, 3, 3) of the measured ellipse


def measure_ellipses(rng: np.random.Generator, true: conics.Ellipses, sigma_px: float
                     ) -> EllipseMeasurement:
    """The true ellipses with Gaussian noise of sigma_px on each centre coordinate and semi-axis
    and sigma_px / semi-major on the orientation (the displacement of the rim's ends)."""
    n = true.semi_major_px.shape[0]
    z = rng.standard_normal((n, 5))
    centre = true.centre_px + sigma_px * z[:, :2]
    a = np.maximum(true.semi_major_px + sigma_px * z[:, 2], 0.5)
    b = np.maximum(true.semi_minor_px + sigma_px * z[:, 3], 0.5)
    angle = true.angle_rad + sigma_px / true.semi_major_px * z[:, 4]
    swap = b > a  # a near-circle's noisy axes may trade places: the major axis turns 90 deg
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    angle = np.where(swap, angle + 0.5 * np.pi, angle)
    angle = (angle + 0.5 * np.pi) % np.pi - 0.5 * np.pi
    return EllipseMeasurement(centre, a, b, angle, conics.conic_from_ellipse(centre, a, b, angle))


def bearings_body(cam: PixelCamera, m: EllipseMeasurement, up_cam: np.ndarray | None
                  ) -> np.ndarray:
    """Unit bearings (N, 3), body axes: to the measured ellipse centre (up_cam None), or to the
    crater centre recovered from the measured conic and the rim-plane normals up_cam (N, 3)
    (camera axes; the catalogue crater's vertical at the navigator's attitude), which removes the
    projection bias of the ellipse centre."""
    if up_cam is None:
        xy = (m.centre_px - [cam.cx_px, cam.cy_px]) / [cam.fx_px, cam.fy_px]
        u_cam = np.column_stack([xy, np.ones(xy.shape[0])])
        u_cam /= np.linalg.norm(u_cam, axis=1, keepdims=True)
    else:
        u_cam = conics.centre_bearings_cam(m.conic, cam.k, up_cam)
    return u_cam @ cam.dcm_body_from_cam.T


def nadir_in_camera(cam: PixelCamera, dcm_body_from_frame: np.ndarray, r_frame_m: np.ndarray
                    ) -> np.ndarray:
    """The nadir direction (unit, camera axes) of a camera at r_frame_m (..., 3) (m, from the
    Moon's centre in any frame) with attitude dcm_body_from_frame (..., 3, 3), (..., 3)."""
    down = -np.asarray(r_frame_m, float) / np.linalg.norm(r_frame_m, axis=-1, keepdims=True)
    return np.einsum("ij,...jk,...k->...i", cam.dcm_cam_from_body, dcm_body_from_frame, down)


def emission_geometry(cam: PixelCamera, centre_px: np.ndarray, nadir_cam: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """tan of the emission angle (N,) at image points (N, 2) px (the angle between the line of
    sight and the local vertical, the ground taken level: the angle from the nadir direction
    nadir_cam (3,), unit, camera axes) and the unit image direction (N, 2) in which it grows."""
    xy = (np.asarray(centre_px, float) - [cam.cx_px, cam.cy_px]) / [cam.fx_px, cam.fy_px]
    ray = np.column_stack([xy, np.ones(len(xy))])
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    cos_e = np.clip(ray @ nadir_cam, 1e-6, 1.0)
    tan_e = np.sqrt(np.maximum(1.0 - cos_e**2, 0.0)) / cos_e
    away = ray - cos_e[:, None] * nadir_cam  # grows the emission, perpendicular to the ray
    norm = np.linalg.norm(away, axis=1, keepdims=True)
    step = ray + 1e-4 * away / np.maximum(norm, 1e-12)
    uv = np.column_stack([cam.fx_px * step[:, 0] / step[:, 2] + cam.cx_px,
                          cam.fy_px * step[:, 1] / step[:, 2] + cam.cy_px])
    direction = uv - centre_px
    length = np.linalg.norm(direction, axis=1, keepdims=True)
    return tan_e, np.where(length > 0, direction / np.maximum(length, 1e-12), 0.0)


def emission_corrected(cam: PixelCamera, m: EllipseMeasurement, nadir_cam: np.ndarray,
                       pixel: PixelErrors) -> EllipseMeasurement:
    """The ellipses with the detector's calibrated emission bias taken off their centres:
    a crater seen obliquely shows its walls unevenly, and the detector puts its centre
    beta(D) tan(e) px along the image direction of growing emission e (`PixelErrors`,
    calibrated on rendered truth by `pipeline.ops.detector_error`); nadir_cam (3,) the
    navigator's nadir direction in camera axes. Unchanged without a bias model."""
    if not pixel.bias_edges_px or len(m.semi_major_px) == 0:
        return m
    tan_e, direction = emission_geometry(cam, m.centre_px, nadir_cam)
    shift = (pixel.bias_per_tan_at(2 * m.semi_major_px) * tan_e)[:, None] * direction
    centre = m.centre_px - shift
    return EllipseMeasurement(centre, m.semi_major_px, m.semi_minor_px, m.angle_rad,
                              conics.conic_from_ellipse(centre, m.semi_major_px, m.semi_minor_px,
                                                        m.angle_rad))


# A rim's apparent-size range is at most ~f R / b (b the ellipse's semi-minor axis, the rim
# foreshortened); ten times that is no rim's.
APPARENT_SIZE_RANGE_LIMIT = 10.0


def apparent_size_ranges(cam: PixelCamera, m: EllipseMeasurement, up_cam: np.ndarray,
                         radius_m: np.ndarray) -> np.ndarray:
    """Ranges (N,) (m) to the crater centres from the measured conics and the rims' radii (m):
    the monocular method (the crater's known size against its apparent size). NaN where the
    conic admits no such rim (no real circle, or a range beyond APPARENT_SIZE_RANGE_LIMIT times
    the one its minor axis alone implies, f R / b: a near-degenerate conic, e.g. a false
    detection's, not a rim)."""
    rho = np.linalg.norm(conics.crater_centres_cam(m.conic, cam.k, up_cam, radius_m), axis=1)
    limit = APPARENT_SIZE_RANGE_LIMIT * cam.fx_px * np.asarray(radius_m) / m.semi_minor_px
    return np.where(rho <= limit, rho, np.nan)


def apparent_size_range_sigma(rho_m: np.ndarray, semi_major_px: np.ndarray,
                              sigma_px: float | np.ndarray, diameter_share: float) -> np.ndarray:
    """1-sigma (N,) (m) of an apparent-size range: the range follows the rim's size measured on
    both semi-axes (`conics.crater_centres_cam`), rho ~ f R / a to first order with a's noise
    averaged over two axes, so sigma_rho / rho = sqrt((sigma_px / (sqrt(2) a))^2 +
    (sigma_D / D)^2) (exact for a near-circle; the simulated spread agrees within 5 %)."""
    return rho_m * np.hypot(sigma_px / (np.sqrt(2.0) * semi_major_px), diameter_share)




@dataclass(frozen=True)
class PixelErrors:
    """A detector's ellipse errors, each a 1-sigma (px) at apparent diameter D (px) of the form
    sqrt(s0^2 + (k D)^2) given as (s0_px, k): the centre's per axis and a semi-axis', each split
    into a white part, fresh in every frame, and a persistent part, the same in every sighting of
    a crater (its rim, light and terrain change little from one frame to the next, so neither
    does the detector's error on it). The persistent semi-axis error moves both axes together.
    `fixed(sigma_px)`: the sensor model's independent noise of sigma_px on centre and semi-axes
    (`measure_ellipses`), nothing persistent; `pipeline.ops.detector_error` calibrates a
    detector's on rendered truth."""

    centre_white: tuple[float, float]
    centre_persistent: tuple[float, float] = (0.0, 0.0)
    axis_white: tuple[float, float] | None = None  # None: the centre's white
    axis_persistent: tuple[float, float] = (0.0, 0.0)
    # the centre's bias along the image direction of growing emission, per tan(emission) (px),
    # in apparent-diameter bins of lower edges `bias_edges_px` (`emission_corrected`)
    bias_edges_px: tuple[float, ...] = ()
    bias_per_tan_px: tuple[float, ...] = ()

    @staticmethod
    def fixed(sigma_px: float) -> PixelErrors:
        return PixelErrors((sigma_px, 0.0))

    @staticmethod
    def _at(coef: tuple[float, float], diam_px: np.ndarray | float) -> np.ndarray | float:
        s0, k = coef
        return s0 if k == 0.0 else np.hypot(s0, k * np.asarray(diam_px, float))

    def centre_white_px(self, diam_px: np.ndarray | float) -> np.ndarray | float:
        return self._at(self.centre_white, diam_px)

    def centre_persistent_px(self, diam_px: np.ndarray | float) -> np.ndarray | float:
        return self._at(self.centre_persistent, diam_px)

    def axis_white_px(self, diam_px: np.ndarray | float) -> np.ndarray | float:
        return self._at(self.axis_white or self.centre_white, diam_px)

    def axis_persistent_px(self, diam_px: np.ndarray | float) -> np.ndarray | float:
        return self._at(self.axis_persistent, diam_px)

    def centre_total_px(self, diam_px: np.ndarray | float) -> np.ndarray | float:
        """One frame's centre error per axis (px): white and persistent together."""
        return np.hypot(self.centre_white_px(diam_px), self.centre_persistent_px(diam_px))

    def bias_per_tan_at(self, diam_px: np.ndarray) -> np.ndarray:
        """The emission bias per tan(emission) (px) at apparent diameters (N,) px (0 below the
        first bin)."""
        d = np.asarray(diam_px, float)
        if not self.bias_edges_px:
            return np.zeros(d.shape)
        k = np.searchsorted(np.asarray(self.bias_edges_px), d, side="right") - 1
        return np.where(k >= 0, np.asarray(self.bias_per_tan_px)[np.maximum(k, 0)], 0.0)


@dataclass(frozen=True)
class SensorNoise:
    """What sets a physical measurement's noise: the detector's ellipse errors (px), focal length
    (px), the range source and its noise, and the catalogue's errors (zero to ignore them)."""

    pixel: PixelErrors
    f_px: float
    range_source: str  # per_crater | apparent_size | none
    sigma_range_m: float  # per_crater ranges
    catalogue: CatalogueErrors


def catalogue_sigmas(noise: SensorNoise, rho_m: np.ndarray, site: np.ndarray | None = None
                     ) -> tuple[np.ndarray | float, np.ndarray | float]:
    """The catalogue's share of a measurement's 1-sigma, per crater (m): across the line of
    sight (the horizontal error; over the range, a bearing's) and along it (the vertical error,
    and with apparent-size ranges the diameter's). `site` (N,) marks the site tier's craters,
    which carry the flight map's relative error instead (its common offset is not noise)."""
    cat = noise.catalogue
    h: np.ndarray | float = cat.horizontal_m
    v: np.ndarray | float = cat.height_m
    d: np.ndarray | float = cat.diameter_share
    if site is not None and np.any(site):
        h = np.where(site, cat.site_relative_m, h)
        v = np.where(site, cat.site_relative_m, v)
        d = np.where(site, 0.0, d)
    return h, (np.hypot(v, rho_m * d) if noise.range_source == "apparent_size" else v)


def persistent_sigmas(noise: SensorNoise, rho_m: np.ndarray, semi_major_px: np.ndarray,
                      site: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per crater (N,): the part of a measurement's 1-sigma that repeats in every sighting of the
    crater, across the line of sight (m) and along it (m): the catalogue's errors
    (`catalogue_sigmas`) and the detector's persistent centre and size errors (`PixelErrors`),
    the latter as rho sigma_c / f across and, with apparent-size ranges, rho sigma_a / a along."""
    rho = np.asarray(rho_m, dtype=float)
    a = np.asarray(semi_major_px, dtype=float)
    cat_h, cat_r = catalogue_sigmas(noise, rho, site)
    pix = noise.pixel
    across = (np.hypot(rho * pix.centre_persistent_px(2 * a) / noise.f_px, cat_h)
              if pix.centre_persistent != (0.0, 0.0) else cat_h)
    along = (np.hypot(rho * pix.axis_persistent_px(2 * a) / a, cat_r)
             if noise.range_source == "apparent_size" and pix.axis_persistent != (0.0, 0.0)
             else cat_r)
    return np.broadcast_to(across, rho.shape), np.broadcast_to(along, rho.shape)


def measurement_sigmas(noise: SensorNoise, rho_m: np.ndarray, semi_major_px: np.ndarray,
                       sightings: np.ndarray | None = None, site: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Per crater (N,): the bearing's 1-sigma per axis (rad) and the range's (m) at ranges rho_m
    (m) and apparent semi-major axes (px). Bearing: the detector's white centre error over f
    (its value at the boresight, an upper bound elsewhere in a pinhole image) and the part that
    repeats in every sighting (`persistent_sigmas`: the catalogue's horizontal error and the
    detector's persistent centre error) across the line of sight. Range: the source's noise
    (`apparent_size_range_sigma` of the white semi-axis error for apparent sizes) and the
    repeating part along the line of sight, to first order (the camera looks down). Without
    ranges: 1 m (unused). `site` (N,) marks the site tier's craters (their map's relative
    error).

    A repeating error is the same in every frame that sees the crater: a filter that fuses K
    sightings as independent must count it once, so `sightings` (N,) (K per crater) multiplies
    its variance by K (its information then sums to one look's; a Schmidt-style consider
    approximation). None: 1 (a single-frame fix)."""
    rho = np.asarray(rho_m, dtype=float)
    k = np.sqrt(np.ones(rho.shape) if sightings is None else np.asarray(sightings, float))
    rep_h, rep_r = persistent_sigmas(noise, rho, semi_major_px, site)
    diam = 2 * np.asarray(semi_major_px, dtype=float)
    sigma_b = np.hypot(noise.pixel.centre_white_px(diam) / noise.f_px, k * rep_h / rho)
    if noise.range_source == "per_crater":
        sigma_r = np.hypot(noise.sigma_range_m, k * rep_r)
    elif noise.range_source == "apparent_size":
        sigma_r = np.hypot(apparent_size_range_sigma(rho, semi_major_px,
                                                     noise.pixel.axis_white_px(diam), 0.0),
                           k * rep_r)
    else:
        sigma_r = np.ones(rho.shape)
    return sigma_b, sigma_r
