"""Real-time mode is honest by default: no training after the stream unless asked, the stream's
frames/s as the system figure, a requested refinement reported apart."""

from __future__ import annotations

import json

import pytest

from slamkit.registry.schema import Mode, RunConfig

from support.commands import run_slamkit

pytestmark = pytest.mark.slow  # every test here starts the slamkit command

SMALL = ("dataset=synthetic", "dataset.num_frames=10", "dataset.width=64", "dataset.height=48", "tracker=gicp",
         "keyframe=every_n", "keyframe.tracking_every=3", "mapper=gaussian_splatting", "mapper.save_images=0",
         "output.progress=false", "output.plot=false")


def test_refinement_is_the_modes_choice_unless_given():
    assert RunConfig(mode=Mode.sequential).refinement_iterations() == 400
    assert RunConfig(mode=Mode.realtime).refinement_iterations() == 0
    assert RunConfig(mode=Mode.realtime, final_iterations=50).refinement_iterations() == 50


@pytest.mark.parametrize("final, steps", [(None, 0), (6, 6)])
def test_realtime_trains_after_the_stream_only_when_asked(tmp_path, final, steps):
    out = tmp_path / "run"
    extra = () if final is None else (f"final_iterations={final}",)
    # mapping at tracking's priority: at `idle` (the default) or `low` a busy test machine may
    # leave it no step in a stream this short
    proc = run_slamkit(*SMALL, "mode=realtime", "realtime.mapping_priority=same", *extra, f"hydra.run.dir={out}",
                       cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mapping_priority"] == "same" and metrics["mapping_cpu_wait_s"] >= 0
    assert metrics["refine_iterations"] == steps and (metrics["refine_time_s"] > 0) == (steps > 0)
    # the stream's CPU by thread: the frame loop, the mapping thread (which took the steps), the loader
    assert metrics["tracking_cpu_s"] > 0 and metrics["loading_cpu_s"] > 0
    assert metrics["mapping_cpu_s"] > 0 and metrics["mapping_iterations"] > 0
    # keyframes went to the mapper beside tracking; mapping paused while tracking was late (if it was)
    assert metrics["keyframe_handover_s"] > 0 and metrics["keyframe_handover_wait_s"] is not None
    assert metrics["mapping_yielded_s"] is not None
    # and the whole process's (every thread, the kernels' workers too) holds the frame loop's
    assert metrics["stream_cpu_s"] >= metrics["tracking_cpu_s"]
    (line,) = [line for line in proc.stdout.splitlines() if "frames/s in real time" in line]  # the summary
    assert f"{metrics['stream_fps']:.1f} frames/s in real time" in line
    assert ("refinement steps" in line) == (steps > 0)
