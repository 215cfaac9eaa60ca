"""A fake OpenAI-compatible chat-completions server on 127.0.0.1, run in a thread of the test.

It answers every caption with the rule segmenter's split (a valid answer), except for the
captions given a fault in ``faults`` (caption -> fault name, see `FakeOpenAI.FAULTS`). A
fault whose name ends in ``-once`` happens on the caption's first request only. Every
request is recorded (caption, arrival time), so tests can check retries and waits.

    with FakeOpenAI(faults={"a man runs": "500"}) as server:
        OpenAISegmenter(server.url, "tiny", timeout=0.5).segment(["a man runs"])
"""

from __future__ import annotations

import gzip
import json
import threading
import time
from collections import defaultdict
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from segmo.text.rules import RuleSegmenter

RETRY_AFTER = 1.2  # seconds a 429 asks for; more than the client's own first back-off (0.5 s)
HANG = 2.0  # seconds a "hang" waits before answering; tests use a shorter client timeout
TRICKLE = 0.05  # seconds between the bytes of a "trickle" answer (about 20 s in all)
FLOOD = 64 << 20  # bytes of a "flood" answer that never ends its JSON


def _envelope(content: object) -> str:
    return json.dumps({"id": "x", "object": "chat.completion", "created": 0, "model": "tiny",
                       "choices": [{"index": 0, "finish_reason": "stop",
                                    "message": {"role": "assistant", "content": content}}]})


