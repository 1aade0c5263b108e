"""Output files appear whole or not at all: everything is written to a temporary sibling, fsynced, checked, then
published under its name.

Every output check lives here, so each command refuses the same things the same way, before any work:
a missing folder, an existing path that is not a regular file (a symlink, FIFO, device or folder is
never replaced, even with --force), an existing file without --force, and a folder we cannot write to.
An output that may not replace a file is published by link(), which fails if anything has appeared under
its name since that check (a concurrent writer): the check and the publication are one atomic step.
Every OSError while writing becomes one UserError line; a full disk says so ("no space left on …").
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import shutil
import stat
import tempfile
from pathlib import Path

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import MAX_JSON_DEPTH, json_depth

# Formats that do not store the 8-bit pixels they are given: a reveal written in one could not be exact.
LOSSY_SUFFIXES = (".jpg", ".jpeg", ".jpe", ".jfif", ".webp", ".heic", ".heif", ".avif", ".jxl", ".jp2", ".gif")


# errors that mean the file system is out of room (blocks or quota) rather than refusing this path
NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
# link() refused by the file system itself (not by the name being taken): publish by rename instead
NO_HARD_LINKS = (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV, errno.EMLINK)


def os_failure(what: str, path: str | os.PathLike, error: OSError, code: str) -> UserError:
    """One readable line for an OSError: what we tried, on which path, and the system's reason (code: the
    refusal's; no params: the path and the system's words are not the refusal's to promise)."""
    return UserError(f"cannot {what} {path}: {error.strerror or error}", code=code)


def write_failure(path: Path, error: OSError) -> UserError:
    """One line for an OSError while writing `path`; a full file system is named as such."""
    if error.errno in NO_SPACE:
        return UserError(f"no space left on the file system of {path.parent} while writing {path.name}; "
                         f"nothing was written", code="file.no_space")
    return os_failure("write", path, error, "file.write_failed")


def existing_kind(path: Path) -> str | None:
    """What is at `path` without following a symlink: None (nothing), "a file" (a regular one), or another kind."""
    try:
        mode = path.lstat().st_mode
    except FileNotFoundError:
        return None
    except OSError as error:
        raise os_failure("inspect", path, error, "file.inspect_failed") from None
    kinds = {stat.S_ISREG: "a file", stat.S_ISDIR: "a directory", stat.S_ISLNK: "a symlink",
             stat.S_ISFIFO: "a FIFO", stat.S_ISSOCK: "a socket"}
    return next((name for test, name in kinds.items() if test(mode)), "a device")


def probe_writable(folder: Path) -> None:
    """Create and remove a scratch file in `folder`, so an unwritable folder is refused before any work."""
    try:
        fd, scratch = tempfile.mkstemp(prefix=".noisenerf-", dir=folder)
        os.close(fd)
        os.unlink(scratch)
    except OSError as error:
        raise os_failure("write to folder", folder, error, "file.folder_not_writable") from None


def check_output_path(path: str | os.PathLike, force: bool = True) -> Path:
    """Refuse an output whose folder is missing or unwritable, that exists as anything but a regular file
    (even with force: we never replace a symlink, FIFO or folder), or (without force) that exists."""
    path = Path(path)
    if not path.parent.is_dir():
        raise UserError(f"output folder does not exist: {path.parent}", code="file.no_output_folder")
    if len(path.name.encode()) > 255:
        raise UserError(f"output file name is longer than 255 bytes: {path.name[:40]}…", code="file.name_too_long",
                        bytes=len(path.name.encode()), most=255)
    kind = existing_kind(path)
    if kind not in (None, "a file"):
        raise UserError(f"output path is {kind}, not a regular file: {path}", code="file.not_regular", kind=kind)
    if kind == "a file" and not force:
        raise UserError(f"output exists (pass --force to overwrite): {path}", code="file.exists")
    probe_writable(path.parent)
    return path


