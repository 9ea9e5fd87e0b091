"""Interactive relighting in the browser: ``hfrad view FILE.hfr``.

A viser web app over a factorization: one control group per emitter
(on/off, intensity, colour; any material can be made an emitter), exposure
and false colour, live timings, and buttons that save the view as PNG (through
``hfrad render``'s renderer) and the emission as JSON (``--emission-file``).

>>> import hfrad                                        # doctest: +SKIP
>>> from hfrad.viewer import ViewerApp                  # doctest: +SKIP
>>> app = ViewerApp(hfrad.load("cornell.hfr"))          # doctest: +SKIP
>>> app.url                                             # doctest: +SKIP
'http://127.0.0.1:8080/?token=...'

The server answers only that page (Host, Origin and token checked on every
request: :mod:`hfrad.viewer.guard`).
"""

__all__ = ["ViewerApp", "UpdateStats", "Emitter", "Lighting", "scene_emitters", "DEFAULT_HOST", "DEFAULT_PORT"]

_HOME = {"ViewerApp": "app", "UpdateStats": "app", "DEFAULT_HOST": "app", "DEFAULT_PORT": "app",
         "Emitter": "lighting", "Lighting": "lighting", "scene_emitters": "lighting"}


def __getattr__(name: str):
    # lazy: `hfrad view` checks --host (viewer.guard, standard library only) before numpy and viser load
    if name in _HOME:
        import importlib

        return getattr(importlib.import_module(f".{_HOME[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
