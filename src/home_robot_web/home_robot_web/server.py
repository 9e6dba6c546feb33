"""The page's HTTP + websocket server on its own asyncio thread (no ROS).

One ``websockets`` server answers plain GET requests (the page, ``/state``) and the page's
websocket (``/ws``) on one port. Every request passes the :class:`~home_robot_web.auth.Gate` first.

Threads: :meth:`WebServer.publish` may be called from any thread (ROS callbacks) and never blocks:
it hands the event to the server's loop. The robot side (:class:`Robot`) is called from the loop
and must not block either (``submit`` answers later through its callback, from any thread). The
server's state (latest events, status history, clients) is touched only in the loop's thread.

A client that does not keep up (its queue of ``client_queue`` events is full) is disconnected
(close code 1013) instead of slowing the robot down; the page reconnects and gets the whole state.
A closed page is only forgotten: nothing is sent to the robot when a browser goes away.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol
from urllib.parse import urlsplit

from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from home_robot_web.auth import COOKIE, Gate
from home_robot_web.errors import ConfigError, ProtocolError, ServerError
from home_robot_web.protocol import dumps, error_event, parse_client_message

#: Largest frame the websocket layer reads before closing the connection (1009), as a multiple of
#: ``max_message_bytes``: frames in between get a clear error message and the connection stays.
FRAME_LIMIT_FACTOR = 16
#: How many points of the robot's path are kept for a page that connects later.
MAX_PATH_POINTS = 2000

LogFn = Callable[[str, str], None]  # (level "info" | "warn" | "error", text)


class Robot(Protocol):
    """What the page may ask of the robot (the ROS shell implements it)."""

    def submit(self, text: str, done: Callable[[dict[str, Any]], None]) -> None:
        """Send a command; call ``done`` once, from any thread, with ``accepted``, ``id``, ``state``,
        ``message``, ``via``. Must not block."""

    def stop(self, reason: str) -> dict[str, Any]:
        """Publish the stop now; returns what the page is told (e.g. ``{"listeners": 3}``). Must not block."""


@dataclass(frozen=True)
class ServerConfig:
    """Limits of the server. Sizes in bytes, rates per second.

    Attributes:
        host: address to bind (127.0.0.1 unless exposed).
        port: TCP port (0 = any free port; the chosen one is :attr:`WebServer.port`).
        max_message_bytes: largest message from a page that is read (larger: an error on the page).
        max_text_chars: longest command (characters).
        max_clients: open pages at once; more get HTTP 503.
        messages_per_s: messages one page may send per second (a burst of twice as many is allowed).
        client_queue: events waiting for one page; a page that falls further behind is disconnected.
        status_history: last ``/task_status`` updates a newly opened page gets.
    """

    host: str = "127.0.0.1"
    port: int = 8090
    max_message_bytes: int = 4096
    max_text_chars: int = 500
    max_clients: int = 16
    messages_per_s: float = 20.0
    client_queue: int = 2000
    status_history: int = 200

    def __post_init__(self) -> None:
        if not 0 <= self.port < 65536:
            raise ConfigError(f"port must be in 0..65535, got {self.port}")
        for name in ("max_message_bytes", "max_text_chars", "max_clients", "client_queue", "status_history"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.messages_per_s > 0:
            raise ConfigError(f"messages_per_s must be > 0, got {self.messages_per_s}")


class TokenBucket:
    """``rate`` events per second on average, bursts up to ``burst``."""

    def __init__(self, rate: float, burst: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate, self.burst, self._clock = rate, burst, clock
        self._tokens, self._last = burst, clock()

    def take(self) -> bool:
        now = self._clock()
        self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate)
        self._last = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


@dataclass(eq=False)
class _Client:
    ws: ServerConnection
    queue: asyncio.Queue
    bucket: TokenBucket
    peer: str
    closed: bool = False
    sent: int = field(default=0)


class _LogHandler(logging.Handler):
    """The websockets library's warnings and errors, one line each (no tracebacks), into our log."""

    def __init__(self, log: LogFn) -> None:
        super().__init__(logging.WARNING)
        self._log = log

    def emit(self, record: logging.LogRecord) -> None:
        exc = f": {record.exc_info[1]!r}" if record.exc_info and record.exc_info[1] else ""
        self._log("warn", f"websocket layer: {record.getMessage()}{exc}")


