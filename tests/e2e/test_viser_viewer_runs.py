"""`viewer=viser` through the command: a Replica run that exits after its last frame, and
`viewer.keep_serving` serving the page after the run until SIGTERM. The viewer itself:
tests/plugins/test_viser_viewer.py."""

from __future__ import annotations

import json
import time
import urllib.request
from pathlib import Path

import pytest

from support.commands import run_slamkit

viser = pytest.importorskip("viser", reason="viser is the optional extra `web` (in `test`)")


@pytest.mark.slow
def test_a_replica_run_with_viser_exits_after_its_last_frame(tmp_path, replica_path):
    out = tmp_path / "run"
    proc = run_slamkit("dataset=replica", f"dataset.path={replica_path}", "dataset.max_frames=6",
                       "mapper=gaussian_splatting", "iterations_per_frame=2", "final_iterations=0",
                       "mapper.eval_every=100", "mapper.save_images=0", "output.progress=false", "viewer=viser",
                       "viewer.port=0", "viewer.splat_keyframes=1", "viewer.render_every=2", f"hydra.run.dir={out}",
                       cwd=tmp_path, env_extra={"OMP_NUM_THREADS": "1"}, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "slamkit: the live map is at http://127.0.0.1:" in proc.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    stats = json.loads((out / "viser.json").read_text())
    assert metrics["completed"] and stats["splats_sent"] == metrics["num_gaussians"] > 0  # the final map
    assert stats["updates"]["render"]["count"] >= 1 and stats["updates"]["image"]["count"] >= 1


@pytest.mark.slow
def test_keep_serving_serves_the_page_after_the_run_until_sigterm(tmp_path):
    import os
    import re
    import signal
    import subprocess
    import sys

    out = tmp_path / "run"
    cmd = [str(Path(sys.executable).with_name("slamkit")), "dataset=synthetic", "dataset.num_frames=4",
           "dataset.width=64", "dataset.height=48", "mapper=none", "output.progress=false", "output.plot=false",
           "viewer=viser", "viewer.port=0", "viewer.keep_serving=true", f"hydra.run.dir={out}"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            env=dict(os.environ, OMP_NUM_THREADS="1"))
    try:
        url = None
        for line in proc.stdout:  # the address, then the line saying the run is done
            found = re.search(r"the map is served at (http://\S+);", line)
            if found:
                url = found.group(1)
                break
        assert url is not None and json.loads((out / "metrics.json").read_text())["completed"]
        assert "<script" in urllib.request.urlopen(url, timeout=10).read().decode()  # still up after the run
        time.sleep(1.0)
        assert proc.poll() is None  # and still waiting
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
