"""One vocabulary for the whole package: methods (`METHODS`, the registered estimators: every list
of methods reads it), statuses, scored quantities (with labels and units) and colours. Config
validation, tables, the report and the recordings all read it here. The stage tables' schemas are
in `pipeline.vocab.tables` (imported apart: it loads polars)."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.core.estimation.estimators import METHODS  # the registered estimators (paper, joint)
from pipeline.core.scoring.status import STATUSES, Status

__all__ = ["ATTITUDE", "ATTITUDE_MCI", "COUNT_COLORS", "CRLB_COLOR", "METHODS", "METHOD_COLORS",
           "POSITION", "QUANTITIES", "STATE_DIM", "STATUSES", "STATUS_CODES", "STATUS_COLORS",
           "Quantity", "Status", "hex_color", "method_color", "quantity"]



# Stable integer codes of statuses for plots (a status column is the source of truth).
STATUS_CODES: dict[str, int] = {s: i for i, s in enumerate(STATUSES)}

# RGB colours per method: recordings (0-255) and report figures (hex) use the same hue.
# The navigation filter, its RTS smoother and the IMU-only path share the table.
METHOD_COLORS: dict[str, tuple[int, int, int]] = {
    "paper": (0, 170, 255), "joint": (40, 200, 110), "filter": (250, 220, 40),
    "smoother": (250, 160, 200), "imu_only": (150, 150, 150)}

# Colours of statuses (plots of the status codes), of the crater counts and of the CRLB band.
STATUS_COLORS: dict[str, tuple[int, int, int]] = {
    "ok": (60, 200, 90), "too_few_craters": (240, 170, 0), "not_converged": (240, 90, 40),
    "degenerate": (220, 40, 40), "ill_conditioned": (200, 60, 200),
    "inconsistent": (150, 90, 230), "below_surface": (120, 120, 120),
    "not_initialised": (90, 90, 160), "needs_ranges": (0, 150, 150), "ambiguous": (180, 140, 60)}
COUNT_COLORS: dict[str, tuple[int, int, int]] = {
    "candidates": (120, 110, 220), "visible": (175, 175, 175), "identified": (255, 200, 60),
    "used": (255, 130, 0), "false_match": (230, 0, 230)}
CRLB_COLOR: tuple[int, int, int] = (200, 200, 200)

# Dimension of the pose state (3 position + 3 attitude): the expected NEES of an honest covariance.
STATE_DIM = 6


def method_color(method: str) -> tuple[int, int, int]:
    """RGB of a method (white for one not in the vocabulary)."""
    return METHOD_COLORS.get(method, (255, 255, 255))


def hex_color(rgb: tuple[int, int, int]) -> str:
    """The `#rrggbb` string of an RGB triple (0-255), for matplotlib."""
    return "#{:02x}{:02x}{:02x}".format(*rgb)


@dataclass(frozen=True)
class Quantity:
    """A scored error quantity: its column suffix (`err_<name>`), label and unit."""

    name: str
    label: str
    unit: str  # "m" or "deg"

    @property
    def axis_label(self) -> str:
        """Label with its unit, e.g. "X (m)", "roll phi (deg)"."""
        return f"{self.label} ({self.unit})"

    @property
    def short(self) -> str:
        """The axis letter or angle name without the unit, e.g. "x", "phi"."""
        return self.name.split("_")[0]


POSITION = (Quantity("x_m", "X", "m"), Quantity("y_m", "Y", "m"), Quantity("z_m", "Z", "m"))
ATTITUDE = (Quantity("phi_deg", "roll phi", "deg"), Quantity("theta_deg", "pitch theta", "deg"),
            Quantity("psi_deg", "yaw psi", "deg"))
# The same Euler angles taken about MCI axes (the paper's apparent convention, see README).
ATTITUDE_MCI = (Quantity("phi_mci_deg", "roll phi, MCI axes", "deg"),
                Quantity("theta_mci_deg", "pitch theta, MCI axes", "deg"),
                Quantity("psi_mci_deg", "yaw psi, MCI axes", "deg"))
QUANTITIES = POSITION + ATTITUDE  # the body-axis pose error (ERRATA 10), scored everywhere

_BY_NAME = {q.name: q for q in (*QUANTITIES, *ATTITUDE_MCI)}


def quantity(name: str) -> Quantity:
    """The quantity called `name` (e.g. "x_m")."""
    return _BY_NAME[name]