def check_output_directory(path: str | os.PathLike) -> Path:
    """A folder to write into: its parent must exist, and it may already exist only as a folder."""
    path = Path(path)
    if not path.parent.is_dir():
        raise UserError(f"output folder does not exist: {path.parent}", code="file.no_output_folder")
    kind = existing_kind(path)
    if kind not in (None, "a directory"):
        raise UserError(f"output path is {kind}, not a folder: {path}", code="file.not_folder", kind=kind)
    return path


def check_output_folder(path: str | os.PathLike, *, replace: bool, marker: str, what: str) -> Path:
    """A folder an output is published as, whole: refused where its parent is missing or unwritable, where it
    exists as anything but a folder, where it holds files (without --force), or where with --force those files
    are not an earlier output of the same kind (no `marker` file in it): --force replaces a `what`, never a
    folder of other files."""
    path = check_output_directory(path)
    try:
        occupied = existing_kind(path) == "a directory" and any(path.iterdir())
    except OSError as error:
        raise os_failure("inspect", path, error, "file.inspect_failed") from None
    if occupied and not replace:
        raise UserError(f"output folder is not empty (pass --force to replace the {what} in it): {path}",
                        code="file.folder_not_empty")
    if occupied and not (path / marker).is_file():
        raise UserError(f"output folder holds files but no {marker}: --force replaces an earlier {what}, not other "
                        f"files: {path}", code="file.folder_not_replaceable", marker=marker)
    probe_writable(path.parent)
    return path


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike, *, replace: bool, marker: str, what: str):
    """Yield a temporary folder beside `path`; publish it as `path` only if the block succeeds, so a reader never
    sees half an output, nor an old one's files beside a new one's. Onto nothing or an empty folder it is one
    rename; over an earlier output (`replace`, checked again by check_output_folder) the old folder is moved aside,
    the new one renamed in, then the old one removed."""
    path = check_output_folder(path, replace=replace, marker=marker, what=what)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=".noisenerf-", dir=path.parent))
    except OSError as error:
        raise write_failure(path, error) from None
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp's 0700 would make the folder owner-only
        fsync_path(tmp)
        publish_folder(tmp, path, replace=replace, marker=marker, what=what)
        fsync_path(path.parent)
    except OSError as error:
        raise write_failure(path, error) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def publish_folder(tmp: Path, path: Path, *, replace: bool, marker: str, what: str) -> None:
    try:
        os.rename(tmp, path)  # replaces nothing, or an empty folder, atomically
        return
    except OSError as error:
        if error.errno not in (errno.ENOTEMPTY, errno.EEXIST):
            raise
    check_output_folder(path, replace=replace, marker=marker, what=what)  # filled while this one was written
    old = Path(tempfile.mkdtemp(prefix=".noisenerf-old-", dir=path.parent))
    os.rename(path, old)
    os.rename(tmp, path)
    shutil.rmtree(old, ignore_errors=True)


def refuse_lossy(path: Path) -> None:
    """A reveal is checked on its 8-bit pixels, so it is only written where those pixels survive."""
    if path.suffix.lower() in LOSSY_SUFFIXES:
        raise UserError(f"{path.suffix} is a lossy format: the revealed pixels would not be the secret's; "
                        f"write .png, .tif or .exr", code="file.lossy_format", suffix=path.suffix.lower()[:60])


def current_umask() -> int:
    """The process's umask (reading it means setting it: set it back at once)."""
    umask = os.umask(0)
    os.umask(umask)
    return umask


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a file's (or a folder's) data to disk, so a rename never publishes an empty file after a crash."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, replace: bool):
    """Yield a temporary path beside `path`; fsync it and publish it as `path` only if the block succeeds.

    replace: whether an existing file at `path` may be replaced (--force, or a file the program owns such as
    a checkpoint); without it the file is published by link(), so a file that appeared at `path` while this
    one was written (another writer) is never replaced: one UserError instead. The temporary name is short
    (not derived from the output's), so any valid output name works; it never outlives a failed block.
    """
    path = check_output_path(path, force=replace)
    try:
        fd, tmp = tempfile.mkstemp(prefix=".noisenerf-", suffix=path.suffix[:16] or ".tmp", dir=path.parent)
        os.close(fd)
    except OSError as error:
        raise write_failure(path, error) from None
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp's 0600 would make every output owner-only
        fsync_path(tmp)
        publish(Path(tmp), path, replace)
        fsync_path(path.parent)
    except OSError as error:
        raise write_failure(path, error) from None
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)


