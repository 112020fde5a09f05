"""One file over HTTP(S), resumable: the bytes go to `FILE.part` beside the destination, a cut
transfer is resumed from where it stopped (an HTTP Range request; a server that ignores it
sends the whole file again), the size is checked against the server's (Content-Length /
Content-Range), and the finished file is renamed into place, so a file under its own name is
always complete. Its SHA-256 is computed and, when one is expected, compared."""

from __future__ import annotations

import hashlib
import http.client
import io
import re
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from slamkit.errors import DataError, OutputError, SlamkitError
from slamkit.progress import Progress

#: Bytes read and written at a time.
CHUNK = 1 << 20
#: The least a RangeReader asks for at a time: a zip member's header and its name in one request.
READ_AHEAD = 64 << 10
USER_AGENT = "slamkit-data"


class DownloadError(SlamkitError):
    """The transfer failed (network, server): an environment failure, exit status 1. The message
    says how far it got and that running the same command again resumes it."""

    exit_status = 1


@dataclass(frozen=True)
class Downloaded:
    """A complete file: its path, size in bytes and SHA-256 (hex)."""

    path: Path
    size: int
    sha256: str


class _Cut(Exception):
    """A transfer that stopped early (kept in FILE.part), worth another try."""


def part_path(dest: Path) -> Path:
    """Where the bytes of `dest` accumulate until it is complete."""
    return dest.with_name(dest.name + ".part")


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            digest.update(block)
    return digest.hexdigest()


