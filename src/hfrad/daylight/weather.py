"""A year of weather: TMY3 or EPW files read with pvlib, hours in local standard time, sun positions.

Both formats label each record with the hour it *ends* (``1:00`` is the
hour from 0:00 to 1:00, in the file's local standard time, no daylight
saving); pvlib's index keeps that label for TMY3 and moves EPW's to the
hour's start. The middle of that hour (``0:30``) stands for it: the sky and the
sun of the record are taken there, as Radiance's ``epw2wea`` does. Sun
positions come from :func:`pvlib.solarposition.get_solarposition` (SPA) at
those instants; irradiances are the file's direct-normal (DNI) and
diffuse-horizontal (DHI) values, W/m^2.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FileFormatError, InputError

__all__ = ["Weather", "read_weather", "HOURS_PER_YEAR"]

HOURS_PER_YEAR = 8760
#: a year without 29 February, so that leap-year TMY files and plots line up (the file's own year is kept nowhere)
_YEAR = 2001


@dataclass(frozen=True)
class Weather:
    """Hourly direct and diffuse irradiance of a site.

    Attributes
    ----------
    path : Path
    place : str
    latitude, longitude : float, degrees (north, east positive)
    timezone : float, hours from UTC of the file's standard time (east positive)
    elevation : float, metres
    month, day : (h,) int
    hour : (h,) float, middle of each record's hour, local standard time (0.5 .. 23.5)
    dni, dhi : (h,) float, W/m^2: direct normal and diffuse horizontal irradiance
    """

    path: Path
    place: str
    latitude: float
    longitude: float
    timezone: float
    elevation: float
    month: np.ndarray
    day: np.ndarray
    hour: np.ndarray
    dni: np.ndarray
    dhi: np.ndarray

    def __len__(self) -> int:
        return len(self.hour)

    @property
    def day_of_year(self) -> np.ndarray:
        """(h,) int, 0..364."""
        start = np.cumsum([0, 31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30])
        return start[self.month - 1] + self.day - 1

    def wea(self) -> str:
        """The year as a Radiance weather tape (``.wea``: longitude and meridian west positive)."""
        head = (f"place {self.place}\nlatitude {self.latitude:.4f}\nlongitude {-self.longitude:.4f}\n"
                f"time_zone {-15.0 * self.timezone:.1f}\nsite_elevation {self.elevation:.1f}\n"
                "weather_data_file_units 1\n")
        rows = "".join(f"{m} {d} {h:.3f} {a:.1f} {b:.1f}\n"
                       for m, d, h, a, b in zip(self.month, self.day, self.hour, self.dni, self.dhi))
        return head + rows

    def sun(self) -> tuple[np.ndarray, np.ndarray]:
        """(altitude, azimuth) (h,) each, degrees: the sun at each record's mid-hour (pvlib SPA).

        Azimuth is measured from north toward east, as Radiance's sky patches are.
        """
        import pandas as pd
        import pvlib

        minutes = np.round(self.hour * 60).astype(int)
        times = (pd.to_datetime({"year": np.full(len(self), _YEAR), "month": self.month, "day": self.day})
                 + pd.to_timedelta(minutes, unit="min"))
        times = pd.DatetimeIndex(times).tz_localize(f"Etc/GMT{-int(self.timezone):+d}"
                                                    if float(self.timezone).is_integer()
                                                    else None)
        if times.tz is None:   # half-hour zones: pvlib takes UTC
            times = (times - pd.Timedelta(hours=self.timezone)).tz_localize("UTC")
        pos = pvlib.solarposition.get_solarposition(times, self.latitude, self.longitude, altitude=self.elevation)
        return np.asarray(pos["apparent_elevation"], float), np.asarray(pos["azimuth"], float)


def read_weather(path: "str | Path") -> Weather:
    """Read a TMY3 (``.csv``) or EPW (``.epw``) file with :mod:`pvlib.iotools`.

    Raises
    ------
    InputError
        The file does not exist or has another suffix.
    FileFormatError
        pvlib cannot read it, or a field is missing or out of range; the message names the file and the field.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"weather file '{path}' not found")
    kind = path.suffix.lower()
    if kind not in (".csv", ".epw"):
        raise InputError(f"weather file '{path}' must be TMY3 (.csv) or EPW (.epw), got '{path.suffix}'")
    import pvlib

    try:
        if kind == ".csv":
            data, meta = pvlib.iotools.read_tmy3(str(path), coerce_year=_YEAR, map_variables=True)
            place, tz, elev = str(meta.get("Name", path.stem)).strip('"'), meta.get("TZ"), meta.get("altitude")
        else:
            data, meta = pvlib.iotools.read_epw(str(path), coerce_year=_YEAR)
            place, tz, elev = str(meta.get("city", path.stem)), meta.get("TZ"), meta.get("altitude")
    except Exception as exc:   # pvlib raises many kinds on a malformed file; the user gets one line
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise FileFormatError(f"{path}: not a readable {'TMY3' if kind == '.csv' else 'EPW'} file ({first})") from None
    for field, value in (("latitude", meta.get("latitude")), ("longitude", meta.get("longitude")),
                         ("time zone", tz), ("elevation", elev)):
        if value is None or not np.isfinite(float(value)):
            raise FileFormatError(f"{path}: header field '{field}' is missing or not a number")
    lat, lon = float(meta["latitude"]), float(meta["longitude"])
    if not (-90 <= lat <= 90 and -180 <= lon <= 180 and -14 <= float(tz) <= 14):
        raise FileFormatError(f"{path}: header latitude {lat}, longitude {lon} or time zone {tz} out of range")
    for field in ("dni", "dhi"):
        if field not in data:
            raise FileFormatError(f"{path}: no '{field}' column")
        v = np.asarray(data[field], float)
        bad = np.flatnonzero(~np.isfinite(v) | (v < 0) | (v > 1500))
        if len(bad):
            raise FileFormatError(f"{path}: field '{field}' of record {bad[0] + 1} is {v[bad[0]]:g} "
                                  "(expected 0..1500 W/m^2)")
    if len(data) != HOURS_PER_YEAR:
        raise FileFormatError(f"{path}: {len(data)} hourly records, expected {HOURS_PER_YEAR} (one year)")
    # pvlib labels a TMY3 record with the hour it ends (1:00) and an EPW record with the hour it
    # starts (its Hour field minus one: 0:00); the middle of the hour is 30 min off either way
    mid = data.index + np.timedelta64(-30 if kind == ".csv" else 30, "m")
    return Weather(path, place, lat, lon, float(tz), float(elev), np.asarray(mid.month, int),
                   np.asarray(mid.day, int), np.asarray(mid.hour + mid.minute / 60.0, float),
                   np.asarray(data["dni"], float), np.asarray(data["dhi"], float))
