"""The ``hfrad view`` web app: interactive relighting of a factorization in the browser.

One :class:`ViewerApp` serves any number of browser tabs (viser's own client:
no CDN, nothing downloaded at run time). The lights and display controls are
shared by all tabs; each tab has its own camera. Every control change hands
the newest state to one worker (:class:`~hfrad.viewer.coalesce.LatestWins`),
which computes the radiosity (:class:`~hfrad.viewer.lighting.Lighting`), the
vertex colours (:mod:`hfrad.viewer.display`) and pushes them to every tab.
"""

from __future__ import annotations

import dataclasses
import datetime
import logging
import math
import os
import threading
import time
import warnings
from pathlib import Path
from typing import Callable

import numpy as np

from .. import memory
from ..errors import AccuracyWarning, InputError
from ..io.emission import emission_json, loads_emission, write_emission
from ..render.camera import Camera
from ..render.falsecolor import UNITS
from ..render.image import BYTES_PER_PIXEL
from .coalesce import LatestWins
from .display import MeshColors, MeshGLB, colorbar, precompensate_aces
from .guard import PageGuard, UploadLimit, check_bindable, guarded_server, is_loopback, self_test, url_host
from .lighting import DEFAULT_INTENSITY, Emitter, Lighting, scene_emitters

log = logging.getLogger(__name__)

#: Address the server binds unless told otherwise: this machine only.
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
#: Height in pixels of pictures saved from the page (width follows the tab's aspect ratio).
PNG_HEIGHT = 720
#: Largest side, pixels, of a picture rendered for the page (the tab reports its aspect ratio).
MAX_PICTURE_SIDE = 8192
#: Largest intensity, W/m^2, a control may set (the sun gives ~1e3; far from float32's 3.4e38).
MAX_INTENSITY = 1e12
#: Largest file the page's "load emission" accepts, bytes (an emission file is ~100 bytes per emitter).
MAX_UPLOAD_BYTES = 1 << 20
_EV_RANGE = (-12.0, 12.0)


def _import_viser():
    try:
        import viser
    except ImportError as exc:
        raise ImportError(f"hfrad view needs viser ({exc}); install it with `pip install viser`") from None
    return viser


def _start_server(viser, guard: PageGuard, host: str, port: int, verbose: bool):
    """A ``viser.ViserServer`` on ``host:port`` whose every request passes ``guard``'s checks."""
    import rich

    console = rich.get_console()
    quiet = console.quiet
    if not verbose:
        console.quiet = True    # viser's banner shows the address without the token: a link that gets 403
    try:
        with guarded_server(guard):
            return viser.ViserServer(host=host, port=port, verbose=verbose)
    finally:
        console.quiet = quiet


def _checked_exposure(value) -> float:
    """The exposure slider's value, EV, if it is a number within the slider's range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not _EV_RANGE[0] <= value <= _EV_RANGE[1]:
        raise InputError(f"exposure must be a number in [{_EV_RANGE[0]:g}, {_EV_RANGE[1]:g}] EV, got {value!r:.60}")
    return float(value)


def _checked_unit(value) -> str:
    if value not in UNITS:
        raise InputError(f"unit must be one of {', '.join(UNITS)}, got {str(value)[:60]!r}")
    return str(value)


def _solution_error(fac, E: np.ndarray, B: np.ndarray):
    """The error figure of the lighting on screen (:meth:`HFactorization.solution_error`), or None."""
    try:
        return fac.solution_error(E, B)
    except Exception as exc:  # a figure that fails must not take the page down
        log.warning("error figure failed: %s", exc)
        return None


def _error_estimate(fac) -> np.ndarray:
    """(3,) float: the factorization's a-priori relative radiosity error per channel (inf: none)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)   # shown on the page as "none" instead
        return np.asarray(fac.error_estimate().bound, dtype=np.float64)


@dataclasses.dataclass
class ViewState:
    """What the controls say; shared by all tabs."""

    emitters: list[Emitter]
    auto_exposure: bool = True
    exposure: float = 0.0
    falsecolor: bool = False
    unit: str = "W/m2"


