"""Who may load the ``hfrad view`` page and open its websocket.

A local web server is reachable by every web page the user's browser opens: a
page on ``http://evil.example`` may open ``ws://127.0.0.1:8080`` (browsers
allow cross-origin websockets and only report the ``Origin``), and with DNS
rebinding a foreign name may even resolve to 127.0.0.1 (the browser then sends
``Host: evil.example:8080``). So, as Jupyter does, every request to the server
must pass three checks (:meth:`PageGuard.refusal`):

1. ``Host`` names this machine with the server's port: ``localhost`` (and
   ``*.localhost``), a loopback address, the bound address; when reachable
   from the network also this machine's own name, and, when bound to every
   interface (0.0.0.0 or ::), any IP literal; a rebinding attack always uses
   a foreign domain name, which these exclude;
2. ``Origin``, when present (browsers always send it on websockets), is the
   same origin as ``Host``: scheme http(s), same host and port;
3. the request carries the per-run token (:func:`secrets.token_urlsafe`,
   printed in the URL ``http://127.0.0.1:8080/?token=...``): as the query
   parameter ``token``, the header ``Authorization: token ...``, or the cookie
   set when the page was loaded with it (viser's client opens its websocket on
   the page's address without the query, so the cookie carries the token there;
   it is ``HttpOnly`` and ``SameSite=Strict``, so no other site's page sends it).

How the checks reach viser. viser (1.x) has no hook for its HTTP or websocket
handshake: ``viser.infra._infra`` calls ``websockets.asyncio.server.serve``
itself, with its own ``process_request`` (the page server). Three ways were
weighed:

- a token-checking proxy in front, viser bound to another loopback port: not
  robust, since the inner port stays open to every page in the browser (a
  page can scan loopback ports with websockets) and carries no checks;
- finding the ``websockets`` server object after start and swapping its
  ``process_request``: relies on an undocumented attribute, and leaves a window
  between listening and swapping in which requests pass unchecked;
- **chosen**: :func:`guarded_server` gives viser's module a view of the
  ``websockets`` package in which ``serve`` wraps ``process_request`` with the
  checks before the socket listens (no window). It touches only viser's own
  module (not the ``websockets`` package, nor other users of it), edits no file,
  and fails closed: if viser did not start its server through it (a viser
  version that starts it differently), or a request without the token is not
  refused (:func:`self_test`), the viewer refuses to start.
"""

from __future__ import annotations

import contextlib
import errno
import http
import inspect
import ipaddress
import logging
import secrets
import socket
import threading
import types
from http.cookies import CookieError, SimpleCookie
from typing import Any, Callable, Iterator
from urllib.parse import parse_qs, urlsplit

from ..errors import InputError

log = logging.getLogger(__name__)

#: Names that always mean this machine (RFC 6761: ``localhost`` and ``*.localhost``).
LOCAL_NAMES = ("localhost",)
#: Hosts that bind every interface.
WILDCARD_HOSTS = ("0.0.0.0", "::")
#: Header of the request :func:`self_test` sends (it is refused like any other, but not logged).
SELF_TEST_HEADER = "X-Hfrad-Self-Test"
#: Bytes of randomness in the token (as Jupyter: 24).
TOKEN_BYTES = 24


def new_token() -> str:
    """A fresh random token for one run of the server (URL-safe text)."""
    return secrets.token_urlsafe(TOKEN_BYTES)


def _ip(host: str) -> "ipaddress.IPv4Address | ipaddress.IPv6Address | None":
    try:
        return ipaddress.ip_address(host.strip("[]").split("%", 1)[0])
    except ValueError:
        return None


def is_loopback(host: str) -> bool:
    """True if ``host`` is a name or address of this machine only (not reachable from the network)."""
    h = host.strip("[]").lower().rstrip(".")
    if h in LOCAL_NAMES or h.endswith(".localhost"):
        return True
    ip = _ip(h)
    return ip is not None and ip.is_loopback


