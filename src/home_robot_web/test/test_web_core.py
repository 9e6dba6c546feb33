"""The web UI's functional core without ROS: token file, attempt limits, request gate, message checks,
map points, and the real HTTP/websocket server on loopback with a recording robot."""

from __future__ import annotations

import json
import math
import os
import stat
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from websockets.exceptions import ConnectionClosedError, InvalidStatus
from websockets.sync.client import connect

from home_robot_web.auth import MIN_TOKEN_CHARS, AttemptLimiter, Gate, read_token_file, token_from
from home_robot_web.errors import ConfigError, ProtocolError, ServerError, TokenFileError
from home_robot_web.protocol import parse_client_message, status_event
from home_robot_web.scene import Path2D, map_points
from home_robot_web.server import ServerConfig, TokenBucket, WebServer

TOKEN = "t0ken-for-the-tests-0123456789"
BUNDLED_MAP = Path(__file__).resolve().parents[3] / "data" / "params.npz"


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


# --- token file -----------------------------------------------------------------------------------------

def test_token_file_is_created_owner_only_and_read_back(tmp_path):
    path = tmp_path / "token"
    token, created = read_token_file(str(path))
    assert created and len(token) >= MIN_TOKEN_CHARS
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert read_token_file(str(path)) == (token, False)


def test_token_file_open_to_others_or_short_is_refused(tmp_path):
    path = tmp_path / "token"
    path.write_text(TOKEN)
    os.chmod(path, 0o644)
    with pytest.raises(TokenFileError, match="chmod 600"):
        read_token_file(str(path))
    os.chmod(path, 0o600)
    assert read_token_file(str(path))[0] == TOKEN
    path.write_text("short")
    with pytest.raises(TokenFileError, match="at least"):
        read_token_file(str(path))
    with pytest.raises(TokenFileError, match="cannot read"):
        read_token_file(str(tmp_path / "missing"), create=False)


# --- attempts and the gate ----------------------------------------------------------------------------

def test_limiter_locks_out_after_max_failures_then_forgets():
    clock = Clock()
    lim = AttemptLimiter(max_failures=3, window_s=10.0, lockout_s=30.0, clock=clock)
    assert not lim.failure("a") and not lim.failure("a")
    assert lim.failures("a") == 2 and lim.locked_for("b") == 0
    assert lim.failure("a") and lim.locked_for("a") == pytest.approx(30.0)
    clock.t += 31.0
    assert lim.locked_for("a") == 0
    lim.failure("c")
    clock.t += 11.0  # outside the window: the old failure no longer counts
    assert not lim.failure("c") and lim.failures("c") == 1
    with pytest.raises(ConfigError):
        AttemptLimiter(max_failures=0)


def test_limiter_memory_is_bounded():
    lim = AttemptLimiter(max_failures=5, max_tracked=10)
    for i in range(100):
        lim.failure(f"10.0.0.{i}")
    assert len(lim._failures) <= 10


def test_token_is_read_from_query_bearer_or_cookie():
    assert token_from("/?token=abc", {}) == ("abc", True)
    assert token_from("/ws", {"Authorization": "Bearer xyz"}) == ("xyz", False)
    assert token_from("/", {"Cookie": "a=1; hr_token=qq"}) == ("qq", False)
    assert token_from("/", {"Cookie": "bad cookie;;;\x00"}) == (None, False)
    assert token_from("/", {}) == (None, False)


def test_gate_token_required_when_exposed():
    lim = AttemptLimiter(max_failures=2, lockout_s=60.0)
    gate = Gate(TOKEN, lim, loopback_only=False)
    host = {"Host": "192.168.1.20:8090"}
    assert gate.check("10.0.0.5", "/", host).status == 401
    assert gate.check("10.0.0.5", "/?token=wrong", host).status == 403
    d = gate.check("10.0.0.5", f"/?token={TOKEN}", host)
    assert d.allowed and d.set_cookie
    assert gate.check("10.0.0.5", "/ws", {**host, "Cookie": f"hr_token={TOKEN}"}).allowed
    assert gate.check("10.0.0.5", "/?token=wrong2", host).status == 403  # second wrong one: locked out
    d = gate.check("10.0.0.5", f"/?token={TOKEN}", host)
    assert d.status == 429 and "locked out" in d.reason  # even with the right token, until the lockout ends
    assert gate.check("10.0.0.6", f"/?token={TOKEN}", host).allowed  # another address is not affected


