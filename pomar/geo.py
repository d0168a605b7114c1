"""WGS84 <-> local ENU conversions (x east, y north, z up, metres) around an origin.

Thin, vectorised wrappers over pymap3d so that the whole project uses one convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymap3d


@dataclass(frozen=True)
class Origin:
    """Origin of a local ENU frame: latitude and longitude in degrees, altitude in metres (ellipsoid)."""

    lat: float
    lon: float
    alt: float

    def to_enu(self, lat, lon, alt) -> np.ndarray:
        """Geodetic (deg, deg, m) -> ENU (..., 3) in metres."""
        e, n, u = pymap3d.geodetic2enu(
            np.asarray(lat, float), np.asarray(lon, float), np.asarray(alt, float), self.lat, self.lon, self.alt
        )
        return np.stack([e, n, u], axis=-1)

    def to_geodetic(self, enu) -> np.ndarray:
        """ENU (..., 3) in metres -> geodetic (..., 3): lat (deg), lon (deg), alt (m)."""
        enu = np.asarray(enu, float)
        lat, lon, alt = pymap3d.enu2geodetic(enu[..., 0], enu[..., 1], enu[..., 2], self.lat, self.lon, self.alt)
        return np.stack([lat, lon, alt], axis=-1)

    def as_dict(self) -> dict:
        return {"lat": self.lat, "lon": self.lon, "alt": self.alt}


def dms_to_deg(deg: float, minutes: float, seconds: float, hemisphere: str) -> float:
    """28 30 58.2 S -> -28.516167."""
    value = abs(deg) + minutes / 60.0 + seconds / 3600.0
    return -value if hemisphere.upper() in ("S", "W") else value


#: The paper's plot at Embrapa's Vacaria station, 28°30'58.2"S 50°52'52.2"W (altitude about 960 m).
VACARIA = Origin(dms_to_deg(28, 30, 58.2, "S"), dms_to_deg(50, 52, 52.2, "W"), 960.0)