def url_host(host: str) -> str:
    """``host`` as written in a URL: IPv6 addresses in brackets; 127.0.0.1 for a wildcard bind."""
    if host in WILDCARD_HOSTS:
        return "127.0.0.1" if host != "::" else "[::1]"
    ip = _ip(host)
    return f"[{host.strip('[]')}]" if ip is not None and ip.version == 6 else host


#: Ports tried after a busy one (viser's own search, 1000 ports, never reported its failure).
PORT_SEARCH = 100


def check_bindable(host: str, port: int) -> int:
    """The first port from ``port`` on which the server can listen on ``host``; InputError at once if none.

    viser tries the next port when binding fails, for any reason, up to 1000
    times, then never reports back: an address that is not this machine's, a
    name that does not resolve, or a busy port 65535 made ``hfrad view`` hang.
    Here every address the name resolves to (the server binds all of them) is
    tried, on ``port`` and up to ``PORT_SEARCH`` ports after it if busy
    (``port`` 0: any free port, chosen when the server starts).

    Returns
    -------
    int
        A port free on every address now (0 if ``port`` is 0).
    """
    if not isinstance(host, str) or not host.strip():
        raise InputError("--host must be an address or name of this machine, got an empty value")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError, OverflowError) as exc:
        raise InputError(f"--host {host[:200]}: cannot resolve this name ({exc}); give an address of this "
                         "machine such as 127.0.0.1") from None
    busy = None
    for candidate in ([0] if port == 0 else range(port, min(port + PORT_SEARCH, 65535) + 1)):
        for family, type_, proto, _, addr in infos:
            try:
                with socket.socket(family, type_, proto) as s:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)    # as asyncio's server does
                    if family == socket.AF_INET6:
                        s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                    s.bind((addr[0], candidate) + tuple(addr[2:]))
            except OSError as exc:
                if exc.errno != errno.EADDRINUSE:
                    raise InputError(f"--host {host[:200]}: cannot listen on {addr[0]} ({exc.strerror or exc}); "
                                     "give an address of this machine such as 127.0.0.1") from None
                busy = exc
                break
        else:
            return candidate
    raise InputError(f"--port {port}: ports {port}-{min(port + PORT_SEARCH, 65535)} on {host[:200]} are all in use "
                     f"({busy.strerror if busy else 'busy'}); give another --port")


