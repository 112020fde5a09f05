"""The real RGB-D data the tests read in place (slamkit.downloads.excerpts.find_test_data), the
first of: $SLAMKIT_DATA; the developers' shared folder beside the repository; the folder
`slamkit-data download test-data` fills by default (`test-data` in the project cache:
$SLAMKIT_CACHE, else ~/.cache/slamkit); the repository's .cache/slamkit/test-data, where
`make test-data` puts it. Each holds the same sub-folders (on a GPU machine the data travels inside the repository:
docs/gpu.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamkit.downloads.excerpts import find_test_data

REPO = Path(__file__).resolve().parents[2]
#: The command that fetches the data (docs/datasets.md, 'The test data').
DOWNLOAD = "slamkit-data download test-data"
DATA = find_test_data(REPO)
TUM = DATA / "tum_fr1_rpy_first150"
REPLICA = DATA / "replica_room0_first20"
SEVENSCENES = DATA / "7scenes_redkitchen_300to999"
#: How a skip for absent data starts (the test run's last line counts them: conftest.py).
MISSING = "shared data not found at"


def missing_data_line(skipped: int) -> str:
    """The loud last line of a test run that skipped `skipped` tests for absent data: where the
    data was looked for and how to point the tests at it."""
    return (f"{skipped} tests SKIPPED for real RGB-D data missing under {DATA}: run `{DOWNLOAD}` "
            f"(or `make test-data`) to fetch it there, or set SLAMKIT_DATA to a folder holding {TUM.name}/, "
            f"{REPLICA.name}/ and {SEVENSCENES.name}/ (docs/datasets.md, 'The test data')")


def require_data(path: Path) -> Path:
    """`path` if it is a folder, else the calling test is skipped, saying where the data was looked for."""
    if not path.is_dir():
        pytest.skip(f"{MISSING} {path} (`{DOWNLOAD}` fetches it, or set SLAMKIT_DATA; docs/datasets.md, "
                    f"'The test data')")
    return path


def paper_data_root(root: Path) -> Path:
    """A data_root as `slamkit-data download paper` lays it out under `root`, holding one Replica
    scene (room0: the shared excerpt) and one TUM sequence (fr1/desk: the shared fr1/rpy excerpt,
    a fr1 camera), both linked to the shared data."""
    (root / "Replica").mkdir(parents=True)
    (root / "Replica" / "room0").symlink_to(require_data(REPLICA), target_is_directory=True)
    (root / "rgbd_dataset_freiburg1_desk").symlink_to(require_data(TUM), target_is_directory=True)
    return root