def test_gate_loopback_checks_host_and_origin():
    gate = Gate(None, AttemptLimiter(), loopback_only=True)
    assert gate.check("127.0.0.1", "/", {"Host": "127.0.0.1:8090"}).allowed
    assert gate.check("127.0.0.1", "/", {"Host": "localhost:8090"}).allowed
    assert gate.check("127.0.0.1", "/", {"Host": "evil.example:8090"}).status == 421  # DNS rebinding
    same = {"Host": "127.0.0.1:8090", "Origin": "http://127.0.0.1:8090"}
    assert gate.check("127.0.0.1", "/ws", same).allowed
    assert gate.check("127.0.0.1", "/ws", {**same, "Origin": "https://evil.example"}).status == 403
    assert gate.check("127.0.0.1", "/ws", {**same, "Origin": "null"}).status == 403
    with pytest.raises(ConfigError):
        Gate("short", AttemptLimiter(), loopback_only=False)


# --- messages ---------------------------------------------------------------------------------------------

def test_good_messages_parse():
    m = parse_client_message('{"type": "command", "text": "  give me the bottle ", "ref": 3}')
    assert (m.kind, m.text, m.ref) == ("command", "give me the bottle", 3)
    assert parse_client_message('{"type": "stop"}').kind == "stop"
    assert parse_client_message('{"type": "ping", "ref": 0}').ref == 0


@pytest.mark.parametrize("raw, match", [
    ("not json", "not JSON"),
    ("[1, 2]", "JSON object"),
    ('{"type": "fly"}', "unknown message type"),
    ('{"type": "command"}', "empty command"),
    ('{"type": "command", "text": "   "}', "empty command"),
    ('{"type": "command", "text": 5}', "'text' must be a string"),
    ('{"type": "command", "text": "' + "a" * 501 + '"}', "command too long: 501"),
    ('{"type": "command", "text": "x", "ref": -1}', "'ref'"),
    ('{"type": "command", "text": "x", "ref": true}', "'ref'"),
    ('{"type": "command", "text": "a\\u0000b"}', "NUL"),
    ('{"type": "command", "text": "' + "a" * 5000 + '"}', "message too large"),
    (b'{"type": "stop"}', "binary"),
    ("[" * 100000, "message too large"),
    ('{"type": "command", "text": "go home \\ud800"}', "not valid Unicode text"),
])
def test_bad_messages_get_a_clear_error(raw, match):
    with pytest.raises(ProtocolError, match=match):
        parse_client_message(raw, max_bytes=4096, max_text_chars=500)


def test_a_stop_with_a_lone_surrogate_still_stops_with_its_reason_mended():
    """JSON may carry "\\ud800", which no ROS string can: a command with it is refused, a stop goes out anyway
    (once, the send failed and the STOP was lost)."""
    m = parse_client_message('{"type": "stop", "text": "hands \\ud800 off"}')
    assert m.kind == "stop" and m.text == "hands ? off"
    m.text.encode("utf-8")


def test_error_keeps_the_ref_when_readable():
    with pytest.raises(ProtocolError) as info:
        parse_client_message('{"type": "command", "text": "", "ref": 12}')
    assert info.value.ref == 12


def test_deeply_nested_json_is_an_error_not_a_crash():
    with pytest.raises(ProtocolError):
        parse_client_message("[" * 3000 + "]" * 3000, max_bytes=10**6)


def test_status_event_checks_types():
    ev = status_event(json.dumps({"id": 3, "text": "go home", "state": "running", "step": 1, "steps": 2,
                                 "primitive": "goto:home", "stamp": 1.5, "extra": "dropped"}))
    assert ev["type"] == "status" and ev["primitive"] == "goto:home" and "extra" not in ev
    for bad in ("nope", "[]", '{"id": 1}', '{"id": "1", "state": "running"}', '{"id": 1, "state": "x", "stamp": NaN}'):
        with pytest.raises(ValueError):
            status_event(bad)


# --- scene --------------------------------------------------------------------------------------------

def test_map_points_from_the_bundled_map(tmp_path):
    ev = map_points(str(BUNDLED_MAP), max_points=500)
    assert ev["n"] == 500 and len(ev["xyz"]) == 1500 and len(ev["rgb"]) == 1500
    assert all(0 <= c <= 255 for c in ev["rgb"]) and max(ev["xyz"]) < 1000  # cm: the home is a few metres
    (tmp_path / "bad.npz").write_bytes(b"not a map")
    with pytest.raises(ConfigError, match="cannot read the map"):
        map_points(str(tmp_path / "bad.npz"))


