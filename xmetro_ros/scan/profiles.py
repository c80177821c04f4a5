"""Recordings of single laser-line profiles of a certified sphere, read from files (CSV or NumPy).

A profile is what a laser line scanner measures in one exposure: points in the laser plane, in the **sensor frame**
(x along the laser line, z the range axis, y = 0 by construction), mm. A profile recording is a list of such
files, each the sphere seen from one *position* of the sensor, possibly profiled several times without moving
(*repeats*): the mean of a position's repeats estimates the scanner's systematic error there, their spread its
random error.

File forms (one profile per file):

- CSV: rows ``x, z[, label]`` (mm; a header line, if any, is skipped; ``label`` 1 = on the sphere, 0 = not, used
  only to score a segmentation, never by the product);
- NumPy ``.npy``: an (N, 2) or (N, 3) array of the same columns; ``.npz``: arrays ``xz`` (N, 2) and optional
  ``label`` (N,).

Names: ``[m_]<position>_<repeat>.<ext>`` (the layout of the Standard Sphere Seg data set): files that share
``<position>`` (and folder) are repeats; the ``m_`` prefix says the sphere centre lies at **negative** y of the
laser plane (the sign of the out-of-plane offset y0), no prefix positive. Another naming gives one position per
file (no repeats) and y0 > 0 unless the caller says otherwise.

A list file (``train_file.txt``) names one profile per line, relative to its own folder (a leading ``/`` is
relative too). Non-finite points (no return) are dropped on reading; an empty file, a row of the wrong width or
a non-numeric value is a :class:`ProfileDataError` naming the file and the line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["ProfileDataError", "ProfileRecord", "load_profile_list", "parse_profile_name", "read_profile"]

_NAME = re.compile(r"^(?P<neg>m_?(?=\d))?(?P<pos>.+?)_(?P<rep>\d+)$")


class ProfileDataError(ValueError):
    """A profile file or list that is missing, unreadable or malformed (the message names the file)."""


@dataclass
class ProfileRecord:
    """One profile (sensor frame, mm).

    Attributes:
        name: the file's path relative to the recording root (``label_out_1/m_6_2.csv``).
        position: key shared by the repeats of one sensor position (folder + position id).
        repeat: the repeat number (0 when the name has none).
        side: +1 or −1, the sign of the sphere centre's y (out of the laser plane).
        xz: (N, 2) finite points, x along the laser line and z the range axis, mm, in file order.
        label: (N,) int8 per-point labels (1 sphere, 0 not) or None.
    """

    name: str
    position: str
    repeat: int
    side: int
    xz: np.ndarray
    label: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.xz)


def parse_profile_name(relpath: str) -> tuple[str, int, int]:
    """``(position, repeat, side)`` from a profile's relative path (see module doc)."""
    p = Path(relpath)
    m = _NAME.match(p.stem)
    folder = p.parent.as_posix()
    if not m:
        return f"{folder}/{p.stem}", 0, 1
    neg = m.group("neg") is not None
    return f"{folder}/{'m_' if neg else ''}{m.group('pos')}", int(m.group("rep")), -1 if neg else 1


def _read_csv(path: Path) -> np.ndarray:
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ProfileDataError(f"cannot read {path}: {e}") from e
    rows: list[list[float]] = []
    width = None
    for i, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [t for t in re.split(r"[,\s;]+", s) if t]
        try:
            vals = [float(t) for t in parts]
        except ValueError:
            if not rows and i == 1:  # a header line
                continue
            raise ProfileDataError(f"{path}:{i}: not a number in {s[:60]!r}") from None
        if len(vals) not in (2, 3) or (width is not None and len(vals) != width):
            raise ProfileDataError(f"{path}:{i}: expected x, z[, label] ({width or '2 or 3'} values), "
                                   f"got {len(vals)}")
        width = len(vals)
        rows.append(vals)
    if not rows:
        raise ProfileDataError(f"{path}: no points")
    return np.asarray(rows, dtype=np.float64)


def _read_numpy(path: Path) -> np.ndarray:
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                if "xz" not in z:
                    raise ProfileDataError(f"{path}: no array 'xz' (arrays: {sorted(z.files)})")
                xz = np.asarray(z["xz"], dtype=np.float64)
                if xz.ndim != 2 or xz.shape[1] != 2:
                    raise ProfileDataError(f"{path}: 'xz' must be (N, 2), got {xz.shape}")
                if "label" in z:
                    lab = np.asarray(z["label"], dtype=np.float64).reshape(-1)
                    if len(lab) != len(xz):
                        raise ProfileDataError(f"{path}: 'label' has {len(lab)} values for {len(xz)} points")
                    return np.column_stack([xz, lab])
                return xz
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ProfileDataError(f"cannot read {path}: {e}") from e
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] not in (2, 3):
        raise ProfileDataError(f"{path}: expected an (N, 2) or (N, 3) array of x, z[, label], got {a.shape}")
    return a


def read_profile(path: str | Path, root: str | Path | None = None, side: int | None = None) -> ProfileRecord:
    """Read one profile file (CSV, .npy or .npz; see module doc). ``root``: the folder names are relative to
    (default: the file's folder). ``side`` overrides the sign taken from the name."""
    path = Path(path)
    if not path.is_file():
        raise ProfileDataError(f"profile file {path} does not exist")
    a = _read_numpy(path) if path.suffix in (".npy", ".npz") else _read_csv(path)
    finite = np.all(np.isfinite(a[:, :2]), axis=1)
    a = a[finite]
    if len(a) == 0:
        raise ProfileDataError(f"{path}: no finite point")
    label = None
    if a.shape[1] == 3:
        if not np.all(np.isin(a[:, 2], (0.0, 1.0))):
            raise ProfileDataError(f"{path}: labels must be 0 or 1")
        label = a[:, 2].astype(np.int8)
    rel = path.relative_to(root).as_posix() if root is not None else path.name
    position, repeat, s = parse_profile_name(rel)
    return ProfileRecord(name=rel, position=position, repeat=repeat, side=side if side is not None else s,
                         xz=np.ascontiguousarray(a[:, :2]), label=label)


def load_profile_list(list_file: str | Path, root: str | Path | None = None) -> list[ProfileRecord]:
    """Every profile a list file names (one relative path per line; see module doc), in list order. ``root``:
    the folder the paths are relative to (default: the list file's folder)."""
    lf = Path(list_file)
    try:
        names = [s.strip() for s in lf.read_text().splitlines()]
    except (OSError, UnicodeDecodeError) as e:
        raise ProfileDataError(f"cannot read the profile list {lf}: {e}") from e
    base = Path(root) if root is not None else lf.parent
    names = [n.lstrip("/") for n in names if n and not n.startswith("#")]
    if not names:
        raise ProfileDataError(f"{lf}: the list names no profile")
    return [read_profile(base / n, root=base) for n in names]
