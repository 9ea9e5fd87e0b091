"""Daylight: sky, sun and windows hour by hour over a year (climate-based daylight modelling).

The layer above :mod:`hfrad.lighting` (it reuses its sensor grids, gather
operator and plans). A weather file (TMY3 or EPW, read with pvlib) gives a
year of direct and diffuse irradiance (:mod:`.weather`); Radiance's
``gendaymtx`` turns it into Perez sky and sun matrices over Reinhart's
patches (:mod:`.sky`); rays through the glazing give the first-hit
irradiance of every patch and sensor from each sky patch, one batched
``fac.solve`` the interreflections (:mod:`.coefficients`, :mod:`.model`), so a
year is a product of small matrices plus the direct sun by rays; IES LM-83
metrics (:mod:`.metrics`) and pictures (:mod:`.report`) summarise it.
See docs/daylight.md.
"""

from .glazing import GlazingTracer, angular_factor
from .metrics import OCCUPANCY, daylight_metrics, occupied_hours
from .model import AnnualResult, DaylightCoefficients, DaylightModel
from .report import carpet_image, metric_plans, write_hourly, write_metrics
from .rooms import sidelit_room
from .run import daylight_year
from .sky import RADIANCE_LUMINANCE, SkyPatches, sky_matrices, sky_patches
from .weather import Weather, read_weather

__all__ = ["Weather", "read_weather", "SkyPatches", "sky_patches", "sky_matrices", "RADIANCE_LUMINANCE",
           "GlazingTracer", "angular_factor", "DaylightModel", "DaylightCoefficients", "AnnualResult",
           "daylight_metrics", "occupied_hours", "OCCUPANCY", "write_hourly", "write_metrics", "carpet_image",
           "metric_plans", "sidelit_room", "daylight_year"]
