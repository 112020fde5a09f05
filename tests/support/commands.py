"""The console scripts run as a test would run them: `run_slamkit` to completion, `Slamkit` as a
process whose stderr is read line by line (to signal it at a point it says it has reached),
`slamkit_in_process` through the entry point in this process; and TINY, a short run with every
phase and output."""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from slamkit.cli import main as slamkit_cli

#: A short run with every phase and output: 6 synthetic frames mapped by 3DGS, refined, evaluated,
#: its checkpoint written.
TINY = {"dataset": "synthetic", "dataset.num_frames": 6, "dataset.width": 64, "dataset.height": 48,
        "keyframe": "every_n", "keyframe.tracking_every": 3, "mapper": "gaussian_splatting", "final_iterations": 4,
        "mapper.save_images": 2, "iterations_per_frame": 2, "output.progress": "false",
        "checkpoint.save": "true"}


def tiny(**changes) -> list[str]:
    """TINY's overrides with `changes` (keys with "__" for "."), e.g. tiny(mode="realtime")."""
    values = dict(TINY, **{k.replace("__", "."): v for k, v in changes.items()})
    return [f"{k}={v}" for k, v in values.items()]


def run_slamkit(*args: str, cwd: Path, env_extra: dict[str, str] | None = None, timeout: float = 600):
    """Run the `slamkit` console script; returns the CompletedProcess (text)."""
    env = dict(os.environ, **(env_extra or {}))
    exe = Path(sys.executable).with_name("slamkit")
    return subprocess.run([str(exe), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


class Slamkit:
    """A `slamkit` process whose stderr is read line by line (to see where it has paused)."""

    def __init__(self, *args: str, cwd: Path, pause_at: str | None = None, env: dict | None = None):
        env = dict(os.environ, **(env or {}))
        if pause_at:
            env["SLAMKIT_PAUSE_AT"] = pause_at
        exe = Path(sys.executable).with_name("slamkit")
        self.proc = subprocess.Popen([str(exe), *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.stderr: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.stderr.append(line)
            self.lines.put(line)
        self.lines.put(None)

    def wait_for(self, text: str, timeout: float = 300) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=1)
            except queue.Empty:
                continue
            if line is None:
                pytest.fail(f"slamkit ended before {text!r}: {''.join(self.stderr)[-3000:]}")
            if text in line:
                return
        self.proc.kill()
        pytest.fail(f"slamkit never said {text!r}")

    def send(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def finish(self, timeout: float = 300) -> tuple[int, str, str]:
        try:
            stdout = self.proc.stdout.read()
            self.proc.wait(timeout=timeout)
        finally:
            self.proc.kill()
        self.reader.join(timeout=10)
        return self.proc.returncode, stdout, "".join(self.stderr)


def slamkit_in_process(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """The `slamkit` entry point in this process: (exit status, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["slamkit", *args])
    with pytest.raises(SystemExit) as exit_:
        slamkit_cli.main()
        sys.exit(0)
    said = capsys.readouterr()
    return exit_.value.code, said.out, said.err