class FakeOpenAI:
    FAULTS = ("500", "429", "hang", "badjson", "invalidjson", "prose", "itisit", "copies",
              "dropped", "reversed", "400", "401", "deepbody", "parts", "number", "deep", "braces",
              "foreign", "nul", "surrogate", "stall", "trickle", "flood", "gzip")

    def __init__(self, faults: dict[str, str] | None = None, block_at: int | None = None,
                 structured: bool = True) -> None:
        self.faults = dict(faults or {})
        self.structured = structured  # False: refuse response_format with a 400, as old servers do
        self.bodies: list[dict] = []  # every request body, in arrival order
        self.headers: list[dict[str, str]] = []  # and its headers
        self.connections: set[int] = set()  # client ports seen (one per kept-alive connection)
        self.calls: dict[str, int] = defaultdict(int)
        self.times: dict[str, list[float]] = defaultdict(list)
        self.total = 0
        self.block_at = block_at  # the request with this number (1-based) waits for `release`
        self.blocked = threading.Event()
        self.release = threading.Event()
        self._lock = threading.Lock()
        self._rules = RuleSegmenter()
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"  # keep-alive, as real servers do
            # buffered: an answer's headers and body leave in one write, as from a real server,
            # so a client never waits on this thread between them on a loaded host
            wbufsize = -1

            def log_message(self, *args):
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                with server._lock:
                    server.bodies.append(body)
                    server.headers.append({k.lower(): v for k, v in self.headers.items()})
                    server.connections.add(self.client_address[1])
                code, headers, text = server.respond(self.path, body)
                fake = headers.pop("X-Fake", None)
                if fake:
                    self.stream(fake, text)
                    return
                try:
                    self.send_response(code)
                    for key, value in {"Content-Type": "application/json", **headers}.items():
                        self.send_header(key, value)
                    self.send_header("Content-Length", str(len(text.encode())))
                    self.end_headers()
                    self.wfile.write(text.encode())
                except OSError:
                    pass  # the client gave up (timeout) or was killed

            def stream(self, fake, text):
                """`text` one byte at a time ("trickle"), FLOOD bytes of spaces ("flood"), or
                those spaces and `text` gzipped ("gzip")."""
                data = {"trickle": text.encode(), "flood": b" " * FLOOD,
                        "gzip": gzip.compress(b" " * FLOOD + text.encode())}[fake]
                try:
                    self.send_response(200)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    if fake == "gzip":
                        self.send_header("Content-Encoding", "gzip")
                    self.end_headers()
                    step = 1 if fake == "trickle" else 65536
                    for i in range(0, len(data), step):
                        self.wfile.write(data[i : i + step])
                        if fake == "trickle":
                            self.wfile.flush()
                            time.sleep(TRICKLE)
                except OSError:
                    pass  # the client stopped reading

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"

    # ------------------------------------------------------------------ behaviour
    def respond(self, path: str, body: dict) -> tuple[int, dict[str, str], str]:
        if path != "/v1/chat/completions":
            return 404, {}, '{"error": {"message": "no such route"}}'
        if "response_format" in body and not self.structured:
            return 400, {}, '{"error": {"message": "response_format is not supported"}}'
        caption = next(m["content"] for m in reversed(body["messages"])
                       if m["role"] == "user" and not m["content"].startswith("Invalid answer"))
        with self._lock:
            self.total += 1
            number = self.total
            self.calls[caption] += 1
            self.times[caption].append(time.monotonic())
            attempt = self.calls[caption]
        if self.block_at is not None and number >= self.block_at:
            self.blocked.set()
            self.release.wait(60)
        fault = self.faults.get(caption, "")
        if fault.endswith("-once"):
            fault = fault[: -len("-once")] if attempt == 1 else ""
        segments = self._rules.segment_one(caption)
        if fault == "401":
            return 401, {}, '{"error": {"message": "bad key"}}'
        if fault == "400":  # what a server says to a prompt longer than its context
            return 400, {}, '{"error": {"message": "maximum context length exceeded"}}'
        if fault == "500":
            return 500, {}, '{"error": {"message": "internal error"}}'
        if fault == "429":
            return 429, {"Retry-After": str(RETRY_AFTER)}, '{"error": {"message": "slow down"}}'
        if fault == "hang":
            time.sleep(HANG)
        if fault == "stall":  # a server that takes a minute: an interrupted run must not wait
            time.sleep(60)
        if fault == "trickle":
            return 200, {"X-Fake": "trickle"}, _envelope(json.dumps({"segments": segments}))
        if fault == "flood":
            return 200, {"X-Fake": "flood"}, "x"
        if fault == "gzip":  # a 64 KB gzip of 64 MB, sent although the client asked for none
            return 200, {"X-Fake": "gzip"}, _envelope(json.dumps({"segments": segments}))
        if fault == "badjson":
            return 200, {}, '{"choices": [ not json'
        if fault == "deepbody":  # a body nested beyond Python's recursion limit
            return 200, {}, '{"choices": ' + "[" * 100_000
        if fault in ("parts", "number"):  # content that is not a string
            answer = json.dumps({"segments": segments})
            content = [{"type": "text", "text": answer}] if fault == "parts" else 12345
            return 200, {}, _envelope(content)
        content = {
            "invalidjson": '{"segments": ["' + caption,
            "prose": f"Sure! The person first does this and then that: {caption}.",
            "itisit": json.dumps({"segments": ["it is it"]}),
            "copies": json.dumps({"segments": [segments[0]] * 5}),
            "dropped": json.dumps({"segments": segments[:1]}),
            "reversed": json.dumps({"segments": segments[::-1]}),
            "deep": '{"a":' * 100_000,
            "braces": "{" * 300_000,  # each '{' a parse: minutes when every one is tried
            "foreign": json.dumps({"segments": [segments[0] + " 火箭发射到月球", *segments[1:]]}),
            "nul": json.dumps({"segments": [segments[0] + " \u0000", *segments[1:]]}),
            "surrogate": json.dumps({"segments": [segments[0] + " \ud800", *segments[1:]]}),
        }.get(fault, "```json\n" + json.dumps({"segments": segments}) + "\n```")
        return 200, {}, _envelope(content)

    # ------------------------------------------------------------------ lifetime
    def __enter__(self) -> FakeOpenAI:
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.02},
                                       daemon=True)
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release.set()
        self.httpd.shutdown()
        self.httpd.server_close()
