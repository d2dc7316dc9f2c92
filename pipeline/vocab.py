"""One vocabulary for the whole package: methods, statuses, scored quantities (with labels and
units) and colours. Config validation, tables, the report and the recordings all read it here."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from pipeline.core.status import STATUSES, Status

__all__ = ["ATTITUDE", "ATTITUDE_MCI", "METHODS", "METHOD_COLORS", "POSITION", "QUANTITIES",
           "STATUSES", "STATUS_CODES", "Method", "Quantity", "Status", "quantity"]


class Method(StrEnum):
    """Single-frame pose estimators (paper Sec. 4 and the joint maximum likelihood)."""

    PAPER = "paper"  # Gauss-Newton position from ranges, then QUEST attitude from bearings
    JOINT = "joint"  # one maximum-likelihood fit of position and attitude to ranges and bearings


METHODS: tuple[str, ...] = tuple(m.value for m in Method)

# Stable integer codes of statuses for plots (a status column is the source of truth).
STATUS_CODES: dict[str, int] = {s: i for i, s in enumerate(STATUSES)}

# RGB colours per method: recordings (0-255) and report figures (hex) use the same hue.
METHOD_COLORS: dict[str, tuple[int, int, int]] = {"paper": (0, 170, 255), "joint": (40, 200, 110)}


@dataclass(frozen=True)
class Quantity:
    """A scored error quantity: its column suffix (`err_<name>`), label and unit."""

    name: str
    label: str
    unit: str  # "m" or "deg"


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
