"""`slamkit-data`: fetch the public sequences GS-ICP SLAM's paper evaluates on, and the tests' data.

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

`slamkit-data download test-data [--root DIR]` fetches the three excerpts the data-driven tests
read (slamkit.downloads.excerpts: TUM fr1/rpy, 7-Scenes redkitchen, Replica room0; one with
`test-data/tum`, `test-data/7scenes` or `test-data/replica`) into DIR, by default $SLAMKIT_DATA,
else `test-data` in the project cache, where the tests look. It says each archive's size
before downloading, fetches them one at a time (resuming a part file, skipping an excerpt
already cut), cuts each excerpt and deletes the archive (unless `--keep-archive`; a kept
archive is cut again without a download), and ends saying where the tests find the data. Of
Replica.zip (~12 GB) only the excerpt's members are read, by HTTP range requests, where its
server answers them and no `--keep-archive` asks for the archive. An archive that is not the one
expected is moved aside as FILE.rejected. docs/datasets.md, "The test data".
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

from slamkit.downloads import catalogue, excerpts
from slamkit.downloads.archives import DamagedArchive, extract
from slamkit.downloads.transfer import Downloaded, RangeReader, download, part_path, ranged, remote_size
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


def _download(archive: catalogue.Archive, root: Path, *, base_url: str | None, sha256: str | None, retries: int,
              progress: bool) -> Downloaded:
    """Download `archive` into ROOT/FILE (resuming a part file; a complete FILE is used as it is)
    and record it; its SHA-256 must match `sha256`, else the one recorded at the first download."""
    recorded = read_manifest(root).get(archive.file_name, {})
    url = archive.url(base_url)
    got = download(url, root / archive.file_name, expected_sha256=sha256 or recorded.get("sha256"),
                   retries=retries, progress=progress)
    _record(root, archive.file_name, url=url, bytes=got.size, sha256=got.sha256,
            downloaded=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
    return got


def _set_aside(root: Path, got: Downloaded, exc: DataError, suffix: str = "corrupt") -> DataError:
    """The error for an archive that cannot be used (`exc`), after moving it aside as FILE.SUFFIX
    and forgetting its record: it is never kept as the finished download, and the next run
    downloads it again."""
    aside = got.path.with_name(f"{got.path.name}.{suffix}")
    got.path.replace(aside)
    _forget(root, got.path.name)
    return type(exc)(f"{exc}; moved aside as {aside.name}: run the same command again to download it afresh")


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
    got = _download(archive, root, base_url=base_url, sha256=sha256, retries=retries, progress=progress)
    try:
        extract(got.path, root)
    except DamagedArchive as exc:
        raise _set_aside(root, got, exc) from None
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


def size_text(n: int | None) -> str:
    """A byte count for people: `1.2 GB`, `84 MB`, `12 kB` (powers of 1000), or `size unknown`."""
    if n is None:
        return "size unknown"
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}" if unit == "GB" else f"{n / scale:.0f} {unit}"
    return f"{n} bytes"


def plan_test_data(chosen: list[excerpts.Excerpt], root: Path, base_url: str | None,
                   keep_archive: bool = False) -> tuple[dict[str, int | None], dict[str, int]]:
    """Say, before anything is downloaded, which excerpts are already there and how large each
    archive still to fetch is (the server's Content-Length). Returns ({archive file: bytes still
    to download (None: unknown)}, {archive file: its size, for an archive whose excerpt is read
    out of it where it is, by HTTP range requests}): an excerpt made `by_range` whose server
    answers range requests, unless `keep_archive` asks for the archive."""
    todo, remote = {}, {}
    for excerpt in chosen:
        archive = excerpt.archive
        url = archive.url(base_url)
        if (root / excerpt.folder).is_dir():
            print(f"slamkit-data: {excerpt.folder}: already in {root}")
            continue
        if (root / archive.file_name).is_file():
            todo[archive.file_name] = 0
            print(f"slamkit-data: {excerpt.folder}: will be cut from {root / archive.file_name} (downloaded earlier)")
            continue
        size = ranged(url) if excerpt.by_range and not keep_archive else None
        if size is not None:
            remote[archive.file_name] = size
            print(f"slamkit-data: {excerpt.folder}: {excerpt.what}; its files to be read out of {archive.file_name} "
                  f"({size_text(size)}) where it is, by HTTP range requests: only they are downloaded")
            continue
        size = remote_size(url)
        part = part_path(root / archive.file_name)
        have = part.stat().st_size if part.is_file() else 0
        todo[archive.file_name] = None if size is None else max(size - have, 0)
        resumed = f", {size_text(have)} of it already here" if have else ""
        print(f"slamkit-data: {excerpt.folder}: {excerpt.what}; to be cut from {archive.file_name} "
              f"({size_text(size)}{resumed})")
    known = [n for n in todo.values() if n]
    if known:
        print(f"slamkit-data: {size_text(sum(known))} to download in all, one archive at a time; each archive is "
              f"deleted once its excerpt is cut (--keep-archive keeps it)")
    return todo, remote


def fetch_excerpt(excerpt: excerpts.Excerpt, root: Path, *, base_url: str | None = None, keep_archive: bool = False,
                  retries: int = 3, progress: bool = True, remaining: int | None = None,
                  by_range: int | None = None) -> Path:
    """Download the archive of one test-data excerpt into `root`, cut the excerpt into
    ROOT/FOLDER (excerpts module) and delete the archive unless `keep_archive`; returns the
    folder. A folder already there is taken as complete. `remaining`: the bytes still to
    download, checked against the free space first (OutputError, exit 1, when short).
    `by_range`: the archive's size, when the excerpt is to be read out of it where it is
    (plan_test_data) instead: nothing is downloaded whole."""
    folder = root / excerpt.folder
    if folder.is_dir():
        return folder
    if by_range is not None:
        return _cut_by_range(excerpt, root, base_url=base_url, size=by_range, retries=retries)
    free = shutil.disk_usage(root).free
    if remaining and free < remaining:
        raise OutputError(f"{root}: {size_text(free)} free, but {excerpt.archive.file_name} needs "
                          f"{size_text(remaining)} more; free some space or give another --root")
    got = _download(excerpt.archive, root, base_url=base_url, sha256=None, retries=retries, progress=progress)
    print(f"slamkit-data: {excerpt.folder}: cutting it from {got.path.name}")
    into = excerpts.staging(root, excerpt)
    try:
        excerpt.cut(got.path, into)
        excerpts.finish(excerpt, into, excerpt.archive.url(base_url), f"archive SHA-256 {got.sha256}")
        into.replace(folder)
    except DamagedArchive as exc:
        raise _set_aside(root, got, exc) from None
    except DataError as exc:  # not the archive expected: set aside, so the next run does not cut it again
        raise _set_aside(root, got, exc, "rejected") from None
    finally:
        shutil.rmtree(into, ignore_errors=True)
    if not keep_archive:
        got.path.unlink()
    _record(root, excerpt.archive.file_name, cut=excerpt.folder)
    print(f"slamkit-data: {excerpt.folder}: done, in {folder}")
    return folder


def _cut_by_range(excerpt: excerpts.Excerpt, root: Path, *, base_url: str | None, size: int, retries: int) -> Path:
    """Cut `excerpt` out of its archive where it is (`size` bytes), reading only what its
    members need; each member's CRC is checked as it is read."""
    url = excerpt.archive.url(base_url)
    reader = RangeReader(url, size, retries=retries)
    print(f"slamkit-data: {excerpt.folder}: reading its files out of {url}")
    into = excerpts.staging(root, excerpt)
    try:
        excerpt.cut(reader, into)
        excerpts.finish(excerpt, into, url, f"read where it is by HTTP range requests: {reader.fetched} of its "
                                            f"{size} bytes")
        into.replace(root / excerpt.folder)
    except DataError as exc:
        raise type(exc)(f"{exc}; nothing was kept: run the same command again") from None
    finally:
        shutil.rmtree(into, ignore_errors=True)
    _record(root, excerpt.archive.file_name, url=url, bytes=size, read_by_range=reader.fetched, cut=excerpt.folder)
    print(f"slamkit-data: {excerpt.folder}: done, in {root / excerpt.folder} ({size_text(reader.fetched)} "
          f"read of {excerpt.archive.file_name}'s {size_text(size)})")
    return root / excerpt.folder


