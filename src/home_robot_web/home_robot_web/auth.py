"""The key to the page: pairing token, request checks and a limit on wrong attempts (no ROS).

Every HTTP request and websocket handshake goes through :meth:`Gate.check`, in this order:

1. a client locked out after too many wrong tokens is refused (429) until its lockout ends;
2. on loopback (not exposed) the ``Host`` header must name this machine (``127.0.0.1``,
   ``localhost`` or ``[::1]``): a web page elsewhere cannot reach the robot through DNS rebinding;
3. a browser's ``Origin`` header, when sent, must be this page's own (a website open in another tab
   cannot open the robot's websocket: websockets are not covered by the browser's same-origin rule);
4. when a token is required (exposed on the network): the token from the ``token`` query parameter,
   the ``hr_token`` cookie or an ``Authorization: Bearer`` header, compared in constant time. Missing
   → 401, wrong → 403 and one failed attempt counted for the client's address.
"""

from __future__ import annotations

import hmac
import math
import os
import secrets
import stat
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from http.cookies import CookieError, SimpleCookie
from urllib.parse import parse_qs, urlsplit

from home_robot_web.errors import ConfigError, TokenFileError

#: Shortest token accepted from a file (characters); generated ones have 32.
MIN_TOKEN_CHARS = 16
#: Name of the cookie the page sets after a good token, so a reload needs no token in the address.
COOKIE = "hr_token"
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]")


def generate_token() -> str:
    """A new random pairing token (32 URL-safe characters, 192 bits)."""
    return secrets.token_urlsafe(24)


