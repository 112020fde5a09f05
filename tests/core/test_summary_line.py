"""The summary line a run prints and logs (slamkit.run.metrics.summary) says what the run did:
frames, ATE, both frames/s named (stream and whole run), keyframes, lost frames, loops closed,
mapping steps, refinement, PSNR and the run folder's size; trajectory.png's title (`headline`)
names the rate it shows."""

from __future__ import annotations

from slamkit.run.metrics import headline, summary


def metrics(**changes) -> dict:
    """A finished run's figures as metrics.json holds them (plus the summary's run_folder_mb)."""
    m = {"num_frames": 150, "num_keyframes": 31, "lost_frames": 1, "ate_rmse_m": 0.049, "fps": 6.25,
         "stream_fps": 8.5, "mode": "sequential", "mapping_iterations": 1500, "mapping_priority": None,
         "mapping_cpu_wait_s": None, "refine_iterations": 400, "refine_time_s": 12.3, "psnr": 21.456,
         "loops_accepted": 2, "run_folder_mb": 3.21, "status": "completed", "completed": True}
    m.update(changes)
    return m


def test_summary_names_every_figure_of_a_sequential_run():
    line = summary(metrics())
    for part in ("150 frames", "ATE RMSE 4.90 cm", "6.2 frames/s (whole run)", "8.5 frames/s (stream)",
                 "31 keyframes", "1 lost", "2 loops closed", "1500 mapping steps in the stream",
                 "400 refinement steps after it (12.3 s)", "PSNR 21.46 dB", "run folder 3.2 MB"):
        assert part in line, (part, line)
    # the rate a sequential run is judged by comes first, and is the one the plot's title shows
    assert line.index("(whole run)") < line.index("(stream)")
    assert headline(metrics()).endswith("6.2 frames/s (whole run)")
    # trajectory.png's title, drawn when the stream ends: the stream's rate, named
    assert headline(metrics(), stream_rate=True).endswith("8.5 frames/s (stream)")


def test_summary_of_a_realtime_run_leads_with_the_stream_rate():
    m = metrics(mode="realtime", mapping_iterations=7, mapping_priority="low", mapping_cpu_wait_s=4.04,
                refine_iterations=0, loops_accepted=None, run_folder_mb=None, psnr=None)
    line = summary(m)
    assert "8.5 frames/s in real time (stream), 6.2 frames/s (whole run)" in line
    assert "7 mapping steps in the stream (low priority, 4.0 s waiting for a CPU)" in line
    for absent in ("loops closed", "refinement", "PSNR", "run folder"):  # loop closure off, not mapped, unknown
        assert absent not in line, (absent, line)
    assert headline(m).endswith("8.5 frames/s in real time (stream)")


def test_summary_says_why_a_run_has_no_result():
    tracking_only = metrics(mapping_iterations=0, refine_iterations=0, psnr=None)
    assert "mapping steps" not in summary(tracking_only)
    failed = summary(metrics(ate_rmse_m=None, tracking_failure="61 % of frames lost", status="failed",
                             completed=False, error="tracking failed"))
    assert "ATE RMSE not reported" in failed and failed.endswith("(failed: tracking failed)")
    interrupted = summary(metrics(status="interrupted", completed=False, phase="refine"))
    assert interrupted.endswith("(incomplete: interrupted during refine)")


def test_starved_real_time_mapping_is_warned_with_the_figures_and_the_ways_out():
    from types import SimpleNamespace

    from slamkit.registry.schema import Mode
    from slamkit.run.pipeline import starved_mapping

    cfg = SimpleNamespace(mode=Mode.realtime, iterations_per_frame=10)
    starved = metrics(mode="realtime", num_frames=40, mapping_iterations=1, refine_iterations=0, psnr=8.85)
    line = starved_mapping(cfg, "gaussian_splatting", starved)
    assert "1 mapping steps for 40 frames" in line and "10 a frame (400)" in line and "PSNR 8.85 dB" in line
    assert "mode=sequential" in line and "final_iterations=400" in line
    fed = metrics(mode="realtime", num_frames=40, mapping_iterations=30, refine_iterations=10)
    assert starved_mapping(cfg, "gaussian_splatting", fed) is None  # a tenth of the method's steps
    assert starved_mapping(cfg, "none", starved) is None  # tracking only: nothing to train
    assert starved_mapping(SimpleNamespace(mode=Mode.sequential, iterations_per_frame=10), "gaussian_splatting",
                           starved) is None
