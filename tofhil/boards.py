"""Calibration boards: checkerboard, ChArUco and ArUco grid, as printed and as OpenCV sees them.

One :class:`BoardSpec` says what is printed: the kind, the grid, the square (or marker) size,
the white margin around the pattern and the reflectances of the ink and the paper. The same
spec gives

- the printed pattern as an image (:meth:`BoardSpec.pattern`): 0 where ink, 1 where paper,
  at an integer number of texels per square so that every square edge falls on a texel
  edge; the twin maps it onto a plane of :attr:`BoardSpec.size_m` (``type: board`` objects);
- the board's 3-D points in its own frame (:meth:`BoardSpec.corner_points`) and the OpenCV
  board object (:meth:`BoardSpec.cv_board`) the detector uses (:mod:`tofhil.targets`).

Board frame (OpenCV's): origin at the pattern's top-left corner (inside the margin), x
along the columns (right on the printed sheet), y along the rows (down), z into the board.
The twin's plane is centred at its origin with the same x and y, so the board frame is the
plane's local frame shifted by :meth:`BoardSpec.origin_in_plane`.

A spec is written as a mapping (in a scene or a YAML file)::

    {type: checkerboard, grid: [9, 6], square_m: 0.03, margin_m: 0.03, reflectance: [0.05, 0.8]}
    {type: charuco, grid: [7, 5], square_m: 0.04, marker_m: 0.03, dictionary: DICT_4X4_50}
    {type: aruco, grid: [4, 3], marker_m: 0.04, separation_m: 0.01}

or in one line, ``KIND:COLSxROWS:SIZE_M[:SECOND_M[:DICTIONARY]]`` (checkerboard: the square;
charuco: the square and the marker; aruco: the marker and the separation), e.g.
``checkerboard:9x6:0.03`` or ``charuco:7x5:0.04:0.03:DICT_5X5_100``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil.errors import InputFileError
from tofhil.schema import Schema

BOARD_KINDS = ("checkerboard", "charuco", "aruco")

#: Texels per square (checkerboard, charuco) or per marker (aruco) of the printed pattern:
#: a multiple of 6 and 7 cells so 4x4 and 5x5 markers (plus their border) print on whole texels.
TEXELS_PER_SQUARE = 84

#: Largest grid side accepted (squares or markers).
MAX_GRID = 64

_KEYS = ("type", "grid", "square_m", "marker_m", "separation_m", "dictionary", "margin_m", "reflectance")


@dataclass(frozen=True)
class BoardSpec:
    """A printed calibration board (see the module doc)."""

    kind: str
    cols: int
    rows: int
    #: Square side (checkerboard, charuco) or marker side (aruco), m.
    square_m: float
    #: ChArUco marker side inside a white square, m (charuco only).
    marker_m: float = 0.0
    #: Gap between markers (aruco only), m.
    separation_m: float = 0.0
    dictionary: str = "DICT_4X4_50"
    #: White border around the pattern, m (a quiet zone the detectors need).
    margin_m: float = 0.0
    #: Diffuse reflectance of the ink and of the paper.
    reflectance: tuple[float, float] = (0.05, 0.8)

    # ------------------------------------------------------------------ parsing
    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, source: Any = "<target>", field: str = "target") -> "BoardSpec":
        """Validate a mapping; errors name ``source`` and ``field``."""
        v = Schema(source)
        d = v.mapping(d, field, allowed=_KEYS, none_ok=False, expected="a board mapping with type, grid, square_m")
        kind = v.enum(v.require(d, "type", field, "one of " + ", ".join(BOARD_KINDS)), f"{field}.type", BOARD_KINDS)
        grid = v.require(d, "grid", field, "[columns, rows] of squares (markers for aruco)")
        if not isinstance(grid, (list, tuple)) or len(grid) != 2:
            raise v.bad(grid, f"{field}.grid", "[columns, rows]: two integers")
        lo = 1 if kind == "aruco" else 2
        cols = v.integer(grid[0], f"{field}.grid[0]", lo=lo, hi=MAX_GRID)
        rows = v.integer(grid[1], f"{field}.grid[1]", lo=lo, hi=MAX_GRID)
        size = {"lo": 0.0, "lo_open": True, "hi": 100.0}
        if kind == "aruco":
            square = v.number(v.require(d, "marker_m", field, "the marker side in m"), f"{field}.marker_m", **size)
            sep = v.number(v.require(d, "separation_m", field, "the gap between markers in m"),
                           f"{field}.separation_m", **size)
            marker = square
        else:
            square = v.number(v.require(d, "square_m", field, "the square side in m"), f"{field}.square_m", **size)
            sep = 0.0
            marker = 0.0
            if kind == "charuco":
                marker = v.number(v.require(d, "marker_m", field, "the marker side in m (< square_m)"),
                                  f"{field}.marker_m", lo=0.0, lo_open=True, hi=square, hi_open=True)
            if kind == "checkerboard" and cols * rows > 4 and (cols % 2) == (rows % 2):
                raise v.error(f"grid {cols}x{rows} is symmetric under a half turn", f"{field}.grid",
                              "one even and one odd number of squares (the detected corners then have "
                              "one orientation)")
        for key in ("square_m", "marker_m", "separation_m"):
            if key in d and (kind == "checkerboard" and key != "square_m" or kind == "aruco" and key == "square_m"
                             or kind == "charuco" and key == "separation_m"):
                raise v.error(f"{key} does not apply to a {kind} board", f"{field}.{key}",
                              {"checkerboard": "square_m", "charuco": "square_m and marker_m",
                               "aruco": "marker_m and separation_m"}[kind])
        dictionary = "DICT_4X4_50"
        if kind != "checkerboard":
            dictionary = v.string(d.get("dictionary", dictionary), f"{field}.dictionary", nonempty=True)
            if not dictionary.startswith("DICT_") or not hasattr(_aruco(), dictionary):
                raise v.error(f"unknown dictionary {dictionary!r}", f"{field}.dictionary",
                              "an OpenCV ArUco dictionary such as DICT_4X4_50, DICT_5X5_100, DICT_APRILTAG_36h11")
            need = cols * rows if kind == "aruco" else (cols * rows) // 2
            have = _dictionary(dictionary).bytesList.shape[0]
            if need > have:
                raise v.error(f"the board needs {need} markers, {dictionary} has {have}", f"{field}.grid",
                              "a smaller grid or a larger dictionary")
        elif "dictionary" in d:
            raise v.error("dictionary does not apply to a checkerboard", f"{field}.dictionary", "no dictionary")
        margin = v.number(d.get("margin_m", square), f"{field}.margin_m", lo=0.0, hi=100.0)
        refl = d.get("reflectance", [0.05, 0.8])
        black, white = v.numbers(refl, f"{field}.reflectance", n=2, lo=0.0, hi=1.0,
                                 expected="[ink, paper] reflectances in [0, 1], ink < paper")
        if not black < white:
            raise v.error(f"ink {black:g} is not darker than paper {white:g}", f"{field}.reflectance",
                          "[ink, paper] reflectances in [0, 1], ink < paper")
        return cls(kind=kind, cols=cols, rows=rows, square_m=square, marker_m=marker, separation_m=sep,
                   dictionary=dictionary, margin_m=margin, reflectance=(black, white))

    @classmethod
    def parse(cls, spec: str | Mapping[str, Any] | "BoardSpec", *, source: Any = "--target",
              field: str = "target") -> "BoardSpec":
        """A spec from a mapping, a YAML file path or a one-line ``KIND:COLSxROWS:SIZE...``."""
        if isinstance(spec, BoardSpec):
            return spec
        if isinstance(spec, Mapping):
            return cls.from_dict(spec, source=source, field=field)
        text = str(spec).strip()
        if text.lower().endswith((".yaml", ".yml")):
            from tofhil.yamlio import load_yaml_file

            path = Path(text)
            if not path.is_file():
                raise InputFileError("no such file", file=path, field=field, expected="a board YAML file")
            data = load_yaml_file(path)
            if isinstance(data, Mapping) and "target" in data:
                data = data["target"]
            return cls.from_dict(data, source=path, field=field)
        expected = ("KIND:COLSxROWS:SIZE_M[:SECOND_M[:DICTIONARY]] (e.g. checkerboard:9x6:0.03, "
                    "charuco:7x5:0.04:0.03, aruco:4x3:0.04:0.01) or a board YAML file")
        parts = text.split(":")
        if len(parts) < 3 or "x" not in parts[1].lower():
            raise InputFileError(f"got {text!r}", file=source if source != "--target" else None, field=field,
                                 expected=expected)
        kind = parts[0].strip().lower()
        try:
            cols, rows = (int(p) for p in parts[1].lower().split("x"))
            nums = [float(p) for p in parts[2:4] if not p.upper().startswith("DICT_")]
        except ValueError:
            raise InputFileError(f"got {text!r}", field=field, expected=expected) from None
        d: dict[str, Any] = {"type": kind, "grid": [cols, rows]}
        names = {"checkerboard": ["square_m"], "charuco": ["square_m", "marker_m"],
                 "aruco": ["marker_m", "separation_m"]}.get(kind, ["square_m"])
        if len(nums) != len(names):
            raise InputFileError(f"got {text!r}: {kind} takes {len(names)} sizes ({', '.join(names)})",
                                 field=field, expected=expected)
        d.update(zip(names, nums))
        dicts = [p for p in parts[2:] if p.upper().startswith("DICT_")]
        if dicts:
            d["dictionary"] = dicts[0]
        return cls.from_dict(d, source=source, field=field)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"type": self.kind, "grid": [self.cols, self.rows]}
        if self.kind == "aruco":
            d.update(marker_m=self.marker_m, separation_m=self.separation_m)
        else:
            d["square_m"] = self.square_m
            if self.kind == "charuco":
                d["marker_m"] = self.marker_m
        if self.kind != "checkerboard":
            d["dictionary"] = self.dictionary
        d.update(margin_m=self.margin_m, reflectance=list(self.reflectance))
        return d

    # ------------------------------------------------------------------ geometry
    @property
    def texel_m(self) -> float:
        """Side of one texel of the printed pattern (m)."""
        return self.square_m / TEXELS_PER_SQUARE

    def _texels(self, length_m: float) -> int:
        return int(round(length_m / self.texel_m))

    @property
    def pattern_size_texels(self) -> tuple[int, int]:
        """(width, height) of the pattern without margin, in texels."""
        if self.kind == "aruco":
            sep = self._texels(self.separation_m)
            return (self.cols * TEXELS_PER_SQUARE + (self.cols - 1) * sep,
                    self.rows * TEXELS_PER_SQUARE + (self.rows - 1) * sep)
        return self.cols * TEXELS_PER_SQUARE, self.rows * TEXELS_PER_SQUARE

    @property
    def margin_texels(self) -> int:
        return self._texels(self.margin_m)

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the printed sheet, margin included (m): the plane the twin renders."""
        w, h = self.pattern_size_texels
        m = 2 * self.margin_texels
        return (w + m) * self.texel_m, (h + m) * self.texel_m

    def origin_in_plane(self) -> np.ndarray:
        """The board frame's origin in the centred plane's local frame (m)."""
        w, h = self.size_m
        m = self.margin_texels * self.texel_m
        return np.array([-w / 2 + m, -h / 2 + m, 0.0])

    def board_to_plane(self) -> np.ndarray:
        """4x4 transform from the board frame to the plane's local frame (a translation)."""
        t = np.eye(4)
        t[:3, 3] = self.origin_in_plane()
        return t

    def corner_points(self) -> np.ndarray:
        """Checkerboard inner corners ``[(cols-1)*(rows-1), 3]`` in row-major order (board frame);
        for ChArUco the chessboard corners in the order of their ids; for ArUco the four
        corners of every marker (id order, each clockwise from top-left)."""
        if self.kind == "checkerboard":
            j, i = np.meshgrid(np.arange(1, self.cols), np.arange(1, self.rows))
            return np.stack([j.ravel() * self.square_m, i.ravel() * self.square_m,
                             np.zeros(j.size)], axis=1)
        board = self.cv_board()
        if self.kind == "charuco":
            return np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        return np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in board.getObjPoints()])

    # ------------------------------------------------------------------ OpenCV
    def cv_board(self) -> Any:
        """The OpenCV board (``cv2.aruco.CharucoBoard`` / ``GridBoard``); None for a checkerboard.
        Sizes are the printed ones (whole texels), so the board matches the pattern exactly."""
        return _cv_board(self)

    def pattern(self) -> np.ndarray:
        """The printed pattern, margin included: ``[H, W]`` float64, 0 = ink, 1 = paper;
        row 0 at the top (board y = -margin), column 0 at the left."""
        return _pattern(self)

    def reflectance_image(self) -> np.ndarray:
        """The pattern as diffuse reflectances (ink / paper)."""
        black, white = self.reflectance
        return black + (white - black) * self.pattern()