def test_path_keeps_moves_only_and_is_bounded():
    p = Path2D(min_step_m=0.1, max_points=3)
    assert p.add(0, 0) and not p.add(0.05, 0) and p.add(0.2, 0)
    for i in range(10):
        p.add(i, 0)
    assert len(p.points) == 3 and p.points[-1] == (9, 0)


def test_token_bucket():
    clock = Clock()
    b = TokenBucket(rate=2.0, burst=2.0, clock=clock)
    assert b.take() and b.take() and not b.take()
    clock.t += 0.5
    assert b.take() and not b.take()


# --- the server on loopback, with a robot that records -------------------------------------------------

class RecordingRobot:
    def __init__(self) -> None:
        self.commands: list[str] = []
        self.stops: list[str] = []
        self.fail_next = False

    def submit(self, text, done):
        if self.fail_next:
            self.fail_next = False
            raise RuntimeError("service gone")
        self.commands.append(text)
        threading.Thread(target=done, args=({"accepted": True, "id": len(self.commands), "state": "queued",
                                              "message": "queued, 0 ahead", "via": "service"},)).start()

    def stop(self, reason):
        self.stops.append(reason)
        return {"listeners": 2}


@pytest.fixture
def served():
    logs: list[tuple[str, str]] = []
    robot = RecordingRobot()

    def start(token: str | None = None, **cfg) -> WebServer:
        server = WebServer(ServerConfig(**{"host": "127.0.0.1", "port": 0, **cfg}),
                           Gate(token, AttemptLimiter(max_failures=3), loopback_only=token is None),
                           robot, b"<html>page</html>", lambda level, text: logs.append((level, text)))
        server.start()
        started.append(server)
        return server

    started: list[WebServer] = []
    yield start, robot, logs
    for s in started:
        s.stop()


def _recv_until(ws, kind: str, limit: int = 50) -> dict:
    for _ in range(limit):
        msg = json.loads(ws.recv(timeout=10))
        if msg["type"] == kind:
            return msg
    raise AssertionError(f"no {kind!r} message")


def test_server_round_trip_and_bad_input(served):
    start, robot, logs = served
    server = start(max_message_bytes=256)
    server.publish({"type": "status", "id": 1, "text": "go home", "state": "queued"})
    with urllib.request.urlopen(server.url, timeout=10) as r:
        assert r.read() == b"<html>page</html>" and "frame-ancestors 'none'" in r.headers["Content-Security-Policy"]
    with connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10) as ws:
        hello = _recv_until(ws, "hello")
        assert hello["statuses"][0]["text"] == "go home" and hello["token_required"] is False
        ws.send(json.dumps({"type": "command", "text": "give me the bottle", "ref": 5}))
        ack = _recv_until(ws, "ack")
        assert ack["ref"] == 5 and ack["id"] == 1 and robot.commands == ["give me the bottle"]
        ws.send("{{not json")
        assert "not JSON" in _recv_until(ws, "error")["error"]
        ws.send(json.dumps({"type": "command", "text": "x" * 1000, "ref": 6}))
        err = _recv_until(ws, "error")
        assert "message too large" in err["error"]
        robot.fail_next = True
        ws.send(json.dumps({"type": "command", "text": "go home", "ref": 7}))
        err = _recv_until(ws, "error")
        assert err["ref"] == 7 and "service gone" in err["error"]
        ws.send(json.dumps({"type": "stop", "ref": 8}))
        assert _recv_until(ws, "stop_sent")["listeners"] == 2 and robot.stops == ["web page STOP"]
        server.publish({"type": "goal", "goal": "ab", "status": "canceled", "time": 1.0})
        assert _recv_until(ws, "goal")["status"] == "canceled"
    # the server survived all of it; a new page still gets the state
    with connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10) as ws:
        assert _recv_until(ws, "hello")["goal"]["status"] == "canceled"
    assert robot.commands == ["give me the bottle"]  # nothing else reached the robot
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(server.url + "nothing", timeout=10)
    assert info.value.code == 404


def test_frames_past_the_websocket_limit_close_the_page_not_the_server(served):
    start, robot, _ = served
    server = start(max_message_bytes=64)
    with connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10) as ws:
        _recv_until(ws, "hello")
        ws.send("x" * 64 * 20)
        with pytest.raises(ConnectionClosedError):  # closed by the server: 1009 message too big
            _recv_until(ws, "never")
        assert ws.close_code == 1009
    with connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10) as ws:
        ws.send(json.dumps({"type": "ping", "ref": 1}))
        assert _recv_until(ws, "pong")["ref"] == 1