def test_data_hint(root: Path) -> str:
    """The last line of a test-data download: where the tests find it."""
    if root == excerpts.default_root():
        return (f"slamkit-data: the test data is in {root}, where the tests look for it by default "
                f"(SLAMKIT_DATA={root} says so explicitly)")
    return f"slamkit-data: the test data is in {root}; run the tests with SLAMKIT_DATA={root} (export it)"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slamkit-data", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    dl = sub.add_parser("download", help="download and extract sequences into --root, or the test data")
    dl.add_argument("names", nargs="+", metavar="NAME", help="replica, a TUM sequence (fr1/desk, "
                    "rgbd_dataset_freiburg1_desk, ...), paper, or test-data (test-data/tum, test-data/7scenes, "
                    "test-data/replica for one excerpt); `slamkit-data list` names them")
    dl.add_argument("--root", type=Path, help="folder the sequences go into (required but for test-data, "
                    "which goes to $SLAMKIT_DATA, else $SLAMKIT_CACHE/test-data, else ~/.cache/slamkit/test-data)")
    dl.add_argument("--base-url", default=os.environ.get(BASE_URL_ENV) or None,
                    help=f"fetch every archive from under this URL (default: the publishers'; env {BASE_URL_ENV})")
    dl.add_argument("--sha256", help="the archive's expected SHA-256 (one archive only)")
    dl.add_argument("--keep-archive", action="store_true", help="keep the archive after extracting (or cutting) it")
    dl.add_argument("--retries", type=int, default=3, help="tries after a cut transfer, each resuming (default 3)")
    dl.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    sub.add_parser("list", help="the sequences this knows")
    return parser


