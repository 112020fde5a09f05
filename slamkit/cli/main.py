"""The `slamkit` command: a Hydra app over the plugin registry.

`slamkit` alone runs the default pipeline on the built-in synthetic sequence; any config value
is an override (`slamkit dataset=tum dataset.path=... tracker=kiss_icp`), `-m` runs sweeps.
`slamkit resume=RUN_DIR [overrides]` continues a run from its checkpoint; `slamkit mode=localize
map=RUN_DIR dataset=...` tracks a sequence in a saved map. Overrides are read with Hydra's own
parser; a key spelled as before 0.3 fails with one line naming the new one. Exit status
(docs/architecture.md, "Run outputs"): 0 completed; 2 a user error, one line (SLAMKIT_DEBUG=1 for
the traceback); 1 an environment failure; 3 tracking failed; 128 + N stopped by signal N, from
start-up on: heavy modules (torch, Hydra, the plugins) are imported only once signals are handled.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import warnings
from pathlib import Path

from slamkit.cli import streams
from slamkit.errors import SlamkitError
from slamkit.run.lifecycle import StopSignals, exit_status, pause_point

log = logging.getLogger("slamkit")

#: Exit status of a run whose tracking failed (an interrupted run's: `exit_status`, 128 + the signal).
TRACKING_FAILED = 3


def _fail(message: str, status: int = 2) -> None:
    print(f"slamkit: error: {message}", file=sys.stderr)
    sys.exit(status)


def _score(run_cfg, metrics: dict) -> float | None:
    """The run's score for an optimising sweeper (`objective.*`): metrics[objective.metric] when
    it is a finite number, else objective.failed_value (e.g. no ground truth for the ATE)."""
    value = metrics.get(run_cfg.objective.metric)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return run_cfg.objective.failed_value


class Command:
    """One invocation of `slamkit`: the plugin registry it discovered, the signal handling of its
    start-up and of the run in progress, and the sweep's runs whose tracking failed. Hydra calls
    `task` once per run (in this process, or pickled into a launcher's worker process, where the
    registry is discovered again and the signals are that process's)."""

    def __init__(self) -> None:
        self.registry = None
        self.startup = StopSignals()  # from the command's start to the run's
        self.stop: StopSignals | None = None  # the current run's, for the message of an interruption
        self.failed_runs: list[str] = []

    def __getstate__(self) -> dict:  # a launcher's worker discovers its own plugins and handles its own signals
        return {"failed_runs": []}

    def __setstate__(self, state: dict) -> None:
        self.__init__()

    def main(self, argv: list[str]) -> None:
        """Run the command with `argv` (its arguments); exits with the run's status."""
        streams.guard()  # a closed, broken or full stdout / stderr never stops the command
        try:
            with self.startup.installed():
                self._start(argv)
        except KeyboardInterrupt as exc:
            phase = self.stop.phase.value if self.stop else "startup"
            print(f"slamkit: interrupted ({str(exc) or 'SIGINT'}) during {phase.replace('startup', 'start-up')}",
                  file=sys.stderr)
            sys.exit(exit_status(str(exc) or "SIGINT"))
        finally:
            # the run folders this command claimed (slamkit.cli.hydra_hooks), however it ends; the
            # module is imported only once a folder was claimed (it imports the heavy run schema)
            ownership = sys.modules.get("slamkit.run.ownership")
            if ownership is not None:
                ownership.release_all()
        if self.failed_runs:
            _fail(f"tracking failed in {len(self.failed_runs)} of the sweep's runs: {', '.join(self.failed_runs)}",
                  TRACKING_FAILED)

    def _start(self, argv: list[str]) -> None:
        pause_point("startup")
        from slamkit.cli.hydra_app import composition, run_hydra
        from slamkit.registry.compose import register
        from slamkit.registry.discovery import discover

        _escape_unencodable_output()
        flags = [a for a in argv if a.startswith("-")]
        # --help, --cfg job, --info ...: Hydra's own options (some take a value), no run to check
        run = all(f in ("-m", "--multirun") for f in flags)
        # hydra/launcher=ray: a local Ray cluster writes no token under the home folder
        # (conf/hydra/launcher/ray.yaml); a cluster that uses tokens needs RAY_AUTH_MODE=token.
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")
        # conf/hydra/launcher/ray.yaml takes the place of the Ray launcher's own config of that name on
        # purpose; Hydra 1.3 still validates it against that schema, and warns that this is deprecated.
        warnings.filterwarnings("ignore", message=r"(?s).*is validated against ConfigStore schema with the same name")
        self.registry = discover()
        register(self.registry)
        self.startup.hold()  # Hydra and OmegaConf cut by a KeyboardInterrupt report another error: hold it
        started = None  # the run or the sweep, composed once and checked
        try:
            if run:
                started = composition(self.task, [a for a in argv if not a.startswith("-")], self.registry,
                                      multirun=bool(flags))
        except SlamkitError as exc:
            if os.environ.get("SLAMKIT_DEBUG"):
                raise
            _fail(str(exc), exc.exit_status)
        try:
            if started is not None:
                started.run()
            else:  # --help, --cfg, --info ...: Hydra's own command line
                run_hydra(self.task, argv)
        finally:
            self.startup.release()  # --help, --cfg: no task

    def task(self, cfg) -> float | None:
        """One run; returns its score (`_score`) for sweepers that optimise it."""
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode
        from omegaconf import OmegaConf

        from slamkit.registry.compose import chosen_plugins, parse_overrides
        from slamkit.registry.discovery import default_registry
        from slamkit.registry.schema import Mode, validate_config
        from slamkit.run import localization, pipeline
        from slamkit.run.state import FAILED
        from slamkit.run.state import INTERRUPTED as STOPPED

        self.startup.release()  # Hydra has composed the config: a signal noted meanwhile stops the command here
        registry = self.registry or default_registry()  # a launcher's worker process
        hydra_cfg = HydraConfig.get()
        names = chosen_plugins(hydra_cfg.runtime.choices)
        out_dir = Path(hydra_cfg.runtime.output_dir)
        failed_value = OmegaConf.select(cfg, "objective.failed_value", default=None)  # also for a config that fails
        self.stop = StopSignals()
        try:
            run_cfg = validate_config(cfg, parse_overrides(list(hydra_cfg.overrides.task)))
            program = localization if run_cfg.mode is Mode.localize else pipeline
            metrics = program.run(run_cfg, registry, names, out_dir, self.stop)
        except SlamkitError as exc:
            log.error("%s", exc, extra={streams.SAID: True})  # the log file's; the terminal gets the line below
            if os.environ.get("SLAMKIT_DEBUG"):
                raise
            if failed_value is None:
                _fail(str(exc), exc.exit_status)
            print(f"slamkit: error: {exc}", file=sys.stderr)  # a search goes on with the next trial
            print(f"slamkit: the run failed; its score is objective.failed_value = {failed_value}")
            return float(failed_value)
        print(f"slamkit: {program.summary(metrics)}")
        print(f"slamkit: outputs in {out_dir}")
        if metrics["status"] == STOPPED:  # interrupted (Ctrl-C, SIGTERM, ...): stop, also a search
            sys.exit(exit_status(self.stop.signal))
        if metrics["status"] == FAILED:  # tracking failed: a sweep goes on, and exits with it at the end
            if hydra_cfg.mode == RunMode.MULTIRUN:
                self.failed_runs.append(str(out_dir))
            else:
                sys.exit(TRACKING_FAILED)
        return _score(run_cfg, metrics)


def _escape_unencodable_output() -> None:
    """Text the terminal's encoding cannot hold (a file name that is not UTF-8, kept by Python as
    surrogate escapes) is printed and logged backslash-escaped instead of raising a logging error
    (the log file's handler does the same: conf/config.yaml)."""
    for stream in (sys.stdout, sys.stderr):
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


def main() -> None:
    """The `slamkit` command (see the module docstring)."""
    Command().main(sys.argv[1:])


if __name__ == "__main__":
    main()