def test_server_with_a_token_refuses_and_logs_and_locks_out(served):
    start, robot, logs = served
    server = start(token=TOKEN)
    base = f"http://127.0.0.1:{server.port}/"
    for path, code in (("", 401), ("?token=nope", 403), ("state", 401)):
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(base + path, timeout=10)
        assert info.value.code == code
    with pytest.raises(InvalidStatus) as refused:  # websocket without the token: refused at the handshake
        connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10)
    assert refused.value.response.status_code == 401
    with connect(f"ws://127.0.0.1:{server.port}/ws?token={TOKEN}", open_timeout=10) as ws:
        assert _recv_until(ws, "hello")["token_required"] is True
    with urllib.request.urlopen(base + f"?token={TOKEN}", timeout=10) as r:
        assert "HttpOnly" in r.headers["Set-Cookie"]
    for _ in range(2):  # two more wrong ones: 3 in all, locked out
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(base + "?token=nope", timeout=10)
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(base + f"?token={TOKEN}", timeout=10)
    assert info.value.code == 429
    refusals = [t for level, t in logs if level == "warn" and t.startswith("refused")]
    assert len(refusals) >= 6 and not any(TOKEN in t for _, t in logs)  # logged, never with the token


def test_a_refused_request_whose_path_is_not_utf8_gets_its_status_and_an_escaped_log_line(served):
    """Raw bytes in the path reach the server as lone surrogates: the refusal is still answered (421 here, a
    foreign Host) and logged in text every logger can write (rclpy's refused it: the answer was a 500)."""
    import socket

    start, _, logs = served
    server = start()
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(b"GET /\xff\xfe HTTP/1.1\r\nHost: evil.example\r\nConnection: close\r\n\r\n")
        answer = b""
        while chunk := sock.recv(4096):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 421"), answer[:80]
    refused = [t for level, t in logs if level == "warn" and t.startswith("refused")]
    assert refused and "GET /\\udcff\\udcfe" in refused[-1], refused
    refused[-1].encode("utf-8")


def test_a_lockout_that_never_ends_is_refused():
    for bad in (math.inf, math.nan, 0.0):
        with pytest.raises(ConfigError, match="lockout_s finite and > 0"):
            AttemptLimiter(max_failures=3, lockout_s=bad)
    with pytest.raises(ConfigError, match="failure_window_s and lockout_s finite"):
        AttemptLimiter(window_s=math.inf)


def test_too_many_messages_get_an_error(served):
    start, robot, _ = served
    server = start(messages_per_s=1.0)
    with connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10) as ws:
        _recv_until(ws, "hello")
        for i in range(5):
            ws.send(json.dumps({"type": "ping", "ref": i}))
        assert "too many messages" in _recv_until(ws, "error")["error"]


def test_port_in_use_is_a_server_error(served):
    start, _, _ = served
    server = start()
    with pytest.raises(ServerError, match="cannot serve"):
        start(port=server.port)


def test_non_finite_event_is_refused():
    server = WebServer(ServerConfig(port=0), Gate(None, AttemptLimiter(), True), RecordingRobot(), b"", print)
    with pytest.raises(ValueError):
        server.publish({"type": "robot", "x": float("nan")})


def test_a_page_that_does_not_read_is_disconnected_not_waited_for(served):
    start, _, logs = served
    server = start(client_queue=4)
    with connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10, max_size=None) as ws:
        _recv_until(ws, "hello")
        big = "x" * 100_000
        for i in range(300):  # 30 MB the page never reads: socket buffers fill, then its queue
            server.publish({"type": "status", "id": i, "state": "running", "text": big})
        deadline = time.monotonic() + 60
        while not any("fell 4 events behind" in t for _, t in logs) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert any("fell 4 events behind" in t for _, t in logs)
        with pytest.raises(ConnectionClosedError):
            while True:
                ws.recv(timeout=30)
        assert ws.close_code == 1013
    with connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10, max_size=None) as ws:  # the server goes on
        assert len(_recv_until(ws, "hello")["statuses"]) == 200


def test_more_pages_than_max_clients_get_503(served):
    start, _, _ = served
    server = start(max_clients=1)
    with connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10) as ws:
        _recv_until(ws, "hello")
        with pytest.raises(InvalidStatus) as refused:
            connect(f"ws://127.0.0.1:{server.port}/ws", open_timeout=10)
        assert refused.value.response.status_code == 503