class PageGuard:
    """The checks on every HTTP request and websocket handshake of one server.

    Parameters
    ----------
    host : str
        The address the server binds.
    token : str, optional
        The per-run secret; a fresh :func:`new_token` by default.

    Attributes
    ----------
    refused : int
        Requests refused so far.
    """

    def __init__(self, host: str, token: str | None = None) -> None:
        self.host = host
        self.token = new_token() if token is None else token
        if len(self.token) < 16:
            raise InputError(f"the page token must be at least 16 characters of randomness; got {len(self.token)}")
        self.refused = 0
        self._names = self._allowed_names(host)

    @staticmethod
    def _allowed_names(host: str) -> set[str]:
        names = {"localhost"}
        if host not in WILDCARD_HOSTS:
            names.add(host.strip("[]").lower().rstrip("."))
        if not is_loopback(host):                 # reachable from the network: also by this machine's name
            with contextlib.suppress(OSError):
                names.update({socket.gethostname().lower(), socket.getfqdn().lower()})
        return names

    def cookie_name(self, port: int) -> str:
        # cookies ignore the port: one name per port keeps two viewers on one machine apart
        return f"hfrad-view-token-{port}"

    # -- checks ---------------------------------------------------------------
    def host_allowed(self, hostport: str, port: int) -> bool:
        """True if a ``Host`` value (``name:port``) names this server."""
        name, got_port = _split_hostport(hostport)
        if name is None or (got_port if got_port is not None else 80) != port:
            return False
        if name in self._names or name.endswith(".localhost"):
            return True
        ip = _ip(name)
        if ip is None:
            return False
        if ip.is_loopback:
            return True
        # bound to every interface: any address literal may reach us (rebinding needs a name)
        return self.host in WILDCARD_HOSTS or ip == _ip(self.host)

    def token_of(self, request) -> str | None:
        """The token a request carries in its query (``?token=``) or ``Authorization: token ...`` header, or None.

        (The cookie the page sets is read by :meth:`refusal` too.)
        """
        query = parse_qs(urlsplit(request.path).query)
        if query.get("token"):
            return query["token"][0]
        auth = request.headers.get("Authorization", "")
        if auth.lower().startswith("token "):
            return auth[6:].strip()
        return None

    def _cookie_token(self, request, port: int) -> str | None:
        for raw in request.headers.get_all("Cookie"):
            try:
                jar = SimpleCookie(raw)
            except CookieError:
                continue
            morsel = jar.get(self.cookie_name(port))
            if morsel is not None:
                return morsel.value
        return None

    def _token_ok(self, given: str | None) -> bool:
        return given is not None and secrets.compare_digest(given.encode("utf-8", "replace"),
                                                            self.token.encode())

    def refusal(self, request, port: int) -> str | None:
        """Why ``request`` to the server on ``port`` is refused, or None if it may pass."""
        hosts = request.headers.get_all("Host")
        if len(hosts) != 1 or not self.host_allowed(hosts[0], port):
            return "Host header does not name this server"
        origins = request.headers.get_all("Origin")
        if len(origins) > 1:
            return "more than one Origin header"
        if origins and not _same_origin(origins[0], hosts[0]):
            return "foreign Origin"
        if not (self._token_ok(self.token_of(request)) or self._token_ok(self._cookie_token(request, port))):
            return "no valid token"
        return None

    # -- the process_request wrapper -------------------------------------------
    def wrap(self, inner: Callable | None) -> Callable:
        """``process_request`` for websockets' ``serve``: the checks, then ``inner`` (viser's page server)."""

        async def process_request(connection, request):
            port = connection.local_address[1]
            reason = self.refusal(request, port)
            if reason is not None:
                if SELF_TEST_HEADER not in request.headers:
                    self.refused += 1
                    peer = connection.remote_address[0] if connection.remote_address else "?"
                    log.warning("hfrad view refused a request from %s (%s)", peer, reason)
                return connection.respond(
                    http.HTTPStatus.FORBIDDEN,
                    f"hfrad view: refused ({reason}). Open the address `hfrad view` printed, "
                    "with its ?token=...\n")
            response = None if inner is None else inner(connection, request)
            if inspect.isawaitable(response):
                response = await response
            if response is not None:
                self._decorate(response, request, port)
            return response

        return process_request

    def _decorate(self, response, request, port: int) -> None:
        h = response.headers
        if self._token_ok(self.token_of(request)):
            h["Set-Cookie"] = (f"{self.cookie_name(port)}={self.token}; Path=/; HttpOnly; SameSite=Strict")
        h["X-Content-Type-Options"] = "nosniff"
        h["Referrer-Policy"] = "no-referrer"                 # the token is in the page's URL
        h["Content-Security-Policy"] = "frame-ancestors 'none'"
        h["X-Frame-Options"] = "DENY"
        h["Cache-Control"] = "no-store"


def _split_hostport(value: str) -> tuple[str | None, int | None]:
    """('name', port) of a Host value; (None, None) if malformed. IPv6 in brackets."""
    value = value.strip().lower()
    if not value or len(value) > 300:
        return None, None
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            return None, None
        name, rest = value[1:end], value[end + 1:]
        if rest and not rest.startswith(":"):
            return None, None
        port = rest[1:] if rest else None
    else:
        name, sep, port = value.partition(":")
        if not sep:
            port = None
    if port is not None:
        if not port.isdigit() or not 0 < int(port) < 65536:
            return None, None
        port = int(port)
    return name.rstrip("."), port


def _same_origin(origin: str, hostport: str) -> bool:
    try:
        parts = urlsplit(origin.strip())
        default = {"http": 80, "https": 443}[parts.scheme.lower()]
        o_port = parts.port
    except (KeyError, ValueError):
        return False                                     # "null", "file://", junk
    if parts.path not in ("", "/") or parts.query or parts.username or not parts.hostname:
        return False
    h_name, h_port = _split_hostport(hostport)
    return (parts.hostname.lower().rstrip("."), o_port or default) == (h_name, h_port or 80)


