"""The closed loop (stage `fly`): the site, the thrust flown, and guidance's series.

Entities: /world/moon/site (the target, MCMF: it turns with the Moon), /world/moon/site_terrain
(the ground around it: a mesh of the world's heights, coloured by height), /world/moon/hazard_scan
(the hazard lidar's ground points as the navigator placed them, at the scan's time),
/world/spacecraft/thrust
(the thrust flown, along body -z, its length the throttle times the chase scale), and series on
`sim_time` alone (guidance runs at its own rate): /flight/throttle, /flight/mass_kg/{true,
believed}, /flight/altitude_m, /flight/speed_m_s, /flight/phase (code), /flight/propellant_kg.
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.core.math.frames import unit_mcmf_from_latlon
from pipeline.viz.rerun.grid import TimeGrid, send_grid_scalars
from pipeline.viz.rerun.world import chase_scale

SITE_COLOR = (60, 255, 120)
THRUST_COLOR = (255, 120, 30)
PHASES = ("coast", "braking", "approach", "terminal")  # their codes: the index
THRUST_LENGTH_M = 40e3  # at full throttle, at the chase scale of 1 (150 km altitude)
TOUCHDOWN_COLOR = (255, 60, 60)


def log_flight(rec: rr.RecordingStream, guidance, touchdown, site_mcmf_m: np.ndarray,
               frames=None) -> None:
    """The guidance table (one row per call) and the touchdown row of a closed-loop run."""
    rec.log("/world/moon/site", rr.Points3D([site_mcmf_m.astype(np.float32)], radii=[300.0],
                                            colors=[SITE_COLOR], labels=["site"]), static=True)
    grid = TimeGrid.of(guidance, frames)
    t = guidance["t_s"].to_numpy()
    throttle = guidance["throttle"].to_numpy()
    altitude = guidance["altitude_m"].to_numpy()
    length = THRUST_LENGTH_M * throttle * chase_scale(np.maximum(altitude, 1.0))
    rec.send_columns("/world/spacecraft/thrust",
                     indexes=[rr.TimeColumn("sim_time", duration=t)],
                     columns=rr.Arrows3D.columns(
                         vectors=np.column_stack([np.zeros_like(t), np.zeros_like(t),
                                                  -length]).astype(np.float32)).partition(
                         np.ones(t.size, dtype=int)))
    rec.log("/world/spacecraft/thrust", rr.Arrows3D.from_fields(colors=[THRUST_COLOR]),
            static=True)
    send_grid_scalars(rec, "/flight/throttle", grid, throttle, "throttle (share of max)",
                      THRUST_COLOR)
    send_grid_scalars(rec, "/flight/mass_kg/true", grid, guidance["mass_kg"].to_numpy(),
                      "mass, true (kg)", (200, 200, 200))
    send_grid_scalars(rec, "/flight/mass_kg/believed", grid,
                      guidance["mass_belief_kg"].to_numpy(), "mass, believed (kg)",
                      (250, 220, 40))
    send_grid_scalars(rec, "/flight/propellant_kg", grid, guidance["propellant_kg"].to_numpy(),
                      "propellant (kg)", (120, 200, 255))
    send_grid_scalars(rec, "/flight/altitude_m", grid, altitude, "altitude above the surface (m)",
                      (255, 255, 255))
    send_grid_scalars(rec, "/flight/speed_m_s", grid, guidance["speed_m_s"].to_numpy(),
                      "speed (m/s)", (255, 255, 255))
    codes = np.array([PHASES.index(p) if p in PHASES else -1
                      for p in guidance["phase"].to_list()], dtype=float)
    send_grid_scalars(rec, "/flight/phase", grid, codes,
                      " | ".join(f"{i} {p}" for i, p in enumerate(PHASES)), THRUST_COLOR,
                      points=True)
    row = touchdown.row(0, named=True)
    if np.isfinite(row["t_s"]):
        u = unit_mcmf_from_latlon(np.radians(row["lat_deg"]), np.radians(row["lon_deg"]))
        rec.log("/world/moon/touchdown", rr.Points3D(
            [(u * float(np.linalg.norm(site_mcmf_m))).astype(np.float32)], radii=[100.0],
            colors=[TOUCHDOWN_COLOR],
            labels=[f"{row['status']}: {row['miss_m']:.1f} m from the site"]), static=True)


def log_hazard_scan(rec: rr.RecordingStream, scan, touchdown: dict) -> None:
    """The hazard lidar's ground points as the navigator placed them (MCMF, m), at the scan's
    time, coloured from dark (low) to light (high); nothing without a scan."""
    if scan.height == 0:
        return
    lat = np.radians(scan["lat_deg"].to_numpy())
    lon = np.radians(scan["lon_deg"].to_numpy())
    h = scan["height_m"].to_numpy()
    pos = unit_mcmf_from_latlon(lat, lon) * (MOON_RADIUS_M + h)[:, None]
    shade = (h - h.min()) / max(float(np.ptp(h)), 1e-9)
    colour = np.stack([40 + 200 * shade, 120 + 120 * shade, np.full_like(shade, 255.0)], -1)
    rec.set_time("sim_time", duration=float(touchdown["hazard_t_s"]))
    rec.log("/world/moon/hazard_scan", rr.Points3D(
        pos.astype(np.float32), radii=[0.15], colors=colour.astype(np.uint8)))


def log_site_terrain(rec: rr.RecordingStream, site_terrain) -> None:
    """The site's terrain table as a mesh (MCMF, m; vertical exaggeration none), coloured from
    dark (low) to light (high) over its height range."""
    n = math.isqrt(site_terrain.height)
    if n < 2 or n * n != site_terrain.height:
        return
    lat = np.radians(site_terrain["lat_deg"].to_numpy())
    lon = np.radians(site_terrain["lon_deg"].to_numpy())
    h = site_terrain["world_height_m"].to_numpy()
    pos = unit_mcmf_from_latlon(lat, lon) * (MOON_RADIUS_M + h)[:, None]
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    tri = np.concatenate([np.stack([a, a + 1, a + n], -1), np.stack([a + 1, a + n + 1, a + n],
                                                                   -1)])
    shade = (h - h.min()) / max(float(np.ptp(h)), 1e-9)
    grey = (60 + 170 * shade).astype(np.uint8)
    rec.log("/world/moon/site_terrain", rr.Mesh3D(
        vertex_positions=pos.astype(np.float32), triangle_indices=tri.astype(np.uint32),
        vertex_colors=np.stack([grey, grey, grey], -1)), static=True)