def _aruco() -> Any:
    import cv2

    return cv2.aruco


def _dictionary(name: str) -> Any:
    a = _aruco()
    return a.getPredefinedDictionary(getattr(a, name))


@lru_cache(maxsize=16)
def _cv_board(spec: BoardSpec) -> Any:
    if spec.kind == "checkerboard":
        return None
    a = _aruco()
    d = _dictionary(spec.dictionary)
    texel = spec.texel_m
    if spec.kind == "charuco":
        # marker side rounded to whole texels, as it is printed
        marker = spec._texels(spec.marker_m) * texel
        return a.CharucoBoard((spec.cols, spec.rows), TEXELS_PER_SQUARE * texel, marker, d)
    sep = spec._texels(spec.separation_m) * texel
    return a.GridBoard((spec.cols, spec.rows), TEXELS_PER_SQUARE * texel, sep, d)


@lru_cache(maxsize=16)
def _pattern(spec: BoardSpec) -> np.ndarray:
    w, h = spec.pattern_size_texels
    m = spec.margin_texels
    if spec.kind == "checkerboard":
        j, i = np.meshgrid(np.arange(w) // TEXELS_PER_SQUARE, np.arange(h) // TEXELS_PER_SQUARE)
        inner = ((i + j) % 2 == 1).astype(np.float64)   # top-left square is ink, as OpenCV's boards
    else:
        # OpenCV draws the board filling the image (no margin asked: ours is added below).
        inner = spec.cv_board().generateImage((w, h), marginSize=0).astype(np.float64) / 255.0
        inner = (inner > 0.5).astype(np.float64)
    img = np.ones((h + 2 * m, w + 2 * m))
    img[m:m + h, m:m + w] = inner
    img.setflags(write=False)
    return img