# -- installing the checks into viser --------------------------------------------------------------------
_install_lock = threading.Lock()
_pending: PageGuard | None = None
_served: list[PageGuard] = []


def _viser_infra() -> types.ModuleType:
    from viser.infra import _infra   # where viser 1.x starts its server (see the module docstring)
    return _infra


class _View(types.ModuleType):
    """A module that shows ``real``'s attributes, with some replaced."""

    def __init__(self, real: types.ModuleType, **overrides: Any) -> None:
        super().__init__(real.__name__, getattr(real, "__doc__", None))
        self.__dict__.update(overrides)
        self._hfrad_real = real

    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["_hfrad_real"], name)


def _guarded_serve(real_serve: Callable) -> Callable:
    def serve(*args, **kwargs):
        guard = _pending
        if guard is not None:
            kwargs["process_request"] = guard.wrap(kwargs.get("process_request"))
            _served.append(guard)
        return real_serve(*args, **kwargs)

    serve._hfrad_guarded = True
    return serve


def _install() -> None:
    infra = _viser_infra()
    ws = getattr(infra, "websockets", None)
    if isinstance(ws, _View):
        return
    if ws is None:
        raise RuntimeError("viser starts its server in a way hfrad view does not know "
                           f"(viser {_viser_version()}); refusing to serve an unguarded page")
    import websockets.asyncio.server as ws_server

    server_view = _View(ws_server, serve=_guarded_serve(ws_server.serve))
    asyncio_view = _View(ws.asyncio, server=server_view)
    infra.websockets = _View(ws, asyncio=asyncio_view)


def _viser_version() -> str:
    try:
        import viser
        return viser.__version__
    except Exception:   # pragma: no cover
        return "?"


@contextlib.contextmanager
def guarded_server(guard: PageGuard) -> Iterator[None]:
    """Within this block, a viser server that starts is guarded by ``guard``; fails closed.

    Raises
    ------
    RuntimeError
        If no server was started through the guard inside the block.
    """
    global _pending
    with _install_lock:
        _install()
        _pending, count = guard, len(_served)
        try:
            yield
        finally:
            _pending = None
        if not any(g is guard for g in _served[count:]):
            raise RuntimeError("viser started its server without hfrad's checks "
                               f"(viser {_viser_version()} changed how it serves); refusing to serve "
                               "an unguarded page")
        del _served[:]


def self_test(host: str, port: int, timeout: float = 5.0) -> None:
    """Fail closed: a request without the token must be refused (403) by the running server."""
    connect = url_host(host).strip("[]")
    with socket.create_connection((connect, port), timeout=timeout) as s:
        hostport = f"{url_host(host)}:{port}"
        s.sendall(f"GET / HTTP/1.1\r\nHost: {hostport}\r\n{SELF_TEST_HEADER}: 1\r\n"
                  "Connection: close\r\n\r\n".encode())
        status = s.recv(64).split(b"\r\n", 1)[0]
    if b" 403 " not in status + b" ":
        raise RuntimeError(f"hfrad view's server answered a request without its token with {status!r}, "
                           "not 403; refusing to serve an unguarded page")