@dataclasses.dataclass(frozen=True)
class UpdateStats:
    """Timings of one update, seconds (``changed`` on the ``time.perf_counter`` clock)."""

    changed: float
    solve: float
    colors: float
    sent: float
    bytes: int


class ViewerApp:
    """A viser server showing a factorization's radiosity under live lights.

    Parameters
    ----------
    fac : HFactorization
        With its scene (``hfrad.load`` of a file from ``hfrad precompute``).
    host : str
        Address to bind; the default serves this machine only. An address that
        cannot be bound raises InputError at once.
    port : int
        The next free port is taken if it is busy.
    save_dir : path
        Where the page's "save" buttons write files (they are also sent to the browser).
    direct : bool
        Re-solve ``fac.solve(E)`` on every change instead of combining unit solutions.
    verbose : bool
        Let viser print its banner and connection log.
    token : str, optional
        The secret the page's URL carries; a fresh random one by default.

    Attributes
    ----------
    server : viser.ViserServer
    url : str
        The page's address, with its token: ``http://127.0.0.1:8080/?token=...``.
    guard : PageGuard
        The checks on every request (Host, Origin, token; see :mod:`hfrad.viewer.guard`).
    last : UpdateStats or None
        The latest update.

    Notes
    -----
    The server answers only its own page: a request whose ``Host`` does not
    name this machine, a websocket opened from another site's page (foreign
    ``Origin``) and a request without the token are refused with 403.
    """

    def __init__(self, fac, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, save_dir: "str | Path" = ".",
                 direct: bool = False, verbose: bool = False, token: str | None = None) -> None:
        if fac.scene is None:
            raise InputError("the factorization has no patches stored; re-run `hfrad precompute` (it stores them)")
        host = str(host).strip()
        if host.startswith("[") and host.endswith("]"):
            host = host[1:-1]                      # [::1] as written in URLs
        if isinstance(port, bool) or int(port) != port or not 0 <= port < 65536:
            raise InputError(f"port must be a whole number in [0, 65535], got {port!r}")
        port = check_bindable(host, int(port))     # fails at once (viser would hang); busy: the next free port
        viser = _import_viser()
        self.guard = PageGuard(host, token)
        self.fac, self.scene = fac, fac.scene
        self.save_dir = Path(save_dir)
        self.direct = direct
        emitters, self.warnings = scene_emitters(self.scene)
        self.state = ViewState(emitters=emitters)
        self._lock = threading.RLock()
        self.lighting = Lighting(fac)
        self.colors = MeshColors(self.scene)
        self.glb = MeshGLB(self.colors.vertices, self.colors.faces)
        self.last: UpdateStats | None = None
        self._shown: tuple | None = None           # (B, E, exposure, falsecolor, unit) on screen now
        self._colorbar_key: tuple | None = None
        self._listeners: list[Callable[[UpdateStats], None]] = []
        self._error = None
        self._solution = None     # the error figure of the lighting on screen (SolutionError or None)
        self._mesh = None

        self._names_lock = threading.Lock()
        self.server = _start_server(viser, self.guard, host, port, verbose)
        self.host, self.port = host, self.server.get_port()
        try:
            self_test(host, self.port)
            self._lock_down()
        except Exception:
            self.server.stop()
            raise
        self._frame_camera()
        self._build_gui()
        self._worker: LatestWins[float] = LatestWins(self._update, self._update_failed, name="hfrad-view")
        self._update(time.perf_counter())          # first picture before anyone connects
        threading.Thread(target=self._estimate_error, daemon=True).start()

    # -- public ----------------------------------------------------------------
    @property
    def url(self) -> str:
        """The page's address with its token (for a wildcard bind: this machine's loopback address)."""
        return f"http://{url_host(self.host)}:{self.port}/?token={self.guard.token}"

    @property
    def loopback_only(self) -> bool:
        """True if the server is reachable from this machine only."""
        return is_loopback(self.host)

    def submit(self) -> float:
        """Schedule an update for the current state; returns its change time (perf_counter)."""
        t = time.perf_counter()
        self._worker.submit(t)
        return t

    def set_emitter(self, name: str, **changes) -> float:
        """Change an emitter (``on``, ``intensity``, ``color``) and schedule an update, as a control does.

        Raises
        ------
        InputError
            An unknown name, an intensity outside [0, MAX_INTENSITY] W/m^2 or a colour outside [0, 1].
        """
        if "intensity" in changes:
            v = changes["intensity"]
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not 0 <= v <= MAX_INTENSITY:
                raise InputError(f"emitter '{name}': intensity must be a number in [0, {MAX_INTENSITY:g}] W/m^2, "
                                 f"got {v!r:.60}")
        with self._lock:
            i = self._index(name)
            self.state.emitters[i] = dataclasses.replace(self.state.emitters[i], **changes)
        return self.submit()

    def add_emitter(self, name: str, intensity: float = DEFAULT_INTENSITY) -> float:
        """Make a material or group an emitter (white) and schedule an update."""
        with self._lock:
            if any(e.name == name for e in self.state.emitters):
                raise InputError(f"'{name}' is already an emitter")
            self.lighting.masks((name,))           # unknown names fail here, with the list of names
            self.state.emitters.append(Emitter(name, intensity))
        self._build_lights()
        return self.submit()

    def load_emission(self, text: str, source: str = "<upload>") -> float:
        """Set the emitters an emission file's text lists (others keep theirs); schedule an update."""
        emitters = [Emitter.from_setting(s) for s in loads_emission(text, source)]
        self.lighting.masks(tuple(e.name for e in emitters))   # names must exist
        with self._lock:
            # names the file does not list keep their light, as `--emission-file` keeps the scene's
            listed = {e.name for e in emitters}
            self.state.emitters = [e for e in self.state.emitters if e.name not in listed] + emitters
        self._build_lights()
        return self.submit()

    def emission_text(self) -> str:
        """The current emitters as an emission file (JSON text)."""
        with self._lock:
            return emission_json([e.setting() for e in self.state.emitters])

    def add_listener(self, fn: Callable[[UpdateStats], None]) -> None:
        """Call ``fn(stats)`` from the worker after every update (tests, benchmarks)."""
        self._listeners.append(fn)

    def wait_idle(self, timeout: float | None = None) -> bool:
        return self._worker.wait_idle(timeout)

    def close(self) -> None:
        self._worker.close()
        self.server.stop()

    def _lock_down(self) -> None:
        """What a connected tab may ask of the server: no share tunnel, uploads capped in size."""
        from viser import _messages as msgs

        ws = self.server._websock_server
        # viser's "share" asks the server to open a public tunnel to share.viser.studio: not here
        if msgs.ShareUrlRequest in getattr(ws, "_incoming_handlers", {}):
            ws.unregister_handler(msgs.ShareUrlRequest)
        self.uploads: UploadLimit | None = UploadLimit(MAX_UPLOAD_BYTES, on_refused=self._notify_id)
        try:
            self.uploads.install(ws)
        except RuntimeError as exc:      # a viser that uploads differently: no upload button
            log.warning("%s; the page offers no 'load emission' button", exc)
            self.uploads = None

    def _notify_id(self, client_id: int, text: str) -> None:
        client = self.server.get_clients().get(client_id)
        self._notify(client, "Not done", text, error=True)

    # -- the update path -----------------------------------------------------------
    def _update(self, changed: float) -> None:
        with self._lock:
            emitters = list(self.state.emitters)
            state = dataclasses.replace(self.state, emitters=emitters)
        t0 = time.perf_counter()
        B = self.lighting.radiosity(emitters, direct=self.direct)
        E = self.lighting.exitance(emitters)
        t1 = time.perf_counter()
        solution = _solution_error(self.fac, E, B)     # O(n m) from the stored rows of F
        if state.falsecolor:
            display, top = self.colors.falsecolor(B, E, state.unit)
            exposure = None
        else:
            display, exposure = self.colors.shaded(B, E, None if state.auto_exposure else state.exposure)
        glb = self.glb.encode(precompensate_aces(display))
        t2 = time.perf_counter()
        if self._mesh is None:
            self._mesh = self.server.scene.add_glb("/radiosity", glb, cast_shadow=False, receive_shadow=False)
        else:
            self._mesh.glb_data = glb
        self.server.flush()
        t3 = time.perf_counter()
        stats = UpdateStats(changed, t1 - t0, t2 - t1, t3 - changed, len(glb))
        with self._lock:
            self.last = stats
            self._shown = (B, E, exposure, state.falsecolor, state.unit)
            self._solution = solution
        if state.falsecolor:
            self._show_colorbar(state.unit, top)
        elif self._colorbar_key is not None:
            self._colorbar.visible = False
            self._colorbar_key = None
        self._show_readout(stats, exposure)
        for fn in list(self._listeners):
            fn(stats)

    def _update_failed(self, changed: float, exc: BaseException) -> None:
        self._readout.content = f"**update failed:** {exc}"

    def _estimate_error(self) -> None:
        try:
            self._error = _error_estimate(self.fac)
        except Exception as exc:  # an estimate that fails must not take the page down
            log.warning("error estimate failed: %s", exc)
            self._error = exc
        if self.last is not None:
            self._show_readout(self.last, self._shown[2] if self._shown else None)

    def _show_readout(self, stats: UpdateStats, exposure: float | None) -> None:
        if self._error is None:
            err = "computing..."
        elif isinstance(self._error, Exception):
            err = "unavailable"
        else:
            err = " / ".join(f"{100 * e:.3g}%" if np.isfinite(e) else "none (eq. 5 needs sigma < 1)"
                             for e in self._error)
        solution = self._solution
        if solution is None or solution.kind == "unavailable":
            this = "unavailable (no stored rows of F in this file)"
        else:
            this = (" / ".join(f"{100 * e:.3g}%" if np.isfinite(e) else "none" for e in solution.bound)
                    + " of the reflected light" + ("" if solution.failure_probability is None else
                                                   f" (sampled rows; may fail with p = {solution.failure_probability:.2g})"))
        mode = "direct solve" if self.direct else \
            f"sum of {len(self.lighting.names)} batched unit solves ({1e3 * self.lighting.basis_seconds:.0f} ms)"
        shown = "false colour" if exposure is None else f"exposure {exposure:+.2f} EV"
        self._readout.content = (
            f"**solve** {1e3 * stats.solve:.1f} ms ({mode})  \n"
            f"**colours sent** {1e3 * stats.sent:.1f} ms after the change ({stats.bytes / 1e6:.2f} MB)  \n"
            f"**rank** {self.fac.rank:,} · **patches** {self.scene.n_patches:,}  \n"
            f"**error of this lighting** (R / G / B) {this}  \n"
            f"**a-priori bound, any lighting** (R / G / B) {err}  \n"
            f"{shown} · updates {self._worker.handled + 1}, coalesced {self._worker.replaced}")

    def _show_colorbar(self, unit: str, top: float) -> None:
        key = (unit, top)
        if key != self._colorbar_key:
            self._colorbar.image = colorbar(unit, top)
            self._colorbar_key = key
        self._colorbar.visible = True

    # -- page ----------------------------------------------------------------------
    def _frame_camera(self) -> None:
        self.server.scene.set_up_direction("+y")
        # black behind the scene, as in rendered pictures
        self.server.scene.set_background_image(np.zeros((8, 8, 3), np.uint8), format="png")
        cam = Camera.auto(self.scene.bounds, aspect=4 / 3)
        self.server.initial_camera.position = cam.position
        self.server.initial_camera.look_at = cam.target
        self.server.initial_camera.fov = math.radians(cam.fov)

    def _guard(self, fn: Callable) -> Callable:
        """Wrap a control's callback: a failure is shown to its tab, never raised into the server."""
        def run(event) -> None:
            try:
                fn(event)
            except Exception as exc:
                log.info("control callback failed: %s", exc)
                self._notify(getattr(event, "client", None), "Not done", str(exc), error=True)
        return run

    def _notify(self, client, title: str, body: str, *, error: bool = False) -> None:
        if client is None:
            return
        try:
            client.add_notification(title, body, color="red" if error else None, auto_close_seconds=8.0)
        except Exception:  # the tab may have gone
            log.info("could not notify a client: %s: %s", title, body)

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False)
        gui.add_markdown(f"**hfrad view** · {self.scene.name}")
        self._readout = gui.add_markdown("starting...")
        self._lights_folder = gui.add_folder("Lights")
        self._light_handles: list = []
        self._build_lights()
        with gui.add_folder("Add an emitter"):
            names = [m for m in self.scene.material_names] + \
                [g for g in self.scene.groups if g not in self.scene.material_names]
            self._new_emitter = gui.add_dropdown("material", names, initial_value=names[0])
            gui.add_button("make emitter").on_click(
                self._guard(lambda ev: self.add_emitter(self._new_emitter.value)))
        with gui.add_folder("Display"):
            auto = gui.add_checkbox("auto exposure", initial_value=True)
            ev = gui.add_slider("exposure (EV)", min=_EV_RANGE[0], max=_EV_RANGE[1], step=0.1, initial_value=0.0)
            fc = gui.add_checkbox("false colour", initial_value=False)
            unit = gui.add_dropdown("unit", list(UNITS), initial_value="W/m2")
            self._colorbar = gui.add_image(colorbar("W/m2", 1.0), label="scale", format="png", visible=False)

            def set_display(**changes):
                def cb(event) -> None:
                    values = {k: f() for k, f in changes.items()}    # all checked before any is set
                    with self._lock:
                        for k, v in values.items():
                            setattr(self.state, k, v)
                    self.submit()
                return self._guard(cb)

            # the browser may send any value (viser checks neither ranges nor choices): checked here
            auto.on_update(set_display(auto_exposure=lambda: bool(auto.value)))
            ev.on_update(set_display(exposure=lambda: _checked_exposure(ev.value), auto_exposure=lambda: False))
            ev.on_update(lambda _: setattr(auto, "value", False) if auto.value else None)
            fc.on_update(set_display(falsecolor=lambda: bool(fc.value)))
            unit.on_update(set_display(unit=lambda: _checked_unit(unit.value)))
        with gui.add_folder("Files"):
            gui.add_button("save PNG").on_click(self._guard(self._save_png))
            gui.add_button("save emission").on_click(self._guard(self._save_emission))
            self._upload_button = None
            if self.uploads is not None:
                self._upload_button = gui.add_upload_button("load emission", mime_type="application/json")
                self._upload_button.on_upload(self._guard(self._load_upload))
        if self.warnings:
            gui.add_markdown("  \n".join(f"warning: {w}" for w in self.warnings))

    def _build_lights(self) -> None:
        gui = self.server.gui
        with self._lock:
            emitters = list(self.state.emitters)
            for h in self._light_handles:
                h.remove()
            self._light_handles = []
            with self._lights_folder:
                for e in emitters:
                    folder = gui.add_folder(e.name)
                    with folder:
                        on = gui.add_checkbox("on", initial_value=e.on)
                        top = max(4 * e.intensity, DEFAULT_INTENSITY)
                        step = 10.0 ** math.floor(math.log10(top / 100))
                        intensity = gui.add_slider("intensity W/m2", min=0.0, max=top, step=step,
                                                   initial_value=e.intensity)
                        color = gui.add_rgb("colour", initial_value=tuple(int(round(255 * c)) for c in e.color))
                    on.on_update(self._guard(lambda ev, n=e.name, h=on: self.set_emitter(n, on=bool(h.value))))
                    intensity.on_update(self._guard(
                        lambda ev, n=e.name, h=intensity: self.set_emitter(n, intensity=float(h.value))))
                    color.on_update(self._guard(
                        lambda ev, n=e.name, h=color: self.set_emitter(n, color=tuple(c / 255 for c in h.value))))
                    self._light_handles.append(folder)

    def _index(self, name: str) -> int:
        for i, e in enumerate(self.state.emitters):
            if e.name == name:
                return i
        raise InputError(f"no emitter named '{name}'; the emitters are "
                         f"{', '.join(repr(e.name) for e in self.state.emitters) or 'none'}")

    # -- files -----------------------------------------------------------------------
    def new_file_name(self, prefix: str, suffix: str) -> Path:
        """A file in ``save_dir`` named ``prefix-YYYYmmdd-HHMMSS[-N]suffix`` that no other save uses.

        The name is reserved by creating the file exclusively (``O_EXCL``), so two
        saves in one second, from two tabs or two viewers sharing the folder,
        get distinct names; the writer then replaces the empty file atomically.
        """
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        with self._names_lock:
            for i in range(1, 10_000):
                path = self.save_dir / f"{prefix}-{stamp}{'' if i == 1 else f'-{i}'}{suffix}"
                try:
                    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
                except FileExistsError:
                    continue
                return path
        raise InputError(f"{self.save_dir}: 10,000 files named {prefix}-{stamp}-N{suffix} already; clean up")

    def save_png(self, camera: Camera, path: "str | Path", *, height: int = PNG_HEIGHT,
                 aspect: float = 4 / 3) -> Path:
        """Render what the page shows through ``hfrad render``'s renderer, from ``camera``.

        Parameters
        ----------
        camera : Camera
        path : path of the PNG
        height : int, pixels, at most ``MAX_PICTURE_SIDE``
        aspect : float
            Width / height; the width ``round(height * aspect)`` is at most ``MAX_PICTURE_SIDE``.

        Raises
        ------
        InputError
            A side outside [1, MAX_PICTURE_SIDE] or a non-finite aspect.
        MemoryLimitError
            The render would not fit in the memory available.
        """
        from ..render import render_image, save_png

        if isinstance(height, bool) or not isinstance(height, (int, np.integer)) or \
                not 1 <= height <= MAX_PICTURE_SIDE:
            raise InputError(f"picture height must be a whole number in [1, {MAX_PICTURE_SIDE}] pixels, "
                             f"got {height!r}")
        aspect = float(aspect)
        width = round(height * aspect) if math.isfinite(aspect) and aspect > 0 else 0
        if not 1 <= width <= MAX_PICTURE_SIDE:
            raise InputError(f"picture width must be in [1, {MAX_PICTURE_SIDE}] pixels, got height {height} x aspect "
                             f"{aspect:.4g} = {height * aspect:.6g}; make the browser window less wide")
        memory.require(BYTES_PER_PIXEL * width * height, f"a {width} x {height} picture")
        with self._lock:
            B, E, exposure, falsecolor, unit = self._shown
        image = render_image(self.scene.replace(emission=E), B, camera=camera, width=width, height=int(height),
                             exposure=exposure, falsecolor=falsecolor, unit=unit)
        return save_png(image, path)

    def _client_camera(self, client) -> tuple[Camera, float]:
        """The tab's camera and aspect ratio, as the browser reports them (checked: it may report anything)."""
        cam = client.camera
        up = cam.up_direction if cam.up_direction is not None else (0.0, 1.0, 0.0)
        w, h = cam.image_width, cam.image_height
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 0 < v <= 1 << 20 for v in (w, h)):
            raise InputError(f"the browser reported a view of {w!r} x {h!r} pixels; reload the page")
        camera = Camera(tuple(map(float, cam.position)), tuple(map(float, cam.look_at)),
                        tuple(map(float, up)), math.degrees(float(cam.fov)))
        return camera, w / h

    def _save_png(self, event) -> None:
        client = event.client
        camera, aspect = self._client_camera(client)
        path = self.new_file_name("hfrad-view", ".png")
        try:
            self.save_png(camera, path, aspect=aspect)
        except BaseException:
            path.unlink(missing_ok=True)           # the reserved, still empty name
            raise
        client.send_file_download(path.name, path.read_bytes(), save_immediately=True)
        self._notify(client, "Saved picture", str(path.resolve()))

    def _save_emission(self, event) -> None:
        with self._lock:
            settings = [e.setting() for e in self.state.emitters]
        path = self.new_file_name("hfrad-emission", ".json")
        try:
            write_emission(path, settings)
        except BaseException:
            path.unlink(missing_ok=True)
            raise
        event.client.send_file_download(path.name, path.read_bytes(), save_immediately=True)
        self._notify(event.client, "Saved emission", f"{path.resolve()} (use with --emission-file)")

    def _load_upload(self, event) -> None:
        upload = event.target.value
        name = str(upload.name)[:200]
        if len(upload.content) > MAX_UPLOAD_BYTES:     # UploadLimit refuses these before they arrive
            raise InputError(f"{name}: {len(upload.content):,} bytes; an emission file is at most "
                             f"{MAX_UPLOAD_BYTES:,}")
        self.load_emission(upload.content.decode("utf-8", errors="replace"), name)
        self._notify(event.client, "Loaded emission", name)
