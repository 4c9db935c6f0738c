"""A fake OpenAI-compatible server for tests and benchmarks: a real HTTP process on 127.0.0.1 (a test double of
the source checkout, not in the wheel).

    python -m lanevil_dev.fake_server [--port 0] [--mode answer|judge|paraphrase] [--delay-ms 50]
        [--fail-every N] [--fail-first N] [--rate-limit-first N --retry-after S] [--max-images N]
        [--require-key KEY] [--no-decode] [--idle-exit-s S]

The first stdout line is the bound port. POST /v1/chat/completions answers deterministically from the request:
- answer mode: "answer: <question> [images=<n> size=<W>x<H> digest=<8 hex>]", the size and an md5 of the decoded
  RGB pixels (so a test sees the frames arrived whole; --no-decode reads the size from the headers only and gives
  digest=-);
- judge mode (DriveLM's prompt): 100 when the answer equals the reference, else a stable number from their hash;
  an answer containing JUNK gets "I cannot rate that." and one containing SCOREFMT gets "Score: 85/100";
- paraphrase mode: "Please tell me: <question>" (yes/no questions keep their first word, statements get "In
  other words: " and a Yes/No answer "<Yes|No> indeed ..."; DROPOPTIONS loses the option letters, FLIPYESNO the
  leading Yes/No, EMPTY gets an empty reply).
A question containing BAD_REQUEST gets a 400. GET /v1/models lists the model, GET /stats the request counts.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import json
import os
import re
import socket
import struct
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

# the checkout root (lanevil_dev's parent): the server process finds `lanevil_dev` there from any working directory
CHECKOUT = Path(__file__).resolve().parent.parent
JUDGE_SPLIT = re.compile(r"This is the correct answer: (.*)This is my answer: (.*)", re.S)


def image_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a PNG or JPEG header, without decoding."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return struct.unpack(">II", data[16:24])
    if data[:2] == b"\xff\xd8":
        i = 2
        while i + 9 < len(data):
            marker, length = data[i + 1], struct.unpack(">H", data[i + 2:i + 4])[0]
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                height, width = struct.unpack(">HH", data[i + 5:i + 9])
                return width, height
            i += 2 + length
    raise ValueError("not a PNG or JPEG image")


def decoded_digest(data: bytes) -> str:
    """md5 (8 hex) of the image's decoded RGB pixels (cv2), as a test computes it from its own frame."""
    import cv2
    import numpy as np

    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return hashlib.md5(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).tobytes()).hexdigest()[:8]


def judge_reply(prompt: str) -> str:
    """The judge mode's reply to DriveLM's rubric prompt."""
    match = JUDGE_SPLIT.search(prompt)
    if not match:
        return "no correct answer given"
    reference, answer = match.groups()
    if "JUNK" in answer:
        return "I cannot rate that."
    if "SCOREFMT" in answer:
        return "Score: 85/100"
    if answer.strip() == reference.strip():
        return "100"
    return str(int(hashlib.md5(prompt.encode()).hexdigest(), 16) % 100)


def paraphrase_reply(prompt: str) -> str:
    """The paraphrase mode's reply: the text after the last 'Text:' marker, reworded trivially."""
    question = prompt.rsplit("Text:", 1)[-1].strip()
    if "EMPTY" in question:
        return ""
    if "DROPOPTIONS" in question:
        return "Please tell me: " + re.sub(r"\(?\b[A-E][.)]\s*", "", question)
    first, _, rest = question.partition(" ")
    if first.lower() in ("is", "are", "does", "do", "can", "should", "will", "was", "were", "has", "have"):
        return f"{first} it true that {rest[0].lower() + rest[1:] if rest else ''}"
    if first.lower().strip(",") in ("yes", "no"):
        return "FLIPPED " + question if "FLIPYESNO" in question else f"{first} indeed {rest}"
    if "?" not in question:
        return "In other words: " + question
    return "Please tell me: " + question