class UploadLimit:
    """Caps the files a page uploads, while the parts arrive (before viser buffers them).

    viser buffers every part of an upload in memory until the last arrives and
    checks the declared size only then; a client may declare any number of
    parts. This wraps viser's handlers of the upload messages so that a
    transfer is refused at its start if it declares more than ``limit`` bytes
    (or more parts than bytes, or too many at once), and a part is dropped if
    it would take its transfer past the declared size.

    Parameters
    ----------
    limit : int, bytes
    max_in_flight : int
        Uploads in progress at once (a refused or overflowing one counts until
        its tab disconnects, since viser keeps its parts until then).
    on_refused : callable(client_id, text), optional
        Told of each refusal (to notify the tab).
    """

    def __init__(self, limit: int, *, max_in_flight: int = 4,
                 on_refused: Callable[[int, str], None] | None = None) -> None:
        self.limit, self.max_in_flight, self.on_refused = int(limit), int(max_in_flight), on_refused
        self.refused = 0
        self._lock = threading.Lock()
        self._transfers: dict[str, dict] = {}

    def install(self, ws_server) -> None:
        """Wrap ``ws_server``'s (viser's ``WebsockServer``) upload handlers.

        Raises
        ------
        RuntimeError
            If viser has no handlers for these messages (a version that uploads differently).
        """
        from viser import _messages as msgs

        handlers = getattr(ws_server, "_incoming_handlers", {})
        for cls, check in ((msgs.FileTransferStartUpload, self._start), (msgs.FileTransferPart, self._part)):
            if not handlers.get(cls):
                raise RuntimeError(f"viser {_viser_version()} handles uploads differently; cannot cap them")
            handlers[cls][:] = [_gated(cb, check) for cb in handlers[cls]]
        ws_server.on_client_disconnect(lambda conn: self._forget(conn.client_id))

    def _refuse(self, client_id: int, text: str) -> bool:
        self.refused += 1
        log.warning("hfrad view: %s", text)
        if self.on_refused is not None:
            try:
                self.on_refused(client_id, text)
            except Exception:  # the tab may have gone
                pass
        return False

    def _start(self, client_id: int, m) -> bool:
        size, parts = m.size_bytes, m.part_count
        if not (isinstance(size, int) and isinstance(parts, int)) or size < 0 or parts < 0 \
                or parts > max(size, 1) or (size > 0) != (parts > 0):
            return self._refuse(client_id, f"upload '{str(m.filename)[:100]}' refused: inconsistent size "
                                           f"({size!r} bytes in {parts!r} parts)")
        if size > self.limit:
            return self._refuse(client_id, f"upload '{str(m.filename)[:100]}' refused: {size:,} bytes, "
                                           f"more than the {self.limit:,} accepted")
        with self._lock:
            if m.transfer_uuid in self._transfers or len(self._transfers) >= self.max_in_flight:
                busy = True
            else:
                busy = False
                if parts > 0:
                    self._transfers[m.transfer_uuid] = dict(client=client_id, size=size, parts=parts,
                                                            got=0, seen=set(), bad=False)
        if busy:
            return self._refuse(client_id, f"upload '{str(m.filename)[:100]}' refused: "
                                           f"{self.max_in_flight} uploads already in progress")
        return True

    def _part(self, client_id: int, m) -> bool:
        with self._lock:
            t = self._transfers.get(m.transfer_uuid)
            if t is None or t["bad"] or t["client"] != client_id:
                return False
            n = len(m.content) if isinstance(m.content, (bytes, bytearray, memoryview)) else None
            if n is None or t["got"] + n > t["size"] or m.part_index in t["seen"] \
                    or not 0 <= m.part_index < t["parts"]:
                t["bad"] = True            # kept (counted in flight) until the tab disconnects
                overflow = True
            else:
                overflow = False
                t["got"] += n
                t["seen"].add(m.part_index)
                if len(t["seen"]) == t["parts"]:
                    del self._transfers[m.transfer_uuid]
        if overflow:
            return self._refuse(client_id, f"upload refused: its parts exceed the {t['size']:,} bytes declared")
        return True

    def _forget(self, client_id: int) -> None:
        with self._lock:
            for uuid in [u for u, t in self._transfers.items() if t["client"] == client_id]:
                del self._transfers[uuid]


def _gated(cb: Callable, check: Callable[[int, Any], bool]) -> Callable:
    """``cb(client_id, message)`` run only if ``check`` passes (sync or coroutine, as ``cb``)."""
    if inspect.iscoroutinefunction(cb):
        async def gated(client_id, message):
            if check(client_id, message):
                await cb(client_id, message)
    else:
        def gated(client_id, message):
            if check(client_id, message):
                cb(client_id, message)
    return gated
