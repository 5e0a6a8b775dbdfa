"""User-facing errors: one clear message naming the file, the field and what was expected."""

from __future__ import annotations

from pathlib import Path


class TofhilError(Exception):
    """An error caused by the user's input (a file, an option, a device), not by a bug.

    The CLI prints the message alone (no traceback) and exits with code 2.
    """

    def __init__(self, message: str, *, file: str | Path | None = None,
                 field: str | None = None, expected: str | None = None) -> None:
        self.file = None if file is None else str(file)
        self.field = field
        self.expected = expected
        parts = []
        if self.file:
            parts.append(f"{self.file}")
        if field:
            parts.append(f"field '{field}'")
        prefix = ": ".join(parts)
        text = f"{prefix}: {message}" if prefix else message
        if expected:
            text += f" (expected {expected})"
        super().__init__(text)


class InputFileError(TofhilError):
    """A file is missing, malformed or lacks a field."""


class DeviceError(TofhilError):
    """A camera could not be opened, configured or read."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) ended a writer: what was kept, for the one line the CLI prints.

    A KeyboardInterrupt still, so library callers see the interrupt they expect.
    """

    def __init__(self, path: str | Path, frames_kept: int) -> None:
        self.path = str(path)
        self.frames_kept = int(frames_kept)
        if frames_kept > 0:
            text = f"interrupted: {frames_kept} frame{'s' if frames_kept != 1 else ''} kept in {path}"
        else:
            text = f"interrupted: nothing was written ({path} not created)"
        super().__init__(text)


def require_input_file(path: str | Path, *, expected: str, field: str | None = None) -> Path:
    """``path`` as a Path if it is a readable regular file; otherwise an :class:`InputFileError`
    that says what is wrong: 'no such file', 'is a directory' or 'is not a regular file'."""
    p = Path(path)
    if p.is_file():
        return p
    reason = "is a directory" if p.is_dir() else "no such file" if not p.exists() else "is not a regular file"
    raise InputFileError(reason, file=p, field=field, expected=expected)
