"""WGS-84 geodetic coordinates and the local NED tangent plane.

The navigation frame is the NED tangent plane at a reference point
(``lat0_deg, lon0_deg, alt0_m``), treated as flat and non-rotating: gravity is
``[0, 0, g0]`` everywhere in it and Earth rate is ignored (a nine-accelerometer
array cannot sense 7.3e-5 rad/s). Conversions between that plane and WGS-84
latitude, longitude and ellipsoidal altitude are exact (through ECEF), so GPS
fixes far from the reference land where they belong.
"""

from __future__ import annotations

import numpy as np

#: WGS-84 semi-major axis, m, and flattening (NIMA TR8350.2).
WGS84_A_M: float = 6378137.0
WGS84_F: float = 1.0 / 298.257223563
WGS84_E2: float = WGS84_F * (2.0 - WGS84_F)


def geodetic_to_ecef(lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray) -> np.ndarray:
    """ECEF position (..., 3), m, of WGS-84 latitude/longitude (deg) and altitude (m)."""
    lat = np.deg2rad(np.asarray(lat_deg, dtype=float))
    lon = np.deg2rad(np.asarray(lon_deg, dtype=float))
    h = np.asarray(alt_m, dtype=float)
    sl, cl = np.sin(lat), np.cos(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sl * sl)
    return np.stack(
        [(n + h) * cl * np.cos(lon), (n + h) * cl * np.sin(lon), (n * (1 - WGS84_E2) + h) * sl],
        axis=-1,
    )


def ecef_to_geodetic(xyz_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """WGS-84 latitude, longitude (deg) and altitude (m) of ECEF points (..., 3).

    Bowring's start and three Newton-like refinements: exact to well below a
    millimetre for points near the Earth's surface.
    """
    p = np.asarray(xyz_m, dtype=float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lon = np.arctan2(y, x)
    r = np.hypot(x, y)
    lat = np.arctan2(z, r * (1.0 - WGS84_E2))
    for _ in range(5):
        sl = np.sin(lat)
        n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sl * sl)
        h = r / np.cos(lat) - n
        lat = np.arctan2(z, r * (1.0 - WGS84_E2 * n / (n + h)))
    sl = np.sin(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sl * sl)
    h = r / np.cos(lat) - n
    return np.rad2deg(lat), np.rad2deg(lon), h


def ecef_to_ned_matrix(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Rotation (3, 3) taking ECEF vectors into NED at the given latitude/longitude."""
    lat, lon = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.array([[-sl * co, -sl * so, cl], [-so, co, 0.0], [-cl * co, -cl * so, -sl]])


class LocalTangentPlane:
    """NED tangent plane at a WGS-84 reference point.

    Parameters
    ----------
    lat0_deg, lon0_deg : float
        Reference latitude and longitude, deg.
    alt0_m : float
        Reference ellipsoidal altitude, m.
    """

    def __init__(self, lat0_deg: float, lon0_deg: float, alt0_m: float) -> None:
        for name, v in (("lat0_deg", lat0_deg), ("lon0_deg", lon0_deg), ("alt0_m", alt0_m)):
            if not np.isfinite(v):
                raise ValueError(f"{name} must be finite, got {v}")
        if not -90.0 < lat0_deg < 90.0:
            raise ValueError(f"lat0_deg must be inside (-90, 90), got {lat0_deg}")
        self.lat0_deg, self.lon0_deg, self.alt0_m = float(lat0_deg), float(lon0_deg), float(alt0_m)
        self._origin = geodetic_to_ecef(lat0_deg, lon0_deg, alt0_m)
        self._r_ne = ecef_to_ned_matrix(lat0_deg, lon0_deg)

    def to_ned(self, lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray) -> np.ndarray:
        """NED position (..., 3), m, of geodetic points."""
        d = geodetic_to_ecef(lat_deg, lon_deg, alt_m) - self._origin
        return d @ self._r_ne.T

    def to_geodetic(self, pos_ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Latitude, longitude (deg) and altitude (m) of NED positions (..., 3)."""
        xyz = self._origin + np.asarray(pos_ned_m, dtype=float) @ self._r_ne
        return ecef_to_geodetic(xyz)
