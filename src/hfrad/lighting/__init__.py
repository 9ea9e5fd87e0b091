"""Lighting with catalogue luminaires: photometric files, direct light, sensors and work planes.

The layer above :mod:`hfrad.solve` and :mod:`hfrad.render` (it reuses the
false-colour map and the lux conversion), below :mod:`hfrad.inverse` and the
CLI. Photometric files (IES LM-63, EULUMDAT) give a candela table
(:mod:`.photometry`); luminaires place it (:mod:`.luminaire`); their direct
light on patches and sensors is ray cast with Embree (:mod:`.direct`); a
:class:`LightingModel` solves the interreflections of all luminaires in one
batched ``fac.solve`` and gathers them at sensors (:mod:`.gather`), so any
dimming is relit in O(m L); :mod:`.report` summarises grids (average,
minimum, U0) and draws plans; :mod:`.spaces` lays one work plane per IfcSpace
of a building model. See docs/lighting.md and docs/buildings.md.
"""

from .direct import caster_for, direct_illuminance, patch_direct_illuminance
from .gather import GatherOperator, gather_operator
from .luminaire import LayoutError, Luminaire, parse_layout, read_layout
from .model import LightingModel, SensorResponse
from .photometry import Photometry, parse_ies, parse_ldt, read_photometry
from .report import grid_stats, plan_image, save_plan, write_csv, write_json
from .sensors import SensorSet, floor_grid, plan_grid, read_sensors, rectangle_grid, write_sensors
from .spaces import space_grids

__all__ = ["Photometry", "parse_ies", "parse_ldt", "read_photometry", "Luminaire", "LayoutError", "parse_layout",
           "read_layout", "direct_illuminance", "patch_direct_illuminance", "caster_for", "GatherOperator",
           "gather_operator", "LightingModel", "SensorResponse", "SensorSet", "read_sensors", "write_sensors",
           "rectangle_grid", "floor_grid", "plan_grid", "space_grids", "grid_stats", "write_csv", "write_json",
           "plan_image", "save_plan"]
