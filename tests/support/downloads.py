"""What the `slamkit-data` tests share: a local HTTP server (files by URL path, Range requests
(206 / 416), HEAD (the size), transfers cut on demand), `slamkit-data download` run in this
process, and its one error line."""

from __future__ import annotations

import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from slamkit.cli import data as cli


def download(capsys, *args: str) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of `slamkit-data download ARGS --no-progress`, in this process."""
    status = cli.main(["download", *args, "--no-progress"])
    out, err = capsys.readouterr()
    return status, out, err


def one_line(err: str) -> str:
    """The only line of `err` (asserted to be one)."""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


class Server:
    """Files by URL path; `cuts[path] = (times, after)`: the next `times` responses for `path`
    announce the full length but stop after `after` body bytes and close the connection.
    `requests`: (path, Range header or None, or "HEAD") of every request; `sent`: body bytes
    sent, by path. `ranges = False` serves the whole file whatever the Range header asks, as a
    server without range support does. Serves on 127.0.0.1 (a thread) from `url` until `close()`."""

    def __init__(self):
        self.files: dict[str, bytes] = {}
        self.cuts: dict[str, tuple[int, int]] = {}
        self.requests: list[tuple[str, str | None]] = []
        self.sent: dict[str, int] = {}
        self.ranges = True
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # quiet
                pass

            def do_HEAD(self):
                server.requests.append((self.path, "HEAD"))
                data = server.files.get(self.path)
                if data is None:
                    self.send_error(404, "Not Found")
                    return
                self.send_response(200)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()

            def do_GET(self):
                rng = self.headers.get("Range")
                server.requests.append((self.path, rng))
                data = server.files.get(self.path)
                if data is None:
                    self.send_error(404, "Not Found")
                    return
                rng = rng if server.ranges else None
                first, _, last = rng.split("=")[1].partition("-") if rng else ("0", "", "")
                start = int(first)
                end = min(int(last), len(data) - 1) if last else len(data) - 1
                if start >= len(data):
                    self.send_response(416)
                    self.send_header("Content-Range", f"bytes */{len(data)}")
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                body = data[start:end + 1]
                self.send_response(206 if rng else 200)
                if rng:
                    self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                times, after = server.cuts.get(self.path, (0, 0))
                if times:
                    server.cuts[self.path] = (times - 1, after)
                    self.wfile.write(body[:after])
                    self.wfile.flush()
                    server.sent[self.path] = server.sent.get(self.path, 0) + min(after, len(body))
                    self.close_connection = True
                    return
                self.wfile.write(body)
                server.sent[self.path] = server.sent.get(self.path, 0) + len(body)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()
