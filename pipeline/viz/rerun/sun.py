"""The Sun (with an epoch): its direction, the day side and terminator, its elevation under the
spacecraft."""

from __future__ import annotations

import numpy as np
import rerun as rr

from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.viz.rerun.base import send_scalars, time_columns

SUN_ENTITY = "/world/sun"  # Arrows3D per frame, MCI: the Moon's centre-to-Sun line


SUNLIGHT_ENTITY = "/world/sunlight"  # Transform3D per frame: MCI from the Sun frame (+z sunward)


SUN_COLUMNS = ("sun_mci_x", "sun_mci_y", "sun_mci_z")


SUN_COLOR = (255, 205, 60)


# The arrow is drawn where the line from the Moon's centre to the Sun leaves the surface (the
# subsolar point, where the viewer puts its label) and ends SUN_ARROW_LENGTH_M further out; a
# width in UI points keeps it a line in the chase view near the surface.
SUN_ARROW_LENGTH_M = 0.6 * MOON_RADIUS_M


SUN_ARROW_RADIUS_UI = 2.5


# The lit side, static in the Sun frame (so the whole Moon's lighting costs a quaternion a
# frame): DAY_SIDE_POINTS points spread evenly over the sunlit hemisphere, shaded from a dim gold
# at the terminator to a warm white at the subsolar point (Lambert: cos incidence), and the
# terminator circle; both lifted SUNLIGHT_LIFT_M above the sphere so that its facets do not hide
# them.
DAY_SIDE_POINTS = 3000


DAY_SIDE_DIM = (200, 165, 80)


DAY_SIDE_BRIGHT = (255, 250, 225)


DAY_SIDE_POINT_RADIUS_UI = 2.0


TERMINATOR_SAMPLES = 180


SUNLIGHT_LIFT_M = 1e3


SUN_ELEVATION_ENTITY = "/trajectory/sun_elevation_deg"  # at the sub-spacecraft point


GSD_ENTITY = "/trajectory/gsd_m_per_px"  # ground sample distance at nadir


def has_sun(frames_table) -> bool:
    """Whether the detection frames carry the Sun (a scenario with trajectory.epoch_utc)."""
    return all(c in frames_table.columns for c in SUN_COLUMNS)


def q_mci_from_sun(sun_mci: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) (x, y, z, w) of the Sun frame, whose +z is the Sun's unit direction
    sun_mci (N, 3): the shortest rotation from +z (half-angle form; 180 deg about x when the
    Sun is along -z)."""
    s = np.asarray(sun_mci, dtype=float).reshape(-1, 3)
    s = s / np.linalg.norm(s, axis=1, keepdims=True)
    q = np.stack([-s[:, 1], s[:, 0], np.zeros(len(s)), 1.0 + s[:, 2]], axis=1)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(norm > 1e-9, q / np.where(norm > 1e-9, norm, 1.0), [1.0, 0.0, 0.0, 0.0])


def day_side_points(n: int = DAY_SIDE_POINTS, radius_m: float = MOON_RADIUS_M + SUNLIGHT_LIFT_M
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) evenly spread over the hemisphere z > 0 (a Fibonacci spiral, uniform in z:
    equal areas) at `radius_m`, and their colours (n, 3) uint8 by cos incidence = z / radius."""
    k = np.arange(n)
    z = (k + 0.5) / n
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    rho = np.sqrt(1.0 - z * z)
    points = radius_m * np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    dark, bright = np.array(DAY_SIDE_DIM, float), np.array(DAY_SIDE_BRIGHT, float)
    colors = np.rint(dark + (bright - dark) * z[:, None]).astype(np.uint8)
    return points, colors


def log_sun(rec: rr.RecordingStream, frames_table) -> None:
    """The Sun in the 3D view (MCI) and its series, per frame (frame and sim_time):
    - /world/sun: the arrow of the line from the Moon's centre to the Sun, from the subsolar
      point (labelled "Sun") SUN_ARROW_LENGTH_M out;
    - /world/sunlight: Transform3D MCI-from-Sun-frame (its +z towards the Sun), with the static
      /world/sunlight/day_side (points shaded by cos incidence over the lit hemisphere) and
      /world/sunlight/terminator (the day-night circle);
    - /trajectory/sun_elevation_deg: the Sun's elevation at the sub-spacecraft point (deg), and
      /trajectory/gsd_m_per_px: the ground sample distance at nadir (m/px), when present."""
    frame = frames_table["frame"].to_numpy()
    t_s = frames_table["t_s"].to_numpy()
    sun = np.stack([frames_table[c].to_numpy().astype(float) for c in SUN_COLUMNS], axis=1)
    ok = np.isfinite(sun).all(axis=1) & (np.linalg.norm(sun, axis=1) > 0)
    if ok.any():
        times = time_columns(frame[ok], t_s[ok])
        s = sun[ok] / np.linalg.norm(sun[ok], axis=1, keepdims=True)
        rec.log(SUN_ENTITY, rr.Arrows3D.from_fields(
            colors=[SUN_COLOR], radii=rr.components.Radius.ui_points(SUN_ARROW_RADIUS_UI),
            labels=["Sun"], show_labels=True), static=True)
        rec.send_columns(SUN_ENTITY, indexes=times, columns=rr.Arrows3D.columns(
            origins=s * (MOON_RADIUS_M + SUNLIGHT_LIFT_M), vectors=s * SUN_ARROW_LENGTH_M))
        rec.send_columns(SUNLIGHT_ENTITY, indexes=times,
                         columns=rr.Transform3D.columns(quaternion=q_mci_from_sun(s)))
        points, colors = day_side_points()
        rec.log(f"{SUNLIGHT_ENTITY}/day_side",
                rr.Points3D(points.astype(np.float32), colors=colors,
                            radii=rr.components.Radius.ui_points(DAY_SIDE_POINT_RADIUS_UI)),
                static=True)
        a = np.linspace(0.0, 2.0 * np.pi, TERMINATOR_SAMPLES + 1)
        ring = (MOON_RADIUS_M + SUNLIGHT_LIFT_M) * np.stack(
            [np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
        rec.log(f"{SUNLIGHT_ENTITY}/terminator",
                rr.LineStrips3D([ring.astype(np.float32)], colors=[SUN_COLOR],
                                radii=rr.components.Radius.ui_points(1.5)), static=True)
    if "sun_elevation_deg" in frames_table.columns:
        send_scalars(rec, SUN_ELEVATION_ENTITY, frame, t_s,
                     frames_table["sun_elevation_deg"].to_numpy(),
                     "Sun elevation at the sub-spacecraft point (deg)", SUN_COLOR)
    if "gsd_m" in frames_table.columns:
        send_scalars(rec, GSD_ENTITY, frame, t_s, frames_table["gsd_m"].to_numpy(),
                     "ground sample distance at nadir (m/px)")