def read_token_file(path: str, create: bool = True) -> tuple[str, bool]:
    """The token kept in ``path``; created (owner-only, a new token) when it does not exist and ``create``.

    Returns:
        (token, created).

    Raises:
        TokenFileError: unreadable, readable or writable by group/others, owned by someone else, or a
            token shorter than :data:`MIN_TOKEN_CHARS`.
    """
    if create and not os.path.exists(path):
        token = generate_token()
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except OSError as exc:
            raise TokenFileError(f"cannot create the token file {path!r}: {exc.strerror}") from exc
        with os.fdopen(fd, "w") as fh:
            fh.write(token + "\n")
        return token, True
    try:
        st = os.stat(path)
        if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise TokenFileError(f"the token file {path!r} is open to group/others (mode "
                                 f"{stat.S_IMODE(st.st_mode):o}): chmod 600 {path}")
        if hasattr(os, "getuid") and st.st_uid != os.getuid():
            raise TokenFileError(f"the token file {path!r} belongs to another user (uid {st.st_uid})")
        with open(path, encoding="utf-8") as fh:
            token = fh.read(4096).strip()
    except OSError as exc:
        raise TokenFileError(f"cannot read the token file {path!r}: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        raise TokenFileError(f"the token file {path!r} is not text") from exc
    if len(token) < MIN_TOKEN_CHARS or any(c.isspace() for c in token):
        raise TokenFileError(f"the token in {path!r} must be at least {MIN_TOKEN_CHARS} characters without spaces")
    return token, False


class AttemptLimiter:
    """Locks a client address out after ``max_failures`` wrong tokens within ``window_s`` seconds.

    The lockout lasts ``lockout_s`` seconds; at most ``max_tracked`` addresses are remembered (the
    oldest is forgotten first), so a flood of addresses cannot grow memory. Not thread-safe: the
    server calls it from its event loop only.
    """

    def __init__(self, max_failures: int = 5, window_s: float = 60.0, lockout_s: float = 60.0,
                 max_tracked: int = 4096, clock: Callable[[], float] = time.monotonic) -> None:
        if max_failures < 1 or not 0 < window_s < math.inf or not 0 < lockout_s < math.inf or max_tracked < 1:
            raise ConfigError(f"max_failures >= 1, failure_window_s and lockout_s finite and > 0 are required, got "
                              f"{max_failures}, {window_s}, {lockout_s}")
        self.max_failures, self.window_s, self.lockout_s = max_failures, window_s, lockout_s
        self._max_tracked = max_tracked
        self._clock = clock
        self._failures: OrderedDict[str, list[float]] = OrderedDict()  # address -> failure times in the window
        self._locked_until: OrderedDict[str, float] = OrderedDict()

    def locked_for(self, peer: str) -> float:
        """Seconds left of ``peer``'s lockout (0 = not locked)."""
        until = self._locked_until.get(peer)
        if until is None:
            return 0.0
        left = until - self._clock()
        if left <= 0:
            del self._locked_until[peer]
            return 0.0
        return left

    def failure(self, peer: str) -> bool:
        """Count one wrong token from ``peer``. Returns True when this failure locks it out."""
        now = self._clock()
        times = [t for t in self._failures.pop(peer, []) if now - t < self.window_s] + [now]
        if len(times) >= self.max_failures:
            self._locked_until[peer] = now + self.lockout_s
            self._locked_until.move_to_end(peer)
            times = []
        if times:
            self._failures[peer] = times
        for table in (self._failures, self._locked_until):
            while len(table) > self._max_tracked:
                table.popitem(last=False)
        return not times

    def failures(self, peer: str) -> int:
        """Wrong tokens from ``peer`` in the current window."""
        now = self._clock()
        return sum(1 for t in self._failures.get(peer, []) if now - t < self.window_s)


@dataclass(frozen=True)
class Decision:
    """What :meth:`Gate.check` decided: ``status`` 0 = allowed, else the HTTP status to refuse with."""

    status: int = 0
    reason: str = ""
    set_cookie: bool = False  # a good token came in the query: the page keeps it in a cookie

    @property
    def allowed(self) -> bool:
        return self.status == 0


def _header(headers: Mapping[str, str], name: str) -> str:
    return headers.get(name) or ""


def token_from(path: str, headers: Mapping[str, str]) -> tuple[str | None, bool]:
    """The token a request carries (query, cookie or bearer header), and whether it came in the query."""
    query = parse_qs(urlsplit(path).query)
    if query.get("token"):
        return query["token"][0], True
    auth = _header(headers, "Authorization")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip(), False
    cookie = _header(headers, "Cookie")
    if cookie:
        try:
            jar = SimpleCookie(cookie)
        except CookieError:
            return None, False
        if COOKIE in jar:
            return jar[COOKIE].value, False
    return None, False


class Gate:
    """The checks of every request (see the module's docstring).

    Args:
        token: the pairing token; None = no token required (the page is on loopback only).
        limiter: counts wrong tokens per client address.
        loopback_only: check the ``Host`` header names this machine (DNS rebinding).
    """

    def __init__(self, token: str | None, limiter: AttemptLimiter, loopback_only: bool) -> None:
        if token is not None and len(token) < MIN_TOKEN_CHARS:
            raise ConfigError(f"the pairing token must have at least {MIN_TOKEN_CHARS} characters")
        self.token = token
        self._token = token.encode() if token is not None else None
        self.limiter = limiter
        self.loopback_only = loopback_only

    @property
    def token_required(self) -> bool:
        return self._token is not None

    def check(self, peer: str, path: str, headers: Mapping[str, str]) -> Decision:
        """Decide on one request from address ``peer`` for ``path`` (with its query) and ``headers``."""
        left = self.limiter.locked_for(peer)
        if left > 0:
            return Decision(429, f"too many wrong tokens from {peer}: locked out for {left:.0f} s more")
        host = _header(headers, "Host").strip().lower()
        if self.loopback_only and host.rsplit(":", 1)[0] not in LOOPBACK_HOSTS:
            return Decision(421, f"this page is served on loopback only; Host {host[:80]!r} is not this machine")
        origin = _header(headers, "Origin").strip().lower()
        if origin:  # "null" (a sandboxed frame, a file) is refused too
            if origin == "null" or urlsplit(origin).netloc != host:
                return Decision(403, f"cross-site request refused (Origin {origin[:80]!r}, Host {host[:80]!r})")
        if self._token is None:
            return Decision()
        given, in_query = token_from(path, headers)
        if not given:
            return Decision(401, "pairing token required: open the address the robot printed (…/?token=...)")
        if not hmac.compare_digest(given.encode("utf-8", "replace"), self._token):
            locked = self.limiter.failure(peer)
            return Decision(403, "wrong pairing token" + (
                f"; {peer} is locked out for {self.limiter.lockout_s:g} s" if locked else
                f" ({self.limiter.failures(peer)} of {self.limiter.max_failures} attempts)"))
        return Decision(set_cookie=in_query)
