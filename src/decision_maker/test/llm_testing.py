"""A scripted OpenAI-compatible chat-completions endpoint on 127.0.0.1 for the LLM-planner tests.

It stands in for the model (which is not under test): it answers from a script, so our client,
validator and the decision maker's handling of LLM plans are tested end to end.
"""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer


def completion(doc=None, content=None, tool=False) -> bytes:
    text = content if content is not None else json.dumps(doc)
    if tool:
        message = {"role": "assistant", "content": None,
                   "tool_calls": [{"id": "c1", "type": "function",
                                   "function": {"name": "submit_plan", "arguments": text}}]}
    else:
        message = {"role": "assistant", "content": text}
    return json.dumps({"id": "x", "object": "chat.completion", "model": "scripted",
                       "choices": [{"index": 0, "message": message, "finish_reason": "stop"}]}).encode()


class ScriptedEndpoint:
    """A chat-completions server on 127.0.0.1 replying from a script: each entry is
    ``(status, body_bytes)`` or ``("sleep", seconds, (status, body))``; the last entry repeats."""

    def __init__(self, script):
        self.script = list(script)
        self.requests: list[dict] = []
        self.headers: list[dict] = []
        endpoint = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                endpoint.requests.append({"path": self.path, "body": json.loads(body)})
                endpoint.headers.append(dict(self.headers))
                step = endpoint.script.pop(0) if len(endpoint.script) > 1 else endpoint.script[0]
                if step[0] == "trickle":  # headers at once, then the body one byte per step[1] s
                    self.send_response(200)
                    self.send_header("Content-Type", "application/json")
                    self.end_headers()
                    try:
                        for b in step[2]:
                            self.wfile.write(bytes([b]))
                            self.wfile.flush()
                            time.sleep(step[1])
                    except (BrokenPipeError, ConnectionResetError):
                        pass
                    return
                if step[0] == "sleep":
                    time.sleep(step[1])
                    step = step[2]
                status, payload = step
                try:
                    self.send_response(status)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(payload)))
                    self.end_headers()
                    self.wfile.write(payload)
                except (BrokenPipeError, ConnectionResetError):
                    pass

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/v1"

    def close(self):
        self.server.shutdown()
        self.server.server_close()