def download(url: str, dest: Path, *, expected_sha256: str | None = None, retries: int = 3,
             timeout: float = 60.0, progress: bool = True, backoff: float = 1.0) -> Downloaded:
    """Fetch `url` into `dest` (see the module docstring); a `dest` already there is taken as
    complete. Up to `retries` more tries after a cut, each resuming, `backoff` * 2^k seconds
    apart. DownloadError (exit 1) when the tries run out, FILE.part kept; DataError for an HTTP
    error the server means (404...) or a SHA-256 other than `expected_sha256`, in which case the
    file is renamed FILE.corrupt."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = part_path(dest)
    if not dest.is_file():
        for attempt in range(retries + 1):
            try:
                _fetch(url, part, timeout, progress)
                break
            except _Cut as cut:
                if attempt == retries:
                    raise DownloadError(f"{url}: {cut}; {part} kept, run the same command again to resume") from None
                time.sleep(backoff * 2**attempt)
        part.replace(dest)
    digest = sha256_of(dest)
    if expected_sha256 is not None and digest != expected_sha256.lower():
        corrupt = dest.with_name(dest.name + ".corrupt")
        dest.replace(corrupt)
        raise DataError(f"{url}: SHA-256 {digest} is not the expected {expected_sha256.lower()}; "
                        f"the file is kept as {corrupt}")
    return Downloaded(dest, dest.stat().st_size, digest)


def remote_size(url: str, timeout: float = 30.0) -> int | None:
    """The size in bytes the server gives for `url` (Content-Length of a HEAD request), or None
    when it gives none or cannot be reached (the download itself then says what went wrong)."""
    request = urllib.request.Request(url, method="HEAD", headers={"User-Agent": USER_AGENT})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            length = response.headers.get("Content-Length")
    except (urllib.error.URLError, OSError, http.client.HTTPException):
        return None
    return int(length) if length and length.isdigit() else None


class RangeReader(io.RawIOBase):
    """The file at `url`, `size` bytes long, read where it is by HTTP Range requests: a seekable
    binary file for zipfile, so that single members of a large zip can be read without
    downloading it whole. `str()` is the URL. A read outside the last block received asks for
    the bytes it needs, READ_AHEAD at least; a cut or failed request is tried `retries` more
    times, then a DownloadError (exit 1); a server that answers a range with anything but those
    bytes is a DownloadError too. `fetched`: the bytes received so far."""

    def __init__(self, url: str, size: int, *, timeout: float = 60.0, retries: int = 3):
        super().__init__()
        self.url, self.size, self.timeout, self.retries = url, size, timeout, retries
        self.pos = self.fetched = self._block_start = 0
        self._block = b""

    def __str__(self) -> str:
        return self.url

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.size}[whence]
        if base + offset < 0:
            raise ValueError(f"negative seek position {base + offset}")
        self.pos = base + offset
        return self.pos

    def readinto(self, buffer) -> int:
        want = min(len(buffer), self.size - self.pos)
        if want <= 0:
            return 0
        start = self.pos - self._block_start
        if not (0 <= start and start + want <= len(self._block)):  # not all in the last block: ask for it
            last = min(self.size, self.pos + max(want, READ_AHEAD)) - 1
            for attempt in range(self.retries + 1):
                try:
                    self._block, self._block_start = self._range(self.pos, last), self.pos
                    break
                except _Cut as cut:
                    if attempt == self.retries:
                        raise DownloadError(f"{self.url}: {cut}; run the same command again") from None
                    time.sleep(2**attempt)
            self.fetched += len(self._block)
            start = 0
        buffer[:want] = self._block[start:start + want]
        self.pos += want
        return want

    def _range(self, first: int, last: int) -> bytes:
        headers = {"User-Agent": USER_AGENT, "Range": f"bytes={first}-{last}"}
        try:
            with urllib.request.urlopen(urllib.request.Request(self.url, headers=headers),
                                        timeout=self.timeout) as response:
                if response.status != 206 or _content_range(response.headers.get("Content-Range", ""))[0] != first:
                    raise DownloadError(f"{self.url}: the server did not answer the range request for bytes "
                                        f"{first}-{last} with them (HTTP {response.status})")
                data = response.read(last - first + 1)
        except urllib.error.HTTPError as exc:
            if exc.code >= 500 or exc.code == 429:
                raise _Cut(f"HTTP {exc.code} {exc.reason}") from None
            raise DataError(f"{self.url}: HTTP {exc.code} {exc.reason}") from None
        except (urllib.error.URLError, OSError, http.client.HTTPException) as exc:
            raise _Cut(f"no connection ({_reason(exc)})") from None
        if len(data) != last - first + 1:
            raise _Cut(f"bytes {first}-{last} stopped after {len(data)}")
        return data


def ranged(url: str, timeout: float = 30.0) -> int | None:
    """The size in bytes of the file at `url` when its server answers Range requests (a probe
    for its first byte comes back 206 with the total), else None: then it can only be
    downloaded whole."""
    request = urllib.request.Request(url, headers={"User-Agent": USER_AGENT, "Range": "bytes=0-0"})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            if response.status != 206:
                return None
            return _content_range(response.headers.get("Content-Range", ""))[1]
    except (urllib.error.URLError, OSError, http.client.HTTPException, _Cut):
        return None


def _fetch(url: str, part: Path, timeout: float, progress: bool) -> None:
    """One try: append to `part` from its current size to the end. _Cut when it stops early."""
    have = part.stat().st_size if part.is_file() else 0
    headers = {"User-Agent": USER_AGENT}
    if have:
        headers["Range"] = f"bytes={have}-"
    try:
        response = urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout)
    except urllib.error.HTTPError as exc:
        if exc.code == 416 and have:  # nothing left to send: complete, or a part longer than the file
            total = _range_total(exc.headers.get("Content-Range", ""))
            if total == have:
                return
            part.unlink()
            raise _Cut(f"{have} bytes kept but the file has {total}; starting again") from None
        if exc.code >= 500 or exc.code == 429:
            raise _Cut(f"HTTP {exc.code} {exc.reason}") from None
        raise DataError(f"{url}: HTTP {exc.code} {exc.reason}") from None
    except (urllib.error.URLError, OSError, http.client.HTTPException) as exc:
        raise _Cut(f"no connection ({_reason(exc)})") from None
    with response:
        if response.status == 206:
            start, total = _content_range(response.headers.get("Content-Range", ""))
            if start != have:
                part.unlink()
                raise _Cut(f"the server resumed at byte {start}, not {have}; starting again")
            mode = "ab"
        else:  # the whole file (the server ignores ranges, or nothing was kept)
            have, mode = 0, "wb"
            length = response.headers.get("Content-Length")
            total = int(length) if length and length.isdigit() else None
        with open(part, mode) as f, Progress(f"download {Path(url).name}", _mb(total), "MB", enabled=progress,
                                             initial=_mb(have), units="MB") as bar:
            while True:
                try:
                    chunk = response.read(CHUNK)
                except (OSError, http.client.HTTPException) as exc:
                    shown = total if total is not None else "?"
                    raise _Cut(f"stopped at {have} of {shown} bytes ({_reason(exc)})") from None
                if not chunk:
                    break
                try:
                    f.write(chunk)
                except OSError as exc:  # a full disk: the bytes so far stay in the part file
                    raise OutputError(f"{part}: cannot write ({_reason(exc)}); {have} bytes kept, run the same "
                                      f"command again to resume") from None
                bar.update(_mb(have + len(chunk)) - _mb(have))
                have += len(chunk)
    if total is not None and have != total:
        raise _Cut(f"stopped at {have} of {total} bytes")


def _mb(n: int | None) -> int | None:
    """Whole megabytes (10^6 bytes) in `n` bytes: the download's progress unit."""
    return None if n is None else n // 1_000_000


def _content_range(value: str) -> tuple[int, int | None]:
    """(first byte, total or None) of a Content-Range `bytes a-b/total`."""
    m = re.fullmatch(r"\s*bytes\s+(\d+)-\d+/(\d+|\*)\s*", value)
    if not m:
        raise _Cut(f"unreadable Content-Range {value!r}")
    return int(m.group(1)), None if m.group(2) == "*" else int(m.group(2))


def _range_total(value: str) -> int | None:
    m = re.fullmatch(r"\s*bytes\s+\*/(\d+)\s*", value)
    return int(m.group(1)) if m else None


def _reason(exc: BaseException) -> str:
    reason = getattr(exc, "reason", None) or exc
    return (str(reason).strip().splitlines() or [type(exc).__name__])[0] or type(exc).__name__
