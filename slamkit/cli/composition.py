"""The composition matrix: every registered plugin of every role against every plugin of the
others (`slamkit.registry.combinations`), each combination run in this process on a few frames
of the built-in synthetic sequence. A combination either runs to the end with sane results (a
finite ATE; with a mapper, Gaussians and a PSNR) or is refused before its first frame in one line
that names the choices that cannot go together; a refused choice or pair is then left out and the
pairs it hid are covered by further runs. `slamkit-plugins --matrix FILE` writes the table
(docs/composition.md); tests/e2e/test_composition_matrix.py runs it and checks the table."""

from __future__ import annotations

import logging
import math
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from slamkit.errors import SlamkitError
from slamkit.registry.combinations import Factor, covered_pairs, factors, pairs, pairwise
from slamkit.registry.discovery import Registry

#: Every run's input and length: 6 frames of 64 x 48 pixels, 2 mapping steps a frame and 2 after.
BASE_OVERRIDES = ("dataset=synthetic", "dataset.num_frames=6", "dataset.width=64", "dataset.height=48",
                  "iterations_per_frame=2", "final_iterations=2", "output.progress=false", "eval.lpips=off",
                  "checkpoint.save=false")
#: Rounds of runs: the pairwise set, then the pairs that refused runs hid (one round is usual).
MAX_ROUNDS = 4


@dataclass
class Outcome:
    """One combination's run: `status` ran | refused | failed, `detail` the run's summary or its
    one-line error, `refused_by` the choices the refusal named (one choice, or a pair)."""

    combination: dict[str, str]
    status: str
    detail: str
    refused_by: tuple[tuple[str, str], ...] = field(default_factory=tuple)


def overrides(combination: dict[str, str]) -> list[str]:
    """The command-line overrides of a combination, after the matrix's BASE_OVERRIDES."""
    return [*BASE_OVERRIDES, *(f"{key}={value}" for key, value in combination.items())]


def named_choices(message: str, combination: dict[str, str]) -> tuple[tuple[str, str], ...]:
    """The combination's choices that `message` names as KEY=VALUE (a part as `mapper/PART` or
    `mapper.PART`)."""
    named = {(key.replace(".", "/"), value) for key, value in re.findall(r"([\w./]+)=([\w-]+)", message)}
    return tuple((k, v) for k, v in combination.items() if (k, v) in named)


def run_combination(combination: dict[str, str], out_dir: Path, registry: Registry) -> Outcome:
    """Run one combination into `out_dir` and judge it (module docstring)."""
    from slamkit.registry.compose import compose_run
    from slamkit.run import pipeline

    started = lambda: (out_dir / "frames.csv").exists()  # noqa: E731 - the stream began
    try:
        cfg, names = compose_run(overrides(combination), registry)
        metrics = pipeline.run(cfg, registry, names, out_dir)
    except SlamkitError as exc:
        message = str(exc)
        named = named_choices(message, combination)
        if started() or "\n" in message or not named:
            return Outcome(combination, "failed", f"{type(exc).__name__}: {message}")
        return Outcome(combination, "refused", message, named)
    except Exception as exc:  # a plugin's own failure outside the run's boundary
        return Outcome(combination, "failed", f"{type(exc).__name__}: {exc}")
    problems = sanity_problems(metrics, combination.get("mapper", "none") != "none")
    if problems:
        return Outcome(combination, "failed", "; ".join(problems))
    return Outcome(combination, "ran", pipeline.summary(metrics))


def sanity_problems(metrics: dict, maps: bool) -> list[str]:
    """What is wrong with a run's results: not completed, no finite ATE, with a mapper no
    Gaussians or no PSNR."""
    found = []
    if metrics.get("status") != "completed":
        found.append(f"status {metrics.get('status')}: {metrics.get('error')}")
    ate = metrics.get("ate_rmse_m")
    if not isinstance(ate, (int, float)) or not math.isfinite(ate):
        found.append(f"ATE {ate}")
    if maps and not metrics.get("num_gaussians"):
        found.append("0 Gaussians")
    if maps and metrics.get("psnr") is None:
        found.append("no PSNR")
    return found


