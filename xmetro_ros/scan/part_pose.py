"""The pose of a part as a user gives it, one convention everywhere: **x, y, z in metres and the quaternion qx, qy,
qz, qw** (REP 103, ROS order), part → scan frame — the 7 numbers of the node's ``cad_pose`` parameter, of
``xmetro predict --cad-pose``, of ``xmetro parts scan --pose`` and of the ``pose=`` of a mesh artifact
(``mesh:path=PART.stl,pose=x;y;z;qx;qy;qz;qw``). Inside the package a pose is the (4, 4) rigid transform in
millimetres (docs/conventions.md); this module converts both ways.

Up to 0.5 the command line took the pose as 12 numbers, the first three rows of that 4×4 matrix in millimetres.
That form is refused with :class:`PoseError`, whose message says what changed and, when the 12 numbers are a rigid
transform, gives the same pose in the 7 numbers to paste instead.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

import numpy as np

from .geometry import matrix_to_quat, quat_to_matrix

__all__ = ["POSE_FORM", "PoseError", "format_pose7", "matrix_mm_to_pose7", "parse_pose7", "pose7_to_matrix_mm"]

#: What a user writes, for messages and help texts.
POSE_FORM = "x y z qx qy qz qw: metres and a quaternion (REP 103), part → scan frame, as the cad_pose parameter"

_MM_PER_M = 1000.0
_SPLIT = re.compile(r"[\s,;]+")


class PoseError(ValueError):
    """A part pose that is not 7 finite numbers with a non-zero quaternion (or the refused 12-number form)."""


def pose7_to_matrix_mm(values: Iterable[float]) -> np.ndarray:
    """``[x, y, z, qx, qy, qz, qw]`` (metres, quaternion in ROS order; normalised) → the (4, 4) rigid transform in
    millimetres. Raises :class:`PoseError` on a wrong count, a non-finite value or a zero quaternion."""
    try:
        v = np.asarray(list(values), dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise PoseError(f"a pose needs 7 finite numbers x, y, z, qx, qy, qz, qw: {e}") from e
    if v.shape != (7,) or not np.isfinite(v).all():
        raise PoseError(f"a pose needs 7 finite numbers x, y, z, qx, qy, qz, qw, got {v.tolist()}")
    if float(np.sum(v[3:] ** 2)) < 1e-12:
        raise PoseError(f"the quaternion qx, qy, qz, qw of the pose {v.tolist()} is zero")
    t = np.eye(4)
    t[:3, :3] = quat_to_matrix(v[3:])
    t[:3, 3] = v[:3] * _MM_PER_M
    return t


def matrix_mm_to_pose7(t: np.ndarray) -> list[float]:
    """(4, 4) rigid transform in millimetres → ``[x, y, z (m), qx, qy, qz, qw]`` (qw ≥ 0)."""
    t = np.asarray(t, dtype=np.float64)
    return [*(t[:3, 3] / _MM_PER_M).tolist(), *matrix_to_quat(t[:3, :3]).tolist()]


def format_pose7(pose: np.ndarray | Iterable[float], sep: str = " ") -> str:
    """The 7 numbers of a pose (a (4, 4) mm transform or the 7 numbers themselves), ``sep``-separated, 12
    significant digits (−0 written 0)."""
    a = np.asarray(pose if isinstance(pose, np.ndarray) else list(pose), dtype=np.float64)
    vals = matrix_mm_to_pose7(a) if a.shape == (4, 4) else a.reshape(-1).tolist()
    return sep.join(f"{(0.0 if abs(x) < 1e-15 else x):.12g}" for x in vals)


def _old_form(vals: list[float], what: str, sep: str) -> PoseError:
    t = np.eye(4)
    t[:3, :] = np.reshape(vals, (3, 4))
    r = t[:3, :3]
    msg = (f"{what}: 12 numbers (3 rows of a 4×4 matrix in millimetres) is the form of xmetro ≤ 0.5, no longer read; "
           f"a part pose is now 7 numbers, {POSE_FORM}. ")
    if np.isfinite(t).all() and np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0:
        return PoseError(msg + f"The same pose: \"{format_pose7(t, sep)}\" (translation / 1000, the rotation as a "
                               "quaternion)")
    return PoseError(msg + "(The first 3×3 of these 12 numbers is not a rotation: there is no equivalent.)")


def parse_pose7(text: str | Iterable[float] | None, *, what: str = "pose", sep: str = " ") -> np.ndarray:
    """A part pose given by a user → the (4, 4) transform in millimetres; None / empty → identity.

    ``text``: 7 numbers separated by spaces, commas or semicolons (or a sequence of 7 numbers): x, y, z in metres,
    qx, qy, qz, qw (normalised). ``what`` names the option in messages; ``sep`` separates the numbers of the
    equivalent suggested for the refused 12-number form.

    Raises:
        PoseError: not numbers, not 7 of them, non-finite, a zero quaternion; 12 numbers (the old millimetre
            matrix form), with the 7-number equivalent when they form a rigid transform.
    """
    if text is None:
        return np.eye(4)
    if isinstance(text, str):
        items = [x for x in _SPLIT.split(text.strip().strip("[]()")) if x]
        if not items:
            return np.eye(4)
        try:
            vals = [float(x) for x in items]
        except ValueError as e:
            raise PoseError(f"{what} {text!r}: not numbers ({e}); expected 7 numbers, {POSE_FORM}") from e
    else:
        try:
            vals = [float(x) for x in text]
        except (TypeError, ValueError) as e:
            raise PoseError(f"{what}: not numbers ({e}); expected 7 numbers, {POSE_FORM}") from e
    if len(vals) == 12:
        raise _old_form(vals, what, sep)
    if len(vals) != 7:
        raise PoseError(f"{what} needs 7 numbers, {POSE_FORM}; got {len(vals)}")
    try:
        return pose7_to_matrix_mm(vals)
    except PoseError as e:
        raise PoseError(f"{what}: {e}") from e
