"""Calibration side files (.npz) that name their own format, read with clear errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tofhil.errors import InputFileError


def load_tagged_npz(path: str | Path, fmt: str, what: str, expected_file: str) -> dict[str, Any]:
    """The arrays of an .npz written with ``format=fmt``; errors name the file and field.

    ``what`` names the content for messages ("tofhil tap calibration"), ``expected_file``
    says where such a file comes from.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileError("no such file", file=p, expected=expected_file)
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputFileError(f"cannot be read as .npz ({exc})", file=p, expected=expected_file) from None
    if str(data.get("format", "")) != fmt:
        raise InputFileError(f"not a {what}", file=p, field="format", expected=repr(fmt))
    return data
