"""Extracting a downloaded archive (.tgz / .tar.gz / .zip) with its integrity checked: a zip's
every member against its CRC-32 before anything is written, a gzip stream's CRC and length as
it is read to its end. Members go into a staging folder beside their destination and move into
place only when all are out, so an interrupted or failed extraction leaves no folder that
looks complete. Members that would land outside the destination (absolute paths, `..`, links
pointing out) refuse the whole archive."""

from __future__ import annotations

import gzip
import shutil
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path, PurePosixPath

from slamkit.errors import DataError, OutputError


class DamagedArchive(DataError):
    """The archive's bytes are not a whole, safe archive of its kind (cut short, a CRC that does
    not match, empty, members that would land outside its folder): the download is at fault,
    not the folder it goes into."""


def archive_kind(path: Path) -> str:
    """"zip" or "tar" from the file name."""
    name = path.name.lower()
    if name.endswith(".zip"):
        return "zip"
    if name.endswith((".tgz", ".tar.gz", ".tar")):
        return "tar"
    raise DataError(f"{path}: not an archive this reads (expected .zip, .tgz, .tar.gz or .tar)")


def _safe(name: str, archive: Path) -> None:
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or ".." in p.parts or (p.parts and ":" in p.parts[0]):  # C:... is absolute on Windows
        raise DamagedArchive(f"{archive}: member {name!r} would land outside the folder it is extracted into")


def extract(archive: Path, into: Path) -> list[Path]:
    """Extract `archive` into the folder `into`; returns the top-level entries made there. An
    entry of that name already in `into` is a DataError (nothing is overwritten), so is a
    damaged or unsafe archive (the staging folder is removed)."""
    archive, into = Path(archive), Path(into)
    kind = archive_kind(archive)
    staging = into / f".{archive.name}.extracting"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        if kind == "zip":
            _extract_zip(archive, staging)
        else:
            _extract_tar(archive, staging)
        tops = sorted(staging.iterdir())
        if not tops:
            raise DamagedArchive(f"{archive}: the archive is empty")
        for top in tops:
            if (into / top.name).exists():
                raise DataError(f"{into / top.name} exists already: move it away to extract {archive.name} again")
        for top in tops:
            top.replace(into / top.name)
        return [into / top.name for top in tops]
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _extract_zip(archive: Path, staging: Path) -> None:
    try:
        with zipfile.ZipFile(archive) as z:
            damaged = z.testzip()
            if damaged is not None:
                raise DamagedArchive(f"{archive}: member {damaged!r} fails its CRC check (a damaged download)")
            for name in z.namelist():
                _safe(name, archive)
            z.extractall(staging)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as exc:
        raise DamagedArchive(f"{archive}: not a complete, readable zip archive ({_first_line(exc)})") from None


def _extract_tar(archive: Path, staging: Path) -> None:
    """One streaming pass: each member checked, then extracted; then the rest of a gzip stream is
    read, so that gzip checks its CRC and length (tarfile stops at the end-of-archive blocks)."""
    compressed = archive.name.lower().endswith((".tgz", ".gz"))

    def checked(t: tarfile.TarFile):
        for member in t:
            _safe(member.name, archive)
            if member.issym() or member.islnk():
                target = PurePosixPath(member.name).parent / member.linkname
                if PurePosixPath(member.linkname).is_absolute() or ".." in target.parts:
                    raise DamagedArchive(f"{archive}: link {member.name!r} points outside the archive's folder")
            elif not (member.isfile() or member.isdir()):
                raise DamagedArchive(f"{archive}: member {member.name!r} is not a file or a folder")
            yield member

    try:
        with (gzip.open if compressed else open)(archive, "rb") as stream:
            with tarfile.open(fileobj=stream, mode="r|") as t:
                if hasattr(tarfile, "data_filter"):
                    t.extractall(staging, members=checked(t), filter="data")
                else:  # Python < 3.10.12 / 3.11.4: `checked` is the whole check
                    t.extractall(staging, members=checked(t))
            while stream.read(1 << 20):
                pass
    except (tarfile.TarError, gzip.BadGzipFile, zlib.error, EOFError, OSError) as exc:
        raise DamagedArchive(f"{archive}: not a complete, readable tar archive ({_first_line(exc)})") from None


def tar_files(archive: Path, wanted: Callable[[str], bool]) -> Iterator[tuple[str, bytes]]:
    """(member name, bytes) of each regular file of a .tgz / .tar.gz / .tar whose name `wanted`
    accepts, in archive order, in one streaming pass; the rest of a gzip stream is then read so
    that its CRC and length are checked. DamagedArchive when the stream is cut or damaged (a
    consumer that stops early skips only the end-of-stream check)."""
    archive = Path(archive)
    compressed = archive.name.lower().endswith((".tgz", ".gz"))
    try:
        with (gzip.open if compressed else open)(archive, "rb") as stream:
            with tarfile.open(fileobj=stream, mode="r|") as t:
                for member in t:
                    if member.isfile() and wanted(member.name):
                        yield member.name, t.extractfile(member).read()
            while stream.read(1 << 20):
                pass
    except (tarfile.TarError, gzip.BadGzipFile, zlib.error, EOFError, OSError) as exc:
        raise DamagedArchive(f"{archive}: not a complete, readable tar archive ({_first_line(exc)})") from None


def open_zip(archive: Path) -> zipfile.ZipFile:
    """The zip archive `archive`, opened for reading single members with `zip_member`;
    DamagedArchive when it has no readable central directory (cut short, not a zip)."""
    try:
        return zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise DamagedArchive(f"{archive}: not a complete, readable zip archive ({_first_line(exc)})") from None


def zip_member(z: zipfile.ZipFile, name: str, archive: Path, dest: Path | None = None) -> bytes | None:
    """The bytes of member `name` of the open zip `z` (of the file `archive`), its CRC-32
    checked; with `dest`, they are streamed into that file instead (a large member: a nested
    archive) and None is returned. DamagedArchive when they do not read back whole; OutputError
    when `dest` cannot be written (a full disk)."""
    try:
        if dest is None:
            return z.read(name)
        with z.open(name) as member, open(dest, "wb") as out:
            while block := member.read(1 << 20):
                try:
                    out.write(block)
                except OSError as exc:
                    raise OutputError(f"{dest}: cannot write ({_first_line(exc)}) while copying {name!r} out of "
                                      f"{archive}") from None
        return None
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as exc:
        raise DamagedArchive(f"{archive}: member {name!r} does not read back whole ({_first_line(exc)})") from None


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0] or type(exc).__name__
