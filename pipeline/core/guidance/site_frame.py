"""The landing site's frame: Cartesian, fixed on the Moon (it turns with MCMF), origin at the site.

Axes: x downrange (the approach direction, horizontal at the site), y crossrange (left of the
track), z up (radial at the site). MCMF = Rz(-theta(t)) MCI with theta = rate t
(`pipeline.core.math.frames`), so a position and its velocity relative to the Moon are
    r_mcmf = Rz(-theta) r_mci,   v_mcmf = Rz(-theta) (v_mci - w x r_mci),   w = rate z,
and Newton's law in the turning frame gains the Coriolis and centrifugal terms (Vallado,
"Fundamentals of Astrodynamics", 4th ed., Sec. 3.5):
    a_rel = g + a_thrust - 2 w x v_rel - w x (w x r).
The Moon's rotation is thus exact: the site moves ~4.6 m/s (at the equator) in MCI, and the
Coriolis term (~9 mm/s^2 at 1.7 km/s) would shift an uncorrected braking phase by ~1.6 km.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.core.dynamics.gravity import gravity_mci, gravity_xyz
from pipeline.core.math.constants import MOON_GM_M3_S2, MOON_ROTATION_RATE_RAD_S


@dataclass(frozen=True)
class SiteFrame:
    """The site (MCMF, m) and the axes dcm_mcmf_from_site (3, 3) (columns x, y, z)."""

    r_site_mcmf_m: np.ndarray
    dcm_mcmf_from_site: np.ndarray
    rotation_rate_rad_s: float = MOON_ROTATION_RATE_RAD_S

    @classmethod
    def toward(cls, r_site_mcmf_m: np.ndarray, r_from_mcmf_m: np.ndarray,
               rotation_rate_rad_s: float = MOON_ROTATION_RATE_RAD_S) -> SiteFrame:
        """The frame whose downrange axis is the horizontal (at the site) direction from a point
        r_from_mcmf_m (MCMF, m; the vehicle at powered-descent initiation) to the site."""
        site = np.asarray(r_site_mcmf_m, dtype=float)
        z = site / np.linalg.norm(site)
        d = site - np.asarray(r_from_mcmf_m, dtype=float)
        x = d - (d @ z) * z
        norm = float(np.linalg.norm(x))
        if norm < 1e-6 * float(np.linalg.norm(d)):
            raise ValueError("the vehicle is straight above the site: no downrange direction")
        x = x / norm
        return cls(site, np.stack([x, np.cross(z, x), z], axis=-1), rotation_rate_rad_s)

    def theta_rad(self, t_s: float) -> float:
        return self.rotation_rate_rad_s * t_s

    def dcm_mci_from_site(self, t_s: float) -> np.ndarray:
        """Rz(theta(t_s)) dcm_mcmf_from_site (3, 3): site axes to MCI at t_s (s)
        (`frames.dcm_mci_from_mcmf`)."""
        c, s = math.cos(self.theta_rad(t_s)), math.sin(self.theta_rad(t_s))
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ self.dcm_mcmf_from_site

    def from_mci(self, t_s: float, r_mci_m: np.ndarray, v_mci_m_s: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Position (m) and velocity relative to the Moon (m/s) in site axes, of an MCI state."""
        r = np.asarray(r_mci_m, dtype=float)
        w_x_r = self.rotation_rate_rad_s * np.array([-r[1], r[0], 0.0])
        site_from_mci = self.dcm_mci_from_site(t_s).T
        return (site_from_mci @ r - self.dcm_mcmf_from_site.T @ self.r_site_mcmf_m,
                site_from_mci @ (np.asarray(v_mci_m_s, dtype=float) - w_x_r))

    def vector_to_mci(self, t_s: float, a_site: np.ndarray) -> np.ndarray:
        """A vector (3,) in site axes expressed in MCI at t_s (s)."""
        return self.dcm_mci_from_site(t_s) @ a_site

    def apparent_gravity(self, r_site_m: np.ndarray, v_site_m_s: np.ndarray,
                         model: str = "point_mass", gm_m3_s2: float = MOON_GM_M3_S2
                         ) -> np.ndarray:
        """g - 2 w x v - w x (w x r) (..., 3) (m/s^2, site axes) at site positions (..., 3) (m)
        moving at v (m/s, relative to the Moon): the acceleration of an unthrusted body seen in
        the site frame. Gravity is evaluated in MCMF axes, which is exact for models symmetric
        about the spin axis (point mass, J2)."""
        c = self.dcm_mcmf_from_site
        r = self.r_site_mcmf_m + np.asarray(r_site_m, dtype=float) @ c.T
        v = np.asarray(v_site_m_s, dtype=float) @ c.T
        w = self.rotation_rate_rad_s
        if r.ndim == 1:  # one state (each guidance cycle): floats, `gravity_xyz`
            x, y, z = r.tolist()
            vx, vy, _ = v.tolist()
            gx, gy, gz = gravity_xyz(x, y, z, model, gm_m3_s2)
            return np.array([gx + 2.0 * w * vy + w * w * x, gy - 2.0 * w * vx + w * w * y,
                             gz]) @ c
        coriolis = -2.0 * w * np.stack([-v[..., 1], v[..., 0], np.zeros(v.shape[:-1])], axis=-1)
        centrifugal = w * w * np.stack([r[..., 0], r[..., 1], np.zeros(r.shape[:-1])], axis=-1)
        return (gravity_mci(r, model, gm_m3_s2) + coriolis + centrifugal) @ c