def _jobs(args) -> tuple[Path, list]:
    """(root, [Archive] or [Excerpt]) for the names given; SlamkitError (exit 2) for bad ones."""
    test_data = [n for n in args.names if excerpts.is_test_data(n)]
    if args.retries < 0:
        raise SlamkitError(f"--retries must be >= 0, got {args.retries}")
    if test_data:
        others = [n for n in args.names if n not in test_data]
        if others:
            raise SlamkitError(f"{others[0]!r} and {test_data[0]!r} in one command: the test data goes into a folder "
                               f"of its own, so download them with two commands")
        if args.sha256 is not None:
            raise SlamkitError("--sha256 is one catalogue archive's checksum; test-data checks its archives by "
                               "the excerpts it cuts")
        chosen = list({e.key: e for name in test_data for e in excerpts.resolve(name)}.values())
        return (args.root or excerpts.default_root()).absolute(), chosen
    archives = list({a.name: a for name in args.names for a in catalogue.resolve(name)}.values())
    if args.sha256 is not None and len(archives) != 1:
        raise SlamkitError(f"--sha256 is one archive's checksum, but the names give {len(archives)} archives")
    if args.root is None:
        raise SlamkitError(f"--root is required for {args.names[0]!r}: the folder the sequences go into "
                           f"(only test-data has a default folder)")
    return args.root, archives


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "list":
        print(f"slamkit-data knows: {catalogue.known()}; and {excerpts.NAME}, the tests' excerpts: "
              + "; ".join(f"{excerpts.NAME}/{e.key} ({e.what})" for e in excerpts.EXCERPTS))
        return 0
    try:
        root, jobs = _jobs(args)
        make_root(root)
        todo, remote = (plan_test_data(jobs, root, args.base_url, args.keep_archive)
                        if isinstance(jobs[0], excerpts.Excerpt) else ({}, {}))
    except SlamkitError as exc:
        print(f"slamkit-data: error: {exc}", file=sys.stderr)
        return exc.exit_status
    status = 0
    for job in jobs:
        archive = job.archive if isinstance(job, excerpts.Excerpt) else job
        try:
            if isinstance(job, excerpts.Excerpt):
                fetch_excerpt(job, root, base_url=args.base_url, keep_archive=args.keep_archive, retries=args.retries,
                              progress=args.progress, remaining=todo.get(archive.file_name),
                              by_range=remote.get(archive.file_name))
            else:
                fetch(job, root, base_url=args.base_url, sha256=args.sha256, keep_archive=args.keep_archive,
                      retries=args.retries, progress=args.progress)
        except SlamkitError as exc:
            if os.environ.get("SLAMKIT_DEBUG"):
                raise
            print(f"slamkit-data: error: {archive.name}: {exc}", file=sys.stderr)
            status = max(status, exc.exit_status)
        except KeyboardInterrupt:
            part = part_path(root / archive.file_name)
            kept = (f"a partial download stays in {part} and resumes" if part.is_file() else
                    "nothing half-done is kept; it goes on")
            print(f"slamkit-data: interrupted during {archive.name}; {kept} when the same command runs again",
                  file=sys.stderr)
            return INTERRUPTED
    if isinstance(jobs[0], excerpts.Excerpt) and status == 0:
        print(test_data_hint(root))
    return status


if __name__ == "__main__":
    sys.exit(main())
