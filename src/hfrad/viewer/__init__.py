"""Interactive relighting in the browser: ``hfrad view FILE.hfr``.

A viser web app over a factorization: one control group per emitter
(on/off, intensity, colour; any material can be made an emitter), exposure
and false colour, live timings, and buttons that save the view as PNG (through
``hfrad render``'s renderer) and the emission as JSON (``--emission-file``).

>>> import hfrad                                        # doctest: +SKIP
>>> from hfrad.viewer import ViewerApp                  # doctest: +SKIP
>>> app = ViewerApp(hfrad.load("cornell.hfr"))          # doctest: +SKIP
>>> app.url                                             # doctest: +SKIP
'http://127.0.0.1:8080'
"""

from .app import DEFAULT_HOST, DEFAULT_PORT, UpdateStats, ViewerApp
from .lighting import Emitter, Lighting, scene_emitters

__all__ = ["ViewerApp", "UpdateStats", "Emitter", "Lighting", "scene_emitters", "DEFAULT_HOST", "DEFAULT_PORT"]
