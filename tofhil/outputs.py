"""Output paths: refuse to overwrite unless forced, and write atomically.

Every command that writes follows the same two rules (README, "Errors and data"): nothing a
user recorded is replaced without ``--force``, and a write that fails leaves neither a
half-written file under the real name nor (with ``--force``) a destroyed previous one. This
module is the one place that says how.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any, Iterator, Sequence

from tofhil.errors import InputFileError, TofhilError

#: What every refusal says, so users (and scripts) meet one wording.
REFUSAL = "refusing to overwrite (use --force to replace it)"


def refuse_existing(path: str | Path, force: bool, *, what: str = "already exists", field: str | None = None,
                    expected: str | None = None, recorded: bool = False) -> None:
    """Raise the one refusal when ``path`` exists and ``force`` is not given.

    ``what`` says what is there (``"already holds a diagnosis"``), ``field`` the option the
    path came from (``--out``); ``recorded``: the file holds recorded data (a session), which
    the message says (an :class:`InputFileError`, as the session writer's)."""
    p = Path(path)
    if force or not p.exists():
        return
    if recorded:
        raise InputFileError(f"{what}; refusing to overwrite recorded data (use --force to replace it)", file=p,
                             field=field, expected=expected)
    raise TofhilError(f"{what}; {REFUSAL}", file=p, field=field, expected=expected)


def check_new_path(path: Path, force: bool) -> None:
    """Refuse to replace an existing file unless forced, and to write anywhere but a regular
    file in an existing directory (never a directory, a device such as /dev/full, a pipe)."""
    if path.is_dir():
        raise InputFileError("is a directory", file=path, expected="a file name for the output")
    if path.exists() and not path.is_file():
        raise InputFileError("is not a regular file (a device or a pipe); refusing to write to it", file=path)
    refuse_existing(path, force, recorded=True)
    parent = path.parent
    if not parent.exists():
        raise InputFileError("directory does not exist", file=parent)
    if not parent.is_dir():
        raise InputFileError("is not a directory", file=parent)


def prepare_output_dir(path: str | Path, names: Sequence[str], *, force: bool) -> Path:
    """Check that ``path`` can take a command's outputs: a directory (or a new one) holding
    none of ``names`` unless ``force``. Creates nothing: callers create it when they write."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise TofhilError("is a file, not a directory", file=out, field="--out",
                          expected="a directory for the report (new or existing)")
    existing = [n for n in names if (out / n).exists()]
    if existing:
        refuse_existing(out / existing[0], force)
    return out


def partial_path(path: Path) -> Path:
    """The temporary name a file is written under beside ``path`` (hidden, this process's).

    Partial files of the same output left by a process that no longer runs (SIGKILL, a power
    cut: nothing could remove them) are removed first, so the next run of the same output
    cleans up after the killed one."""
    remove_stale_partials(path)
    return path.with_name(f".{path.name}.{os.getpid()}.partial")


def remove_stale_partials(path: Path) -> list[Path]:
    """Remove ``.NAME.PID.partial`` beside ``path`` whose PID is not a running process (this
    machine's: a live PID, even another user's, keeps its file). Returns what was removed."""
    import glob

    removed = []
    prefix = f".{path.name}."
    for p in path.parent.glob(glob.escape(prefix) + "*.partial"):
        pid = p.name[len(prefix):-len(".partial")]
        if pid.isdigit() and int(pid) != os.getpid() and not _running(int(pid)):
            remove_partial(p)
            removed.append(p)
    return removed


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)  # signal 0: only whether the process exists
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's process (or no such pid number)
        return True
    return True


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed onto ``path`` when the block ends
    without an exception, removed when it raises (for writers that want a path: HDF5,
    parquet, a directory)."""
    path = Path(path)
    tmp = partial_path(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        remove_partial(tmp)
        raise


@contextmanager
def atomic_file(path: str | Path, mode: str = "wb", **open_kwargs: Any) -> Iterator[IO[Any]]:
    """An open temporary file beside ``path`` (``mode`` ``"wb"`` or ``"w"``), renamed onto it
    when the block ends without an exception; a directory that cannot take it is one
    :class:`TofhilError` naming the file."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise TofhilError(f"cannot write here ({exc.strerror})", file=path, expected="a writable directory") from None
    try:
        # mkstemp makes the file private (0600); the output is as readable as any file the
        # user writes (the umask's mode), as before it went through a temporary name
        os.chmod(tmp, 0o666 & ~_umask())
        with os.fdopen(fd, mode, **open_kwargs) as f:
            yield f
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise TofhilError(f"cannot write ({exc.strerror or exc})", file=path, expected="a writable file") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text_atomic(path: str | Path, text: str) -> Path:
    """``path`` holds ``text`` (UTF-8), or what it held before if the write failed."""
    with atomic_file(path, "w", encoding="utf-8") as f:
        f.write(text)
    return Path(path)


def remove_partial(path: Path) -> None:
    """Remove a temporary file (or directory) this process wrote; never raises."""
    import shutil

    try:
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        pass
