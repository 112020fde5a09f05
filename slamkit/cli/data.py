"""`slamkit-data`: fetch the public sequences GS-ICP SLAM's paper evaluates on.

`slamkit-data download NAME... --root DIR` downloads each archive into DIR (a cut transfer
resumes), checks its size and SHA-256 (recorded in `DIR/slamkit-data.json` at the first
download), extracts it into the layout the dataset plugins read and deletes it (unless
`--keep-archive`); a sequence already complete under DIR is not downloaded again. NAME:
`replica` (NICE-SLAM's Replica.zip, eight scenes), a TUM RGB-D sequence
(`rgbd_dataset_freiburg1_desk` or `fr1/desk`), or `paper` for all four archives;
`slamkit-data list` prints them. `--base-url URL` (or SLAMKIT_DATA_BASE_URL) reads a mirror.
docs/datasets.md, "Downloading the paper's sequences". Exit status: 0 done, 1 a download failed
(what it had is kept) or --root cannot be created, 2 a bad name, --root, checksum or archive
(one line each), 130 interrupted. An archive that does not extract (cut short, damaged) is never
kept as the finished download: it is moved aside as FILE.corrupt, its record dropped, and the
next run downloads it again.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from slamkit.downloads import catalogue
from slamkit.downloads.archives import DamagedArchive, extract
from slamkit.downloads.transfer import download, part_path
from slamkit.errors import DataError, OutputError, SlamkitError
from slamkit.formats.atomic import write_atomic

#: The record of what was downloaded into a root folder.
MANIFEST = "slamkit-data.json"
BASE_URL_ENV = "SLAMKIT_DATA_BASE_URL"
INTERRUPTED = 130


def read_manifest(root: Path) -> dict:
    """{archive file name: {url, bytes, sha256, downloaded, extracted}} from ROOT/slamkit-data.json
    (empty when there is none); DataError naming it when it is not such a file."""
    path = root / MANIFEST
    if not path.is_file():
        return {}
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: not readable as JSON ({exc}); move it away to start a new record") from None
    if not isinstance(manifest, dict) or not all(isinstance(v, dict) for v in manifest.values()):
        raise DataError(f"{path}: expected an object of archive records; move it away to start a new record")
    return manifest


def _record(root: Path, file_name: str, **fields) -> None:
    manifest = read_manifest(root)
    manifest[file_name] = {**manifest.get(file_name, {}), **fields}
    write_atomic(root / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def _forget(root: Path, file_name: str) -> None:
    """Drop the record of `file_name` (a damaged download's checksum must not bind the next one)."""
    manifest = read_manifest(root)
    if manifest.pop(file_name, None) is not None:
        write_atomic(root / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def make_root(root: Path) -> None:
    """Create the folder `--root` names (and its parents). DataError (exit 2) when it names
    something that is not a folder, OutputError (exit 1) when it cannot be created."""
    for path in (root, *root.parents):
        if path.exists() and not path.is_dir():
            raise DataError(f"--root {root}: {path} is a file, expected a folder (or a path to create one at)")
        if path.exists():
            break
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"--root {root}: cannot create the folder ({exc.strerror or exc}); "
                          f"give a folder this user can write") from None


def fetch(archive: catalogue.Archive, root: Path, *, base_url: str | None = None, sha256: str | None = None,
          keep_archive: bool = False, retries: int = 3, progress: bool = True) -> list[Path]:
    """Download, check and extract one archive under `root` (see the module docstring); returns
    its dataset folders. Already complete folders are returned as they are."""
    folders = [root / f for f in archive.folders]
    if all(f.is_dir() for f in folders):
        missing = archive.missing(root)
        if missing:
            raise DataError(f"{missing[0]} not found: {archive.name} under {root} is incomplete (move its folders "
                            f"away to download it again)")
        print(f"slamkit-data: {archive.name}: already in {root}")
        return folders
    recorded = read_manifest(root).get(archive.file_name, {})
    url = archive.url(base_url)
    got = download(url, root / archive.file_name, expected_sha256=sha256 or recorded.get("sha256"),
                   retries=retries, progress=progress)
    _record(root, archive.file_name, url=url, bytes=got.size, sha256=got.sha256,
            downloaded=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
    try:
        extract(got.path, root)
    except DamagedArchive as exc:  # never kept as the finished download: the next run fetches it again
        corrupt = got.path.with_name(got.path.name + ".corrupt")
        got.path.replace(corrupt)
        _forget(root, archive.file_name)
        raise DamagedArchive(f"{exc}; moved aside as {corrupt.name}: run the same command again to download it "
                             f"afresh") from None
    missing = archive.missing(root)
    if missing:
        raise DataError(f"{got.path}: extracted, but {missing[0]} is not there (expected the {archive.dataset} "
                        f"layout: {', '.join(archive.required)} in each sequence folder)")
    if not keep_archive:
        got.path.unlink()
    _record(root, archive.file_name, extracted=list(archive.folders))
    print(f"slamkit-data: {archive.name}: {len(folders)} folder(s) in {root} (archive {got.size} bytes, "
          f"SHA-256 {got.sha256}); run with dataset={archive.dataset} dataset.path={folders[0]}")
    return folders


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slamkit-data", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    dl = sub.add_parser("download", help="download and extract sequences into --root")
    dl.add_argument("names", nargs="+", metavar="NAME", help="replica, a TUM sequence (fr1/desk, "
                    "rgbd_dataset_freiburg1_desk, ...) or paper; `slamkit-data list` names them")
    dl.add_argument("--root", required=True, type=Path, help="folder the sequences go into")
    dl.add_argument("--base-url", default=os.environ.get(BASE_URL_ENV) or None,
                    help=f"fetch every archive from under this URL (default: the publishers'; env {BASE_URL_ENV})")
    dl.add_argument("--sha256", help="the archive's expected SHA-256 (one archive only)")
    dl.add_argument("--keep-archive", action="store_true", help="keep the archive after extracting it")
    dl.add_argument("--retries", type=int, default=3, help="tries after a cut transfer, each resuming (default 3)")
    dl.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    sub.add_parser("list", help="the sequences this knows")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "list":
        print(f"slamkit-data knows: {catalogue.known()}")
        return 0
    try:
        archives = list({a.name: a for name in args.names for a in catalogue.resolve(name)}.values())
        if args.sha256 is not None and len(archives) != 1:
            raise SlamkitError(f"--sha256 is one archive's checksum, but the names give {len(archives)} archives")
        if args.retries < 0:
            raise SlamkitError(f"--retries must be >= 0, got {args.retries}")
    except SlamkitError as exc:
        print(f"slamkit-data: error: {exc}", file=sys.stderr)
        return exc.exit_status
    try:
        make_root(args.root)
    except SlamkitError as exc:
        print(f"slamkit-data: error: {exc}", file=sys.stderr)
        return exc.exit_status
    status = 0
    for archive in archives:
        try:
            fetch(archive, args.root, base_url=args.base_url, sha256=args.sha256, keep_archive=args.keep_archive,
                  retries=args.retries, progress=args.progress)
        except SlamkitError as exc:
            if os.environ.get("SLAMKIT_DEBUG"):
                raise
            print(f"slamkit-data: error: {archive.name}: {exc}", file=sys.stderr)
            status = max(status, exc.exit_status)
        except KeyboardInterrupt:
            print(f"slamkit-data: interrupted during {archive.name}; a partial download stays in "
                  f"{part_path(args.root / archive.file_name)} and resumes when the same command runs again",
                  file=sys.stderr)
            return INTERRUPTED
    return status


if __name__ == "__main__":
    sys.exit(main())