class FakeState:
    """Settings and counters shared by the handler threads."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.lock = threading.Lock()
        self.chat_requests = 0
        self.statuses: dict[str, int] = {}
        self.last_request = time.monotonic()

    def next_number(self) -> int:
        """The 1-based number of this chat request."""
        with self.lock:
            self.chat_requests += 1
            self.last_request = time.monotonic()
            return self.chat_requests

    def count(self, status: int) -> None:
        """Count a reply status."""
        with self.lock:
            self.statuses[str(status)] = self.statuses.get(str(status), 0) + 1


class Handler(BaseHTTPRequestHandler):
    """Serves /v1/chat/completions, /v1/models and /stats."""

    protocol_version = "HTTP/1.1"
    state: FakeState

    def setup(self):
        super().setup()
        # headers and body go out in two writes: without TCP_NODELAY, Nagle's algorithm and the client's delayed
        # ACK hold the body back ~40 ms on keep-alive connections
        self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def log_message(self, format, *args):  # noqa: A002 - quiet unless asked
        if self.state.args.verbose:
            super().log_message(format, *args)

    def send_json(self, status: int, body: dict, headers: dict | None = None) -> None:
        """One JSON reply with a Content-Length (keep-alive)."""
        data = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        for key, value in (headers or {}).items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(data)

    def do_GET(self):  # noqa: N802 - http.server's name
        if self.path.rstrip("/") == "/v1/models":
            self.send_json(200, {"object": "list", "data": [{"id": self.state.args.model, "object": "model"}]})
        elif self.path == "/stats":
            with self.state.lock:
                self.send_json(200, {"chat_requests": self.state.chat_requests, "statuses": dict(self.state.statuses)})
        else:
            self.send_json(404, {"error": {"message": f"no route {self.path}"}})

    def do_POST(self):  # noqa: N802 - http.server's name
        body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
        if self.path.rstrip("/") != "/v1/chat/completions":
            return self.send_json(404, {"error": {"message": f"no route {self.path}"}})
        number = self.state.next_number()
        status, reply, headers = self.respond(number, body)
        if self.state.args.delay_ms:
            time.sleep(self.state.args.delay_ms / 1000)
        self.state.count(status)
        self.send_json(status, reply, headers)

    def respond(self, number: int, raw: bytes) -> tuple[int, dict, dict]:
        """(status, body, headers) for chat request `number`."""
        args = self.state.args
        if args.require_key and self.headers.get("Authorization") != f"Bearer {args.require_key}":
            return 401, {"error": {"message": "missing or wrong API key", "type": "invalid_api_key"}}, {}
        if number <= args.rate_limit_first:
            return 429, {"error": {"message": "rate limited"}}, {"Retry-After": str(args.retry_after)}
        if number <= args.fail_first or (args.fail_every and number % args.fail_every == 0):
            return 500, {"error": {"message": f"injected failure of request {number}"}}, {}
        try:
            request = json.loads(raw)
            texts, images = self.read_messages(request["messages"])
        except (ValueError, KeyError, TypeError) as error:
            return 400, {"error": {"message": f"bad request: {error}", "type": "invalid_request_error"}}, {}
        prompt = "".join(texts)
        if "BAD_REQUEST" in prompt:
            return 400, {"error": {"message": "the question asked for a 400", "type": "invalid_request_error"}}, {}
        if args.max_images is not None and len(images) > args.max_images:
            return 400, {"error": {"message": f"At most {args.max_images} image(s) may be provided in one request"}}, {}
        content = {"judge": judge_reply, "paraphrase": paraphrase_reply}.get(args.mode, None)
        try:
            text = content(prompt) if content else self.describe(prompt, images)
        except ValueError as error:  # base64 or image bytes that do not decode (binascii.Error is a ValueError)
            return 400, {"error": {"message": f"bad image: {error}", "type": "invalid_request_error"}}, {}
        return 200, {"id": f"fake-{number}", "object": "chat.completion", "model": request.get("model"),
                     "choices": [{"index": 0, "message": {"role": "assistant", "content": text},
                                  "finish_reason": "stop"}]}, {}

    @staticmethod
    def read_messages(messages: list) -> tuple[list[str], list[str]]:
        """The user messages' text and the base64 payloads of their image_url data URLs."""
        texts, images = [], []
        for message in messages:
            if message.get("role") != "user":
                continue
            content = message["content"]
            for part in [{"type": "text", "text": content}] if isinstance(content, str) else content:
                if part["type"] == "text":
                    texts.append(part["text"])
                elif part["type"] == "image_url":
                    header, _, data = part["image_url"]["url"].partition(",")
                    if not header.startswith("data:image/") or not header.endswith(";base64"):
                        raise ValueError(f"image_url is not a base64 data URL: {header[:40]!r}")
                    images.append(data)
        return texts, images

    def describe(self, question: str, images: list[str]) -> str:
        """The answer mode's reply: the question, the image count, size and pixel digest (--no-decode: only the
        first 3 KiB of each image are decoded, for the size in its header)."""
        if self.state.args.no_decode:
            sizes = {image_size(base64.b64decode(data[:4096])) for data in images}
        else:
            images = [base64.b64decode(data, validate=True) for data in images]
            sizes = {image_size(data) for data in images}
        size = "x".join(map(str, sizes.pop())) if len(sizes) == 1 else "mixed" if sizes else "none"
        digest = "-" if self.state.args.no_decode or not images else \
            hashlib.md5("".join(decoded_digest(d) for d in images).encode()).hexdigest()[:8]
        return f"answer: {question} [images={len(images)} size={size} digest={digest}]"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The server's command line."""
    parser = argparse.ArgumentParser(prog="python -m lanevil_dev.fake_server",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--port", type=int, default=0, help="0: any free port (printed on the first line)")
    parser.add_argument("--mode", choices=("answer", "judge", "paraphrase"), default="answer")
    parser.add_argument("--model", default="fake-vlm")
    parser.add_argument("--delay-ms", type=float, default=0.0, help="latency added to every chat request")
    parser.add_argument("--fail-every", type=int, default=0, help="every Nth chat request gets a 500")
    parser.add_argument("--fail-first", type=int, default=0, help="the first N chat requests get a 500")
    parser.add_argument("--rate-limit-first", type=int, default=0, help="the first N chat requests get a 429")
    parser.add_argument("--retry-after", type=float, default=0.05, help="the 429s' Retry-After (seconds)")
    parser.add_argument("--max-images", type=int, default=None, help="refuse (400) more images per request")
    parser.add_argument("--require-key", default=None, help="refuse (401) requests without this Bearer key")
    parser.add_argument("--no-decode", action="store_true", help="read image sizes from headers, skip the digest")
    parser.add_argument("--idle-exit-s", type=float, default=600.0, help="exit after this long without requests")
    parser.add_argument("--verbose", action="store_true")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    """Serve until idle for --idle-exit-s."""
    args = parse_args(argv)
    state = FakeState(args)
    handler = type("BoundHandler", (Handler,), {"state": state})
    server = ThreadingHTTPServer(("127.0.0.1", args.port), handler)
    server.daemon_threads = True
    print(server.server_address[1], flush=True)

    def exit_when_idle():
        while time.monotonic() - state.last_request < args.idle_exit_s:
            time.sleep(min(1.0, args.idle_exit_s / 4))
        server.shutdown()

    threading.Thread(target=exit_when_idle, daemon=True).start()
    server.serve_forever(poll_interval=0.1)


class FakeServer:
    """A fake server subprocess for tests and benchmarks (a context manager that always kills it): `.url` is its
    API root, `.stats()` its counters."""

    def __init__(self, *options: str, idle_exit_s: float = 120.0, start_timeout_s: float = 30.0):
        command = [sys.executable, "-m", "lanevil_dev.fake_server", "--idle-exit-s", str(idle_exit_s),
                   *options]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            [str(CHECKOUT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        line = _read_line(self.process, start_timeout_s)
        if not line.strip().isdigit():
            self.kill()
            raise RuntimeError(f"fake server did not start: {line!r} {self.process.stderr.read()[-2000:]}")
        self.port = int(line)
        self.url = f"http://127.0.0.1:{self.port}/v1"

    def stats(self) -> dict:
        """GET /stats: {"chat_requests": n, "statuses": {"200": n, ...}}."""
        import httpx

        return httpx.get(f"http://127.0.0.1:{self.port}/stats", timeout=10).json()

    def kill(self) -> None:
        """Stop the process (idempotent)."""
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(timeout=10)
        for stream in (self.process.stdout, self.process.stderr):
            stream.close()

    def __enter__(self) -> "FakeServer":
        return self

    def __exit__(self, *exc) -> None:
        self.kill()


def _read_line(process: subprocess.Popen, timeout_s: float) -> str:
    """The process's first stdout line, or '' after timeout_s."""
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.append(process.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    return lines[0] if lines else ""


if __name__ == "__main__":
    main()
