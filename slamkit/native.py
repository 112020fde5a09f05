"""Compiled helpers built on first use: one C++17 source file behind a C ABI (plus the shared
headers of slamkit/csrc and the headers beside it), loaded with ctypes.

A library is compiled with the system C++ compiler (`$CXX`, else `c++`) and cached under
`$SLAMKIT_CACHE/extensions/` (else `~/.cache/slamkit/extensions/`), never in the source tree, by a
hash of the source and its headers, the flags, the compiler version and (for -march=native) the
CPU. It is built under a temporary name, recorded (size and SHA-256, `slamkit.cache.record`) and
renamed into place; a cached library is loaded only when it matches its record, else rebuilt
with one line on stderr (a truncated library mapped into the process kills it with SIGBUS).
Without a compiler, or if the build fails, `NativeLibrary.get()` returns None and `error` says why
in one line; the caller falls back to its numpy / torch path. ctypes rather than
`torch.utils.cpp_extension`: the same code serves numpy callers and builds much faster
(docs/cpu_rasterizer.md, "Build: a plain C++ library loaded with ctypes").
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

from slamkit.cache import cache_dir, damage, record

#: Flags every library is built with. -ffp-contract=off and no -ffast-math: results must round as
#: the numpy / torch reference does. -fno-math-errno only lets sqrt be inlined.
BASE_FLAGS = ("-O3", "-std=c++17", "-shared", "-fPIC", "-pthread", "-ffp-contract=off", "-fno-math-errno",
              "-DNDEBUG")


#: Headers every library may include (`#include "slk_thread_pool.h"`): on the include path and in
#: the build hash, so a changed header rebuilds the libraries that use it.
INCLUDE_DIR = Path(__file__).resolve().parent / "csrc"


def available_threads() -> int:
    """$OMP_NUM_THREADS when set (as torch and OpenMP libraries read it), else the CPUs this
    process may use."""
    try:
        return max(1, int(os.environ["OMP_NUM_THREADS"]))
    except (KeyError, ValueError):
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def cache_root() -> Path:
    return cache_dir("extensions")


def _cpu_id() -> str:
    """The CPU model and feature flags (what -march=native depends on)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
        keys = ("model name", "flags", "Features", "CPU part")
        keep = [ln for ln in text.splitlines() if ln.split(":")[0].strip() in keys]
        return "\n".join(sorted(set(keep)))
    except OSError:
        return platform.processor() or platform.machine()


class NativeLibrary:
    """One C++ source compiled and loaded on the first `get()` (thread-safe, tried once).

    source: the .cpp file. label: what to call it in messages. abi_version: the value its
    `slk_abi_version()` must return (a stale cached build is refused). declare: sets argtypes /
    restype on the loaded CDLL. native: also try -march=native (keyed by the CPU model, so a
    cache copied to another CPU is rebuilt, not run with instructions it lacks)."""

    def __init__(self, source: Path, label: str, abi_version: int, declare: Callable[[ctypes.CDLL], None],
                 native: bool = True, flags: tuple[str, ...] = BASE_FLAGS):
        self.source, self.label, self.abi_version = Path(source), label, abi_version
        self.declare, self.native, self.flags = declare, native, tuple(flags)
        self.lib = None
        self.error: str | None = None
        self.path: Path | None = None  # the loaded library
        self.built_flags: tuple[str, ...] = ()  # the compiler flags it was built with
        self._lock = threading.Lock()
        self._tried = False

    def get(self):
        """The loaded library, or None (then `error` says why)."""
        with self._lock:
            if not self._tried:
                self._tried = True
                try:
                    self.lib = self._load()
                except Exception as exc:  # reported in one line; the caller falls back
                    text = str(exc) if isinstance(exc, RuntimeError) else f"{type(exc).__name__}: {exc}"
                    self.error = (text.strip().splitlines() or [type(exc).__name__])[0]
        return self.lib

    def _load(self):
        compiler = os.environ.get("CXX", "c++")
        exe = shutil.which(compiler)
        if exe is None:
            raise RuntimeError(f"no C++ compiler found ({compiler!r} is not on PATH; set CXX)")
        version = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60).stdout
        error = None
        # -march=native first (where asked); a compiler that rejects it gets the portable build
        for native in ([True, False] if self.native else [False]):
            flags = list(self.flags) + (["-march=native"] if native else [])
            digest = hashlib.sha256()
            headers = [h.read_bytes() for h in self.headers()]
            for part in (self.source.read_bytes(), *headers, " ".join(flags).encode(), version.encode(),
                         platform.machine().encode()):
                digest.update(part)
            if native:
                digest.update(_cpu_id().encode())
            path = cache_root() / f"slamkit_{self.source.stem}_{digest.hexdigest()[:16]}.so"
            why = damage(path)
            if why is not None:
                if why != "missing":
                    print(f"slamkit: the cached build of the {self.label} ({path}) is damaged ({why}); rebuilding it",
                          file=sys.stderr, flush=True)
                try:
                    self._compile(exe, flags, path, compiler)
                except RuntimeError as exc:
                    if why != "missing":
                        exc = RuntimeError(f"the cached build of the {self.label} is damaged ({why}) and rebuilding it "
                                           f"failed: {exc}")
                    error = error or exc
                    continue
            lib = self._open(path)
            self.path, self.built_flags = path, tuple(flags)
            return lib
        raise error

    def headers(self) -> list[Path]:
        """The headers the build may include, in the build hash: the shared ones (INCLUDE_DIR) and
        those beside the source (its own parts, `#include "name.h"`)."""
        return sorted(INCLUDE_DIR.glob("*.h")) + sorted(self.source.parent.glob("*.h"))

    def _compile(self, exe: str, flags: list[str], path: Path, compiler: str) -> None:
        """Build into a temporary file beside `path`, record it, then rename it into place."""
        path.parent.mkdir(parents=True, exist_ok=True)
        print(f"slamkit: compiling the {self.label} (first use, a few seconds)...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        fd, tmp = tempfile.mkstemp(suffix=".so.tmp", dir=path.parent)
        os.close(fd)
        try:
            proc = subprocess.run([exe, *flags, f"-I{INCLUDE_DIR}", str(self.source), "-o", tmp],
                                  capture_output=True, text=True, timeout=600)
            if proc.returncode != 0:
                lines = proc.stderr.strip().splitlines()
                first = next((ln for ln in lines if "error" in ln), lines[0] if lines else "")
                why = first.strip()[:200] or f"the compiler ({compiler}) exited with status {proc.returncode} and " \
                                             "printed nothing"
                raise RuntimeError(f"compiling {self.source.name} failed: {why}")
            record(path, content=Path(tmp))  # a concurrent reader of the old file then rebuilds: never a wrong load
            os.replace(tmp, path)  # atomic: concurrent builders each install a complete file
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        print(f"slamkit: {self.label} compiled in {time.perf_counter() - t0:.1f} s ({path})", file=sys.stderr,
              flush=True)

    def _open(self, path: Path):
        lib = ctypes.CDLL(str(path))
        lib.slk_abi_version.restype = ctypes.c_int
        if lib.slk_abi_version() != self.abi_version:
            raise RuntimeError(f"{path} has ABI {lib.slk_abi_version()}, expected {self.abi_version}")
        self.declare(lib)
        return lib