def loggable(text: str) -> str:
    """``text`` with what UTF-8 cannot carry (a request's raw bytes, kept by websockets as lone surrogates) escaped:
    rclpy's logger, and any UTF-8 writer, refuses it as it is."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def _safe_path(path: str) -> str:
    """The request path for the log, without its query (which may hold a token), bytes that are not UTF-8 escaped."""
    return loggable(urlsplit(path).path[:100])


def _response(status: int, reason: str, body: bytes, content_type: str, extra: list[tuple[str, str]] = ()) -> Response:
    headers = Headers([("Content-Type", content_type), ("Content-Length", str(len(body))),
                       ("Cache-Control", "no-store"), ("X-Content-Type-Options", "nosniff"),
                       ("Referrer-Policy", "no-referrer"), ("Connection", "close"), *extra])
    return Response(status, reason, headers, body)


_REASONS = {200: "OK", 401: "Unauthorized", 403: "Forbidden", 404: "Not Found", 421: "Misdirected Request",
            429: "Too Many Requests", 503: "Service Unavailable"}
#: The page's policy: its own scripts and websocket only, never inside another site's frame.
CSP = ("default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; connect-src 'self'; "
       "img-src 'self' data:; frame-ancestors 'none'; base-uri 'none'; form-action 'none'")


class WebServer:
    """Serves ``page`` and its websocket; see the module's docstring.

    Args:
        config: limits and address.
        gate: the checks of every request (token, host, origin, attempts).
        robot: where commands and stops go.
        page: the HTML page (UTF-8).
        log: ``log(level, text)``, level ``info`` | ``warn`` | ``error``.
    """

    def __init__(self, config: ServerConfig, gate: Gate, robot: Robot, page: bytes, log: LogFn) -> None:
        self.config, self.gate, self._robot, self._page, self._log = config, gate, robot, page, log
        self.port: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._start_error: BaseException | None = None
        self._stop_event: asyncio.Event | None = None
        # loop thread only:
        self._clients: set[_Client] = set()
        self._statuses: collections.deque[dict[str, Any]] = collections.deque(maxlen=config.status_history)
        self._latest: dict[str, tuple[dict[str, Any], str]] = {}  # event type -> (event, its JSON)
        self._path: collections.deque[list[float]] = collections.deque(maxlen=MAX_PATH_POINTS)
        self.refused = 0  # requests refused by the gate (loop thread writes, others may read)
        self._ws_logger = logging.getLogger(f"home_robot_web.websockets.{id(self)}")
        self._ws_logger.propagate = False
        self._ws_logger.setLevel(logging.WARNING)
        self._ws_logger.addHandler(_LogHandler(log))

    # --- lifecycle (any thread) -------------------------------------------------------------------

    def start(self, timeout_s: float = 10.0) -> None:
        """Bind and serve in a background thread. Raises :class:`ServerError` (address in use, ...)."""
        self._thread = threading.Thread(target=self._run, name="web-ui-server", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout_s):
            raise ServerError(f"the web server did not start within {timeout_s:g} s")
        if self._start_error is not None:
            raise ServerError(f"cannot serve on {self.config.host}:{self.config.port}: {self._start_error}")

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close every page's connection and stop serving (waits up to ``timeout_s``)."""
        loop, ev = self._loop, self._stop_event
        if loop is not None and ev is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(ev.set)
            except RuntimeError:  # the loop closed meanwhile
                pass
        if self._thread is not None:
            self._thread.join(timeout_s)

    @property
    def url(self) -> str:
        host = self.config.host if self.config.host not in ("0.0.0.0", "::") else "127.0.0.1"
        return f"http://{host}:{self.port}/"

    def publish(self, event: dict[str, Any]) -> None:
        """Send ``event`` to every page (and keep it for pages that open later). Never blocks.

        Raises:
            ValueError: the event cannot be JSON (NaN, infinity, non-JSON values).
        """
        text = dumps(event)
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(self._apply, event, text)
        except RuntimeError:  # the loop is closing (shutdown): nothing to show anything on
            pass

    def clients(self) -> int:
        return len(self._clients)

    # --- the loop's thread ------------------------------------------------------------------------

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main())
        finally:
            self._started.set()
            loop.close()

    async def _main(self) -> None:
        self._stop_event = asyncio.Event()
        c = self.config
        try:
            server = await serve(self._serve, c.host, c.port, process_request=self._process_request,
                                 max_size=c.max_message_bytes * FRAME_LIMIT_FACTOR, max_queue=16,
                                 ping_interval=20.0, ping_timeout=20.0, open_timeout=10.0, close_timeout=2.0,
                                 logger=self._ws_logger, server_header=None)
        except OSError as exc:
            self._start_error = exc
            self._started.set()
            return
        self.port = int(server.sockets[0].getsockname()[1])
        self._started.set()
        await self._stop_event.wait()
        server.close()
        try:
            await asyncio.wait_for(server.wait_closed(), 3.0)
        except TimeoutError:
            self._log("warn", "web server: pages did not close within 3 s")

    def _hello(self) -> dict[str, Any]:
        out: dict[str, Any] = {"type": "hello", "statuses": list(self._statuses), "path": list(self._path),
                               "token_required": self.gate.token_required,
                               "limits": {"max_message_bytes": self.config.max_message_bytes,
                                          "max_text_chars": self.config.max_text_chars}}
        for kind in ("memory", "robot", "goal"):
            if kind in self._latest:
                out[kind] = self._latest[kind][0]
        return out

    def _apply(self, event: dict[str, Any], text: str) -> None:
        kind = event.get("type")
        if kind == "status":
            self._statuses.append(event)
        elif kind in ("memory", "robot", "goal", "map"):
            self._latest[kind] = (event, text)
            if kind == "robot" and event.get("add") is not None:
                self._path.append(event["add"])
        for client in list(self._clients):
            self._offer(client, text)

    def _offer(self, client: _Client, text: str) -> None:
        if client.closed:
            return
        try:
            client.queue.put_nowait(text)
        except asyncio.QueueFull:
            client.closed = True
            self._log("warn", f"page at {client.peer} fell {self.config.client_queue} events behind: disconnected "
                              "(it reconnects and gets the whole state)")
            asyncio.ensure_future(client.ws.close(1013, "too slow: reconnect"))

    def _reply_from_any_thread(self, client: _Client, event: dict[str, Any]) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(self._offer, client, dumps(event))
        except RuntimeError:
            pass

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        peer = str(connection.remote_address[0]) if connection.remote_address else "?"
        decision = self.gate.check(peer, request.path, request.headers)
        route = urlsplit(request.path).path
        if not decision.allowed:
            self.refused += 1
            self._log("warn", f"refused {peer} GET {_safe_path(request.path)}: {decision.status} {decision.reason}")
            extra = [("Retry-After", str(int(self.gate.limiter.lockout_s)))] if decision.status == 429 else []
            return _response(decision.status, _REASONS.get(decision.status, "Refused"),
                             loggable(decision.reason + "\n").encode(), "text/plain; charset=utf-8",
                             extra)
        if route == "/ws":
            if len(self._clients) >= self.config.max_clients:
                return _response(503, _REASONS[503], f"at most {self.config.max_clients} pages at once\n".encode(),
                                 "text/plain; charset=utf-8")
            return None  # the websocket handshake goes on
        if route in ("/", "/index.html"):
            extra = [("Content-Security-Policy", CSP), ("X-Frame-Options", "DENY")]
            if decision.set_cookie and self.gate.token is not None:
                extra.append(("Set-Cookie", f"{COOKIE}={self.gate.token}; Path=/; HttpOnly; SameSite=Strict"))
            return _response(200, "OK", self._page, "text/html; charset=utf-8", extra)
        if route == "/state":
            return _response(200, "OK", (dumps(self._hello()) + "\n").encode(), "application/json")
        return _response(404, _REASONS[404], b"not found\n", "text/plain; charset=utf-8")

    async def _serve(self, ws: ServerConnection) -> None:
        c = self.config
        peer = str(ws.remote_address[0]) if ws.remote_address else "?"
        client = _Client(ws, asyncio.Queue(c.client_queue), TokenBucket(c.messages_per_s, 2 * c.messages_per_s), peer)
        # registered and greeted in one step of the loop: no event falls between the state and the stream
        self._clients.add(client)
        self._offer(client, dumps(self._hello()))
        if "map" in self._latest:
            self._offer(client, self._latest["map"][1])
        self._log("info", f"page connected from {peer} ({len(self._clients)} open)")
        sender = asyncio.ensure_future(self._send_loop(client))
        try:
            async for raw in ws:
                self._on_frame(client, raw)
        except ConnectionClosed:
            pass
        finally:
            client.closed = True
            self._clients.discard(client)
            sender.cancel()
            self._log("info", f"page from {peer} closed ({len(self._clients)} open); nothing changes on the robot")

    async def _send_loop(self, client: _Client) -> None:
        try:
            while True:
                text = await client.queue.get()
                await client.ws.send(text)
                client.sent += 1
        except (ConnectionClosed, asyncio.CancelledError):
            pass

    def _on_frame(self, client: _Client, raw: str | bytes) -> None:
        c = self.config
        if not client.bucket.take():
            self._offer(client, dumps(error_event(
                f"too many messages: at most {c.messages_per_s:g} per second; this one was not sent to the robot")))
            return
        try:
            msg = parse_client_message(raw, c.max_message_bytes, c.max_text_chars)
        except ProtocolError as exc:
            self._log("info", f"bad message from {client.peer}: {exc}")
            self._offer(client, dumps(error_event(str(exc), exc.ref)))
            return
        try:
            if msg.kind == "command":
                ref = msg.ref

                def done(ack: dict[str, Any], client: _Client = client, ref: int | None = ref) -> None:
                    self._reply_from_any_thread(client, {"type": "ack", "ref": ref, **ack})

                self._robot.submit(msg.text, done)
            elif msg.kind == "stop":
                info = self._robot.stop(msg.text or "web page STOP")
                self._offer(client, dumps({"type": "stop_sent", "ref": msg.ref, **info}))
            else:
                self._offer(client, dumps({"type": "pong", "ref": msg.ref, "time": time.time()}))
        except Exception as exc:  # the robot side failed: the page is told, the server goes on
            self._log("error", f"{msg.kind} from {client.peer} failed: {exc!r}")
            self._offer(client, dumps(error_event(f"the robot could not take the {msg.kind}: {exc}", msg.ref)))