def run_matrix(registry: Registry, root: Path | None = None, seed: int = 0,
               on_outcome: Callable[[int, Outcome], None] = lambda n, o: None) -> tuple[list[Factor], list[Outcome]]:
    """Every combination of the matrix run (in sub-folders of `root`, a temporary folder when
    None): the pairwise set first; a refusal leaves its choice or pair out of the rounds after
    it, which cover the pairs its run hid. Returns the factors and the outcomes in run order."""
    found = factors(registry)
    refused: set = set()
    covered: set = set()
    outcomes: list[Outcome] = []
    with tempfile.TemporaryDirectory(prefix="slamkit-matrix-") as scratch:
        base = Path(root) if root is not None else Path(scratch)
        for _ in range(MAX_ROUNDS):
            rows = pairwise(found, seed, covered=covered, refused=refused)
            if not rows:
                break
            for row in rows:
                if _makes_refused(row, refused):  # learnt earlier this round
                    continue
                outcome = run_combination(row, base / f"run{len(outcomes):03d}", registry)
                outcomes.append(outcome)
                on_outcome(len(outcomes), outcome)
                if outcome.status == "refused":
                    refused.add(outcome.refused_by[0] if len(outcome.refused_by) == 1
                                else frozenset(outcome.refused_by[:2]))
                else:  # ran, or failed (reported; its pairs are not tried again)
                    covered |= covered_pairs(row, found)
    return found, outcomes


def _makes_refused(row: dict[str, str], refused: set) -> bool:
    chosen = list(row.items())
    return any(c in refused for c in chosen) or any(
        frozenset((a, b)) in refused for i, a in enumerate(chosen) for b in chosen[i + 1:])


def markdown(found: list[Factor], outcomes: list[Outcome]) -> str:
    """docs/composition.md: the factors, every run with its outcome, and the pairs it covered."""
    ran = {p for o in outcomes if o.status == "ran" for p in covered_pairs(o.combination, found)}
    every = pairs(found)
    refused = [o for o in outcomes if o.status == "refused"]
    hidden = {p for p in every - ran
              if any(c in {r.refused_by[0] for r in refused if len(r.refused_by) == 1} for c in p)
              or frozenset(p) in {frozenset(r.refused_by[:2]) for r in refused if len(r.refused_by) > 1}}
    lines = [
        "# What composes with what",
        "",
        "Generated by `slamkit-plugins --matrix docs/composition.md` (`slamkit.cli.composition`); "
        "tests/e2e/test_composition_matrix.py runs the same matrix and fails when this table is not what it finds.",
        "Every registered plugin of every role (the example packages `slamkit-p2plane` and "
        "`slamkit-mcmc` included), every part of the 3DGS mapper, each preset and both mapping modes, "
        "combined so that every pair of choices appears in some run; each run takes "
        f"`{' '.join(BASE_OVERRIDES)}`. A run either runs to the end (a finite ATE; with a mapper, "
        "Gaussians and a PSNR) or is refused before its first frame in one line naming the choices "
        "that cannot go together; those are then left out of the runs after it. The dataset role is "
        "not a column: the matrix runs on the built-in sequence (the other datasets need recordings; "
        "their tests read the shared data).",
        "",
        "| choice | options |",
        "|---|---|",
        *(f"| `{f.key}` | {', '.join(f.values)}"
          f"{' (with mapper ' + ' / '.join(f.requires[1]) + ')' if f.requires else ''} |" for f in found),
        "",
        f"{len(outcomes)} runs: {sum(o.status == 'ran' for o in outcomes)} ran to the end, {len(refused)} refused, "
        f"{sum(o.status == 'failed' for o in outcomes)} failed. Of the {len(every)} pairs of choices one run can "
        f"make, {len(ran & every)} were in a run that ran to the end and {len(hidden)} hold a refused choice "
        "or pair.",
        "",
        "| # | " + " | ".join(f.key for f in found) + " | outcome |",
        "|---" * (len(found) + 2) + "|",
    ]
    for number, outcome in enumerate(outcomes, start=1):
        cells = [outcome.combination.get(f.key, "") for f in found]
        verdict = "ran" if outcome.status == "ran" else f"{outcome.status}: {outcome.detail}"
        lines.append(f"| {number} | " + " | ".join(cells) + f" | {verdict.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def quiet_logs() -> None:
    """The matrix's runs log at WARNING and above only (their INFO lines go nowhere useful)."""
    logging.getLogger("slamkit").setLevel(logging.WARNING)
