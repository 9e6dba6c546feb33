"""The page's messages: what the browser may send, checked before anything reaches the robot (no ROS).

Browser → node (one JSON object per websocket text frame)::

    {"type": "command", "text": "give me the bottle", "ref": 7}   # → submit_command, answered by "ack"
    {"type": "stop", "ref": 8}                                    # → /cancel_command, answered by "stop_sent"
    {"type": "ping", "ref": 9}                                    # → "pong"

``ref`` (optional, integer 0..2**31-1) is echoed in the answer. Anything else — not JSON, not an
object, an unknown type, a missing or empty text, a text over the limit, a frame over the size
limit, binary frames — raises :class:`~home_robot_web.errors.ProtocolError` with a sentence for the
person, which the node sends back as ``{"type": "error", "ref": ..., "error": "..."}``.

Node → browser: ``hello`` (the whole state at connect), ``status`` (one ``/task_status`` update),
``memory``, ``robot``, ``goal``, ``map``, ``ack``, ``stop_sent``, ``pong``, ``error`` (see
docs/web_ui.md). The functions below build them from plain values.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from home_robot_web.errors import ProtocolError

KINDS = ("command", "stop", "ping")
MAX_REF = 2**31 - 1
#: Task status fields passed to the page (the decision maker's TaskStatus), with their types.
STATUS_FIELDS: dict[str, type | tuple[type, ...]] = {
    "id": int, "text": str, "state": str, "step": int, "steps": int, "primitive": str, "message": str,
    "sentence": str, "stamp": (int, float),
}
#: Longest string field of a status passed on (characters); longer ones are cut.
MAX_STATUS_FIELD_CHARS = 2000


@dataclass(frozen=True)
class ClientMessage:
    """One checked message from the page."""

    kind: str  # one of KINDS
    text: str = ""  # the command (kind "command"), or the stop's reason
    ref: int | None = None


def _ref(doc: dict) -> int | None:
    ref = doc.get("ref")
    if ref is None:
        return None
    if isinstance(ref, bool) or not isinstance(ref, int) or not 0 <= ref <= MAX_REF:
        raise ProtocolError(f"'ref' must be an integer 0..{MAX_REF}")
    return ref


def parse_client_message(raw: str | bytes, max_bytes: int = 4096, max_text_chars: int = 500) -> ClientMessage:
    """Check one websocket frame from the page.

    Args:
        raw: the frame (text; a binary frame is refused).
        max_bytes: largest frame accepted (UTF-8 bytes).
        max_text_chars: longest command text (characters, after stripping spaces).

    Raises:
        ProtocolError: with a sentence for the person, and the ``ref`` when it could be read.
    """
    if isinstance(raw, (bytes, bytearray, memoryview)):
        raise ProtocolError("binary messages are not accepted: send JSON text")
    size = len(raw.encode("utf-8", "surrogatepass"))
    if size > max_bytes:
        raise ProtocolError(f"message too large: {size} bytes, at most {max_bytes}")
    try:
        doc = json.loads(raw)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ProtocolError(f"not JSON: {str(exc)[:80]}") from exc
    if not isinstance(doc, dict):
        raise ProtocolError("a message must be a JSON object with a 'type'")
    ref = _ref(doc)
    kind = doc.get("type")
    if kind not in KINDS:
        raise ProtocolError(f"unknown message type {str(kind)[:40]!r}: expected one of {', '.join(KINDS)}", ref)
    text = doc.get("text", "")
    if not isinstance(text, str):
        raise ProtocolError("'text' must be a string", ref)
    text = text.strip()
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:  # a lone surrogate (JSON's "\ud800"): no ROS string can carry it
        if kind == "command":
            raise ProtocolError("the command is not valid Unicode text (a lone surrogate)", ref) from None
        text = text.encode("utf-8", "replace").decode("utf-8")  # a stop always goes out: its reason mended
    if kind == "command":
        if not text:
            raise ProtocolError("empty command: type what the robot should do", ref)
        if len(text) > max_text_chars:
            raise ProtocolError(f"command too long: {len(text)} characters, at most {max_text_chars}", ref)
        if "\x00" in text:
            raise ProtocolError("the command contains a NUL character", ref)
    elif kind == "stop":
        text = " ".join(text.split())[:200]
    return ClientMessage(kind, text, ref)


def dumps(event: dict[str, Any]) -> str:
    """An event as compact JSON (NaN/inf refused: the browser's JSON cannot read them)."""
    return json.dumps(event, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def error_event(message: str, ref: int | None = None) -> dict[str, Any]:
    return {"type": "error", "ref": ref, "error": message}


def status_event(data: str) -> dict[str, Any]:
    """A ``/task_status`` message (the decision maker's JSON) as a page event.

    Raises:
        ValueError: not a task status (not JSON, no ``id``/``state``, wrong types).
    """
    try:
        doc = json.loads(data)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"not JSON: {exc}") from exc
    if not isinstance(doc, dict) or "id" not in doc or "state" not in doc:
        raise ValueError("not a task status (no id/state)")
    out: dict[str, Any] = {"type": "status"}
    for key, kind in STATUS_FIELDS.items():
        if key not in doc:
            continue
        value = doc[key]
        if isinstance(value, bool) or not isinstance(value, kind):
            raise ValueError(f"task status field {key!r} has the wrong type")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"task status field {key!r} is not finite")
        out[key] = value[:MAX_STATUS_FIELD_CHARS] if isinstance(value, str) else value
    return out


def finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def robot_event(x: float, y: float, yaw: float, add: bool) -> dict[str, Any]:
    """The robot's pose (map frame, m, rad); ``add``: this pose is a new point of its path (``add`` = [x, y],
    1 cm resolution; the server keeps the path for pages that open later), else ``add`` is null."""
    return {"type": "robot", "x": round(x, 3), "y": round(y, 3), "yaw": round(yaw, 4),
            "add": [round(x, 2), round(y, 2)] if add else None}


def goal_event(goal_id: str, status: str, wall_time: float) -> dict[str, Any]:
    """A navigation goal's state change (``status``: accepted | executing | canceling | succeeded |
    canceled | aborted), seen at ``wall_time`` (s since the epoch)."""
    return {"type": "goal", "goal": goal_id, "status": status, "time": wall_time}


def memory_event(instances: list[dict[str, Any]], revision: int) -> dict[str, Any]:
    """The object memory: one dict per instance (id, name, x, y, z, confidence, last_seen, source, state,
    place, note)."""
    return {"type": "memory", "revision": revision, "instances": instances}
