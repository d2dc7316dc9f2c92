"""The scenario epoch: an ISO 8601 UTC time inside the span of the DE421 ephemeris the Sun comes
from (`pipeline.io.ephemeris`)."""

from __future__ import annotations

from datetime import UTC, datetime

from pipeline.errors import ConfigError

# DE421's span (JD 2414864.5 - 2471184.5 TDB) less a day at each end for the light time.
DE421_FIRST_UTC = datetime(1899, 7, 30, tzinfo=UTC)
DE421_LAST_UTC = datetime(2053, 10, 7, tzinfo=UTC)


def parse_epoch_utc(epoch_utc: str) -> datetime:
    """An ISO 8601 time as an aware UTC datetime; no offset means UTC, another offset is converted.

    Raises ConfigError (one line) for anything else or an epoch outside DE421's span.
    """
    text = epoch_utc.strip() if isinstance(epoch_utc, str) else None
    try:
        if not text:
            raise ValueError
        dt = datetime.fromisoformat(text)
    except ValueError:
        raise ConfigError(f"epoch_utc {epoch_utc!r} is not an ISO 8601 UTC time such as "
                          f"'2025-03-14T06:55:00Z'") from None
    dt = dt.replace(tzinfo=UTC) if dt.tzinfo is None else dt.astimezone(UTC)
    if not DE421_FIRST_UTC <= dt <= DE421_LAST_UTC:
        raise ConfigError(f"epoch_utc {epoch_utc!r} is outside the DE421 ephemeris "
                          f"({DE421_FIRST_UTC:%Y-%m-%d} to {DE421_LAST_UTC:%Y-%m-%d})")
    return dt