def publish(tmp: Path, path: Path, replace: bool) -> None:
    """Give the finished temporary file its name: rename over `path` when replace, else link (refused at once
    if the name is taken, by whatever took it since the output was checked)."""
    if replace:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise UserError(f"output exists (pass --force to overwrite): {path} appeared while this one was "
                        f"written", code="file.exists") from None
    except OSError as error:
        if error.errno not in NO_HARD_LINKS:
            raise
        check_output_path(path, force=False)  # a file system without hard links: check, then rename
        os.replace(tmp, path)


def write_bytes(path: str | os.PathLike, data: bytes, *, replace: bool) -> None:
    """Write `data` to `path` atomically (atomic_output), its size checked before it is published."""
    path = Path(path)
    with atomic_output(path, replace=replace) as tmp:
        with open(tmp, "wb") as handle:
            handle.write(data)
        if tmp.stat().st_size != len(data):  # a write that lost bytes without an error is still a failure
            raise UserError(f"cannot write {path}: {tmp.stat().st_size} of {len(data)} bytes reached the disk",
                            code="file.write_incomplete", written=tmp.stat().st_size, bytes=len(data))


def finite_json(data):
    """The data with every non-finite float as None: strict JSON has no Infinity (a perfect PSNR)."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {key: finite_json(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [finite_json(value) for value in data]
    return data


def json_text(data, indent: int | None = None) -> str:
    """Strict JSON text (non-finite floats become null)."""
    return json.dumps(finite_json(data), indent=indent, allow_nan=False)


def write_json(path: str | os.PathLike, data, *, replace: bool = True) -> None:
    """Atomically write indented JSON (a file the program owns: replaced unless told otherwise)."""
    write_bytes(path, (json_text(data, indent=2) + "\n").encode(), replace=replace)


def parse_json(text: str | bytes, what: str, source: str | os.PathLike = ""):
    """Parse JSON from a file someone else made, nesting at most MAX_JSON_DEPTH (json's recursive decoder
    raises RecursionError on a deep enough input; that becomes one UserError too). NaN and Infinity still
    parse: every number is checked where it is used (runtime.limits), with a message naming it."""
    try:
        data = json.loads(text)
        too_deep = json_depth(data) > MAX_JSON_DEPTH
    except RecursionError:
        data, too_deep = None, True
    except (UnicodeDecodeError, ValueError) as error:  # JSONDecodeError is a ValueError
        raise UserError(f"{what} is not valid JSON{f': {source}' if source else ''} "
                        f"({' '.join(str(error).split())[:160]})", code="json.invalid") from None
    if too_deep:
        raise UserError(f"{what} is nested deeper than {MAX_JSON_DEPTH} levels{f': {source}' if source else ''}",
                        code="json.too_deep", depth=MAX_JSON_DEPTH)
    return data


def read_json(path: str | os.PathLike, what: str) -> dict:
    """Read a JSON object or raise one clear UserError naming `what`."""
    try:
        text = Path(path).read_bytes()
    except FileNotFoundError:
        raise UserError(f"{what} not found: {path}", code="file.not_found") from None
    except OSError as error:
        raise os_failure(f"read {what}", path, error, "file.read_failed") from None
    data = parse_json(text, what, path)
    if not isinstance(data, dict):
        raise UserError(f"{what} must hold a JSON object: {path}", code="json.not_object")
    return data
