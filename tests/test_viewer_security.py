"""`hfrad view` answers only its own page: Host, Origin and token checks in the real server on 127.0.0.1,
an unbindable --host refused at once, uploads and pictures capped, saved names that never collide."""

from __future__ import annotations

import contextlib
import http.server
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
import uuid

import pytest
from typer.testing import CliRunner

import hfrad
from hfrad.cli import app as cli_app
from hfrad.errors import InputError, MemoryLimitError

viser = pytest.importorskip("viser", reason="hfrad view needs viser (pip install viser)")
from websockets.exceptions import InvalidStatus  # noqa: E402  (websockets comes with viser)
from websockets.sync.client import connect  # noqa: E402

from hfrad.viewer.guard import (  # noqa: E402
    PageGuard, _same_origin, _split_hostport, check_bindable, guarded_server, self_test)

#: An address of RFC 5737's documentation range: never one of this machine's.
FOREIGN_ADDRESS = "203.0.113.7"
PROTO = [f"viser-v{viser.__version__}"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def fac():
    return hfrad.factorize(hfrad.load_scene("cornell", patches=300), eps=0.05)


@pytest.fixture(scope="module")
def app(fac, tmp_path_factory):
    from hfrad.viewer import ViewerApp

    app = ViewerApp(fac, port=free_port(), save_dir=tmp_path_factory.mktemp("saves"))
    yield app
    app.close()


def get(url: str, **headers) -> tuple[int, dict, bytes]:
    """(status, headers, body) of a GET with exactly these extra headers."""
    req = urllib.request.Request(url, headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def ws_status(url: str, **kwargs) -> int:
    """101 if the websocket handshake succeeds (and the first message arrives), else the HTTP status."""
    try:
        ws = connect(url, subprotocols=PROTO, open_timeout=10, **kwargs)
    except InvalidStatus as exc:
        return exc.response.status_code
    try:
        assert len(ws.recv(timeout=10)) > 0     # the scene starts to arrive
    finally:
        ws.close()
    return 101


def test_page_needs_token_and_own_host(app):
    base = f"http://127.0.0.1:{app.port}/"
    assert re.fullmatch(rf"http://127\.0\.0\.1:{app.port}/\?token=[A-Za-z0-9_-]{{32}}", app.url)
    token = app.guard.token
    for url, headers in ((base, {}), (base + "?token=wrong", {}), (base + "?token=" + token[:-1], {}),
                         (base, {"Cookie": f"hfrad-view-token-{app.port}=wrong"}),
                         (base, {"Cookie": f"hfrad-view-token-{app.port + 1}={token}"}),  # another viewer's
                         (app.url, {"Host": f"evil.example:{app.port}"}),                # DNS rebinding
                         (app.url, {"Host": f"127.0.0.1.evil.example:{app.port}"}),
                         (app.url, {"Host": f"127.0.0.1:{app.port + 1}"}),
                         (app.url, {"Host": "127.0.0.1"}),
                         (app.url, {"Origin": "http://evil.example"})):
        status, _, body = get(url, **headers)
        assert status == 403, (url, headers)
        assert b"refused" in body and len(body) < 300          # no page in a refusal
    status, headers, body = get(app.url)
    assert status == 200 and len(body) > 10_000
    cookie = headers["Set-Cookie"]
    assert cookie.startswith(f"hfrad-view-token-{app.port}={token};")
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    assert headers["Referrer-Policy"] == "no-referrer"
    assert "frame-ancestors 'none'" in headers["Content-Security-Policy"]
    # the cookie set by the page, the Authorization header, and the other names of this machine
    assert get(base, Cookie=f"other=1; hfrad-view-token-{app.port}={token}")[0] == 200
    assert get(base, Authorization=f"token {token}")[0] == 200
    assert get(app.url, Host=f"localhost:{app.port}")[0] == 200
    assert get(app.url, Host=f"LOCALHOST:{app.port}", Origin=f"http://localhost:{app.port}")[0] == 200
    assert app.guard.refused >= 10


def test_websocket_refuses_foreign_origin_and_missing_token(app):
    own = f"http://127.0.0.1:{app.port}"
    ws_url = app.url.replace("http://", "ws://")
    bare = f"ws://127.0.0.1:{app.port}/"
    assert ws_status(ws_url, origin="http://evil.example") == 403                   # another site's page
    assert ws_status(ws_url, origin=f"http://evil.example:{app.port}") == 403
    assert ws_status(ws_url, origin="null") == 403                                  # sandboxed frame, file://
    assert ws_status(ws_url, origin=f"http://127.0.0.1:{app.port + 1}") == 403
    assert ws_status(bare, origin=own) == 403                                       # no token
    assert ws_status(bare + "?token=" + "x" * 32, origin=own) == 403                # wrong token
    assert ws_status(ws_url, origin=own, additional_headers={"Host": f"evil.example:{app.port}"}) == 403
    # DNS rebinding: the page on evil.example resolved to 127.0.0.1, with the token stolen or not
    assert ws_status(ws_url, origin=f"http://evil.example:{app.port}",
                     additional_headers={"Host": f"evil.example:{app.port}"}) == 403
    # the page's own websocket: same origin, token in the query or in the cookie the page set
    assert ws_status(ws_url, origin=own) == 101
    assert ws_status(bare, origin=own,
                     additional_headers={"Cookie": f"hfrad-view-token-{app.port}={app.guard.token}"}) == 101
    assert ws_status(ws_url) == 101                                     # a script (no Origin) with the token


def test_host_and_origin_rules():
    """The header rules on their own, including IPv6 and a server bound to every interface."""
    guard = PageGuard("127.0.0.1", token="t" * 32)
    assert _split_hostport("[::1]:8080") == ("::1", 8080) and _split_hostport("a:b") == (None, None)
    assert _split_hostport("Example.COM.:80") == ("example.com", 80) and _split_hostport("[::1") == (None, None)
    for host, ok in (("127.0.0.1:8080", True), ("localhost:8080", True), ("[::1]:8080", True),
                     ("app.localhost:8080", True), ("127.0.0.2:8080", True), ("127.0.0.1", False),
                     ("127.0.0.1:80", False), ("192.168.1.5:8080", False), ("evil.example:8080", False),
                     ("localhost.evil.example:8080", False), ("", False), ("x" * 400, False),
                     ("127.0.0.1:8080:1", False), ("127.0.0.1:99999", False)):
        assert guard.host_allowed(host, 8080) is ok, host
    wide = PageGuard("0.0.0.0", token="t" * 32)              # the network may reach it by address
    assert wide.host_allowed("192.168.1.5:8080", 8080) and not wide.host_allowed("evil.example:8080", 8080)
    lan = PageGuard("192.168.1.5", token="t" * 32)
    assert lan.host_allowed("192.168.1.5:8080", 8080) and not lan.host_allowed("192.168.1.6:8080", 8080)
    for origin, ok in (("http://127.0.0.1:8080", True), ("http://127.0.0.1:8080/", True),
                       ("null", False), ("http://127.0.0.1:8081", False), ("http://127.0.0.1", False),
                       ("file://", False), ("ws://127.0.0.1:8080", False), ("http://u@127.0.0.1:8080", False),
                       ("http://localhost:8080", False)):
        assert _same_origin(origin, "127.0.0.1:8080") is ok, origin
    with pytest.raises(InputError, match="16 characters of randomness; got 5"):
        PageGuard("127.0.0.1", token="short")


def test_fails_closed_without_the_checks():
    """No server started through the checks, or a server that serves without the token: refused."""
    with pytest.raises(RuntimeError, match="without hfrad's checks"):
        with guarded_server(PageGuard("127.0.0.1")):
            pass                                  # (a viser that starts its server some other way)

    class Open(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            self.end_headers()

        def log_message(self, *args):
            pass

    server = http.server.HTTPServer(("127.0.0.1", 0), Open)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with pytest.raises(RuntimeError, match="not 403"):
            self_test("127.0.0.1", server.server_address[1])
    finally:
        server.shutdown()
        server.server_close()


def test_unbindable_host_fails_at_once(fac, tmp_path):
    """Before: viser tried 1000 ports on an address it cannot bind, then `hfrad view` hung for ever."""
    from hfrad.viewer import ViewerApp

    for host, why in ((FOREIGN_ADDRESS, "cannot listen on 203.0.113.7"), ("no-such-host.invalid", "cannot resolve")):
        t0 = time.perf_counter()
        with pytest.raises(InputError, match=why):
            ViewerApp(fac, host=host, port=free_port(), save_dir=tmp_path)
        assert time.perf_counter() - t0 < 5
        result = CliRunner().invoke(cli_app, ["view", str(tmp_path / "any.hfr"), "--host", host])
        assert result.exit_code == 2, result.output
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: --host ") and why in lines[0]
    # a busy port: the next free one; the last port busy: refused (viser's own search died on port 65536)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert port < check_bindable("127.0.0.1", port) <= port + 100
    with socket.socket() as last:
        with contextlib.suppress(OSError):          # (if another program holds it, it is busy all the same)
            last.bind(("127.0.0.1", 65535))
            last.listen()
        with pytest.raises(InputError, match="--port 65535: ports 65535-65535 on 127.0.0.1 are all in use"):
            check_bindable("127.0.0.1", 65535)
        result = CliRunner().invoke(cli_app, ["view", str(tmp_path / "any.hfr"), "--port", "65535"])
        assert result.exit_code == 2 and "are all in use" in result.output, result.output
    for host in ("", "   "):
        with pytest.raises(InputError, match="got an empty value"):
            check_bindable(host, 8080)


def test_cli_prints_token_url_and_warns_off_loopback(fac, tmp_path):
    """`hfrad view --host 0.0.0.0`: a warning, then the URL with its token, which opens the page."""
    hfr = tmp_path / "c.hfr"
    hfrad.save(fac, hfr)
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "hfrad", "view", str(hfr), "--host", "0.0.0.0",
                             "--port", str(port), "--save-dir", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("hfrad view: http"):
                break
        text = "".join(lines)
        url = re.search(r"hfrad view: (http://\S+)", text)
        assert url, text
        url = url.group(1)
        # (the port asked for, or the next free one if another program took it meanwhile)
        assert re.fullmatch(r"http://127\.0\.0\.1:\d+/\?token=[A-Za-z0-9_-]{32}", url), url
        port = int(url.split(":")[2].split("/")[0])
        assert "warning: --host 0.0.0.0 is not a loopback address" in text
        assert "(viser)" not in text and "│" not in text      # no banner with a token-less address
        assert get(url)[0] == 200
        assert get(f"http://127.0.0.1:{port}/")[0] == 403
    finally:
        proc.terminate()
        proc.wait(30)
        proc.stdout.close()


class FakeClient:
    """What the page's callbacks use of a viser client (downloads and notifications recorded)."""

    def __init__(self, width: int = 1200, height: int = 800) -> None:
        self.downloads: list[str] = []
        self.notes: list[tuple[str, str]] = []
        cam = dict(position=(0.28, 0.27, -0.8), look_at=(0.28, 0.27, 0.28), up_direction=(0.0, 1.0, 0.0),
                   fov=0.8, image_width=width, image_height=height,
                   aspect=property(lambda c: float(c.image_width) / c.image_height))   # as viser's
        self.camera = type("Cam", (), cam)()

    def send_file_download(self, name, content, save_immediately=False):
        self.downloads.append(name)

    def add_notification(self, title, body, **kwargs):
        self.notes.append((title, body))


def test_saved_names_never_collide(app):
    event = type("Event", (), {"client": FakeClient(480, 360)})()
    for _ in range(3):                                    # three in one second (usually): three names
        app._save_emission(event)
    app._save_png(event)
    app._save_png(event)
    names = event.client.downloads
    assert len(set(names)) == 5, names
    for name in names:
        path = app.save_dir / name
        assert path.stat().st_size > 0                   # the reserved name was filled, not left empty
    assert all(json.loads((app.save_dir / n).read_text())["format"] == "hfrad-emission" for n in names[:3])
    # a name taken by someone else (another viewer sharing the folder) is skipped, never overwritten
    first = app.new_file_name("x", ".png")
    taken = [first] + [app.new_file_name("x", ".png") for _ in range(3)]
    assert len({p.name for p in taken}) == 4 and all(p.exists() for p in taken)
    # a picture that cannot be rendered leaves no empty file behind
    bad = type("Event", (), {"client": FakeClient(100_000, 1)})()
    before = set(os.listdir(app.save_dir))
    with pytest.raises(InputError, match="picture width"):
        app._save_png(bad)
    assert set(os.listdir(app.save_dir)) == before


def test_picture_size_capped(app, monkeypatch):
    from hfrad.render.camera import Camera

    camera = Camera.auto(app.scene.bounds)
    for kwargs, match in ((dict(aspect=1000.0), "picture width"), (dict(aspect=float("nan")), "picture width"),
                          (dict(aspect=-1.0), "picture width"), (dict(height=100_000), "picture height"),
                          (dict(height=0), "picture height"), (dict(height=2.5), "picture height")):
        with pytest.raises(InputError, match=match):
            app.save_png(camera, app.save_dir / "never.png", **kwargs)
    for w, h in ((0, 100), (100, 0), (-5, 10), (10**9, 10), (True, 1)):
        with pytest.raises(InputError, match="the browser reported a view"):
            app._client_camera(FakeClient(w, h))
    import hfrad.memory
    monkeypatch.setattr(hfrad.memory, "available_bytes", lambda: 100 << 20)   # 100 MB free
    with pytest.raises(MemoryLimitError, match="a 8192 x 6144 picture"):
        app.save_png(camera, app.save_dir / "never.png", height=6144)
    assert not (app.save_dir / "never.png").exists()


def _upload_messages(button_uuid: str, content: bytes, *, declared: int | None = None, parts: int = 1,
                     filename: str = "e.json") -> list[bytes]:
    import msgspec

    from viser import _messages as msgs

    tid = str(uuid.uuid4())
    start = msgs.FileTransferStartUpload(button_uuid, tid, filename, "application/json", parts,
                                         len(content) if declared is None else declared)
    step = -(-len(content) // parts)
    out = [start] + [msgs.FileTransferPart(button_uuid, tid, i, content[i * step:(i + 1) * step])
                     for i in range(parts)]
    return [msgspec.msgpack.encode(m.as_serializable_dict()) for m in out]


def _camera_message() -> bytes:
    """The first message a tab sends (viser counts a client as connected from it)."""
    import msgspec

    from viser import _messages as msgs

    m = msgs.ViewerCameraMessage((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -1.0), 0.8, 0.01, 100.0, 600, 800,
                                 (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    return msgspec.msgpack.encode(m.as_serializable_dict())


def _plain(frame: bytes) -> bytes:
    """A server message's bytes, zstd-decompressed where viser compressed them (after a 16-byte header)."""
    import zstandard

    at = frame.find(b"\x28\xb5\x2f\xfd")                  # zstd's magic number
    if at < 0:
        return frame
    return zstandard.ZstdDecompressor().decompressobj().decompress(frame[at:])


def _wait(cond, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return False


def test_uploads_capped_as_they_arrive(app):
    from viser import _messages as msgs

    from hfrad.viewer.app import MAX_UPLOAD_BYTES

    assert msgs.ShareUrlRequest not in app.server._websock_server._incoming_handlers   # no public tunnel
    button = app._upload_button._impl.uuid
    pending = app.server.gui._current_file_upload_states
    refused = app.uploads.refused
    light = lambda: [e for e in app.state.emitters if e.name == "light"][0]        # noqa: E731
    good = json.dumps({"format": "hfrad-emission", "version": 1,
                       "emitters": [{"name": "light", "exitance": [5.0, 5.0, 5.0]}]}).encode()
    with connect(app.url.replace("http://", "ws://"), subprotocols=PROTO, open_timeout=10, max_size=None) as ws:
        ws.send(_camera_message())
        assert _wait(lambda: len(app.server.get_clients()) == 1)
        # declared too large: refused at the start, nothing buffered
        for m in _upload_messages(button, b"{}", declared=MAX_UPLOAD_BYTES + 1)[:1]:
            ws.send(m)
        assert _wait(lambda: app.uploads.refused == refused + 1)
        end = time.monotonic() + 10                           # the tab is told why
        while b"more than the 1,048,576 accepted" not in _plain(ws.recv(timeout=max(0.1, end - time.monotonic()))):
            pass
        # more parts than bytes, and parts past the declared size: refused
        ws.send(_upload_messages(button, b"{}", parts=3)[0])
        assert _wait(lambda: app.uploads.refused == refused + 2)
        big = b" " * 5000 + good
        for m in _upload_messages(button, big, declared=100, parts=2):
            ws.send(m)
        assert _wait(lambda: app.uploads.refused == refused + 3)
        assert sum(len(p) for s in list(pending.values()) for p in list(s["parts"].values())) <= 100
        assert light().intensity != 5.0                       # none of these was loaded
        # a real emission file, in three parts: loaded
        for m in _upload_messages(button, good, parts=3):
            ws.send(m)
        assert _wait(lambda: light().intensity == 5.0), app.state.emitters
        end = time.monotonic() + 10
        while b"Loaded emission" not in _plain(ws.recv(timeout=max(0.1, end - time.monotonic()))):
            pass
    assert app.uploads.refused == refused + 3
    assert _wait(lambda: not pending)                      # the tab's unfinished upload dropped on disconnect


def test_controls_refuse_values_out_of_range(app):
    """viser passes on whatever value a tab sends for a slider or dropdown: the page's callbacks check them."""
    import msgspec

    from viser import _messages as msgs

    handles = {h.label: h for h in app.server.gui._gui_input_handle_from_uuid.values()}
    before = (app.state.exposure, app.state.unit, list(app.state.emitters))
    with connect(app.url.replace("http://", "ws://"), subprotocols=PROTO, open_timeout=10, max_size=None) as ws:
        ws.send(_camera_message())
        assert _wait(lambda: len(app.server.get_clients()) >= 1)
        for label, value in (("exposure (EV)", float("nan")), ("exposure (EV)", 1e308), ("unit", "furlongs"),
                             ("intensity W/m2", float("inf")), ("intensity W/m2", 1e300),
                             ("colour", (300, -5, 2))):
            ws.send(msgspec.msgpack.encode(msgs.GuiUpdateMessage(handles[label]._impl.uuid,
                                                                 {"value": value}).as_serializable_dict()))
            assert _wait(lambda: repr(handles[label].value) == repr(value))     # (nan != nan)
            time.sleep(0.3)                    # the callback runs on viser's thread pool after the value is set
        assert app.wait_idle(10)
    assert (app.state.exposure, app.state.unit, list(app.state.emitters)) == before
    assert "failed" not in app._readout.content
    with pytest.raises(InputError, match=r"intensity must be a number in \[0, 1e\+12\]"):
        app.set_emitter("light", intensity=1e13)


def test_upload_limit_counts_uploads_in_flight():
    """At most `max_in_flight` unfinished uploads; one that overflowed counts until its tab disconnects."""
    from viser import _messages as msgs

    from hfrad.viewer.guard import UploadLimit

    seen, told = [], []

    class Server:                                     # viser's WebsockServer, as far as UploadLimit uses it
        def __init__(self):
            self._incoming_handlers = {msgs.FileTransferStartUpload: [lambda c, m: seen.append(("start", c))],
                                       msgs.FileTransferPart: [lambda c, m: seen.append(("part", c))]}
            self.disconnect = []

        def on_client_disconnect(self, cb):
            self.disconnect.append(cb)

    server = Server()
    limit = UploadLimit(1000, max_in_flight=2, on_refused=lambda c, text: told.append((c, text)))
    limit.install(server)
    start, part = (server._incoming_handlers[k][0] for k in (msgs.FileTransferStartUpload, msgs.FileTransferPart))

    def begin(client, tid, size=10, parts=2):
        start(client, msgs.FileTransferStartUpload("b", tid, "f.json", "application/json", parts, size))

    begin(1, "a")
    begin(1, "b")
    begin(2, "c")                                     # a third at once: refused
    assert seen == [("start", 1), ("start", 1)] and told[-1][0] == 2 and "2 uploads already" in told[-1][1]
    part(1, msgs.FileTransferPart("b", "a", 0, b"12345"))
    part(1, msgs.FileTransferPart("b", "a", 1, b"12345"))                       # "a" complete: a slot frees
    part(1, msgs.FileTransferPart("b", "b", 0, b"x" * 11))                      # "b" overflows: poisoned
    part(1, msgs.FileTransferPart("b", "b", 1, b"y"))                           # and stays dropped
    part(2, msgs.FileTransferPart("b", "a", 0, b"z"))                           # another tab's part: dropped
    assert seen[2:] == [("part", 1), ("part", 1)] and "exceed the 10 bytes declared" in told[-1][1]
    begin(2, "d")
    begin(2, "e")                                     # "b" (poisoned) and "d" in flight: refused
    assert seen[-1] == ("start", 2) and len(seen) == 5 and "already in progress" in told[-1][1]
    server.disconnect[0](type("Conn", (), {"client_id": 1})())                # tab 1 leaves: "b" forgotten
    begin(2, "e")
    assert seen[-1] == ("start", 2) and len(seen) == 6
    assert limit.refused == 3
