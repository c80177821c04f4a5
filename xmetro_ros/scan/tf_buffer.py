"""A ROS-free transform buffer: the tree of frames /tf and /tf_static describe, looked up at any stamp.

What it models (tf2's buffer, without ROS; docs/profile-streams.md):

- **Edges**: each frame (``child``) has at most one ``parent``; an edge carries ``T(parent ← child)``: the child's
  origin (translation, **metres**, in the parent frame) and orientation (unit quaternion ``(x, y, z, w)``, ROS
  order) – the content of one ``geometry_msgs/TransformStamped``. A **static** edge (/tf_static, e.g. the hand-eye
  flange → sensor) holds one transform valid at every stamp; a **dynamic** edge (/tf, e.g. the robot's joints) keeps
  a history of stamped samples, at most ``cache_time_ns`` older than its newest sample (default 10 s).
- **Lookup** ``T(target ← source)`` at a stamp (int nanoseconds): the two frames' chains are walked up to their
  nearest common ancestor, so edges are chained in any direction (inverted where walked downward). Each dynamic
  edge is interpolated between its two samples bracketing the stamp: translation linearly, rotation by SLERP (the
  shorter arc). Beyond the newest or before the oldest sample a stamp is answered only within
  ``max_extrapolation_ns`` (default 0: never), extrapolated linearly from the two end samples (held, with one).
- **Batch lookup**: one call for many stamps (all the profiles of a scan), vectorised over the stamps.
- **Failures** carry a :class:`TfErrorCode`: ``UNKNOWN_FRAME`` (never seen: the tf is missing), ``NOT_CONNECTED``
  (both known, no path between them), ``EXTRAPOLATION_FUTURE`` (newer than the newest sample beyond the bound: the
  tf is late, a caller may retry once more arrives), ``EXTRAPOLATION_PAST`` (older than the history: final),
  ``INVALID_TRANSFORM`` (a rejected input: not finite, zero quaternion, empty or equal frame names, a loop).
  :meth:`TransformBuffer.lookup` raises :class:`TransformError`; :meth:`TransformBuffer.check` and
  :meth:`TransformBuffer.lookup_batch` (``raise_on_error=False``) answer without raising.

A frame looked up in itself is the identity, known or not; frame names lose a leading ``/`` (as tf2 does).
A record for a child that already has another parent (or switches static ⇄ dynamic) replaces its edge and
history. Inputs are plain records (:class:`TransformRecord`), so the ROS side feeds ``tf2_msgs/TFMessage`` in by
copying fields. Thread-safe: one lock around every insert and lookup.
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "BatchLookup",
    "TfErrorCode",
    "TransformBuffer",
    "TransformError",
    "TransformRecord",
    "invert_transforms",
    "matrices_to_quats",
    "quats_to_matrices",
    "slerp",
]

_SLERP_LINEAR_BELOW = 1e-6  # angle (rad) under which SLERP falls back to normalised linear interpolation


class TfErrorCode(str, enum.Enum):
    """Why a transform cannot be had (the ``code`` of :class:`TransformError`; ``OK`` only in batch statuses)."""

    OK = "OK"
    UNKNOWN_FRAME = "UNKNOWN_FRAME"
    NOT_CONNECTED = "NOT_CONNECTED"
    EXTRAPOLATION_FUTURE = "EXTRAPOLATION_FUTURE"
    EXTRAPOLATION_PAST = "EXTRAPOLATION_PAST"
    INVALID_TRANSFORM = "INVALID_TRANSFORM"

    @property
    def retryable(self) -> bool:
        """True where later tf data may still make the lookup succeed (a missing, unconnected or late frame);
        False for ``EXTRAPOLATION_PAST`` (the history never grows backwards) and ``INVALID_TRANSFORM``."""
        return self in (TfErrorCode.UNKNOWN_FRAME, TfErrorCode.NOT_CONNECTED, TfErrorCode.EXTRAPOLATION_FUTURE)


# Batch statuses as small integers (index into this tuple).
_CODES: tuple[TfErrorCode, ...] = tuple(TfErrorCode)
_OK, _FUTURE, _PAST = (_CODES.index(c) for c in (TfErrorCode.OK, TfErrorCode.EXTRAPOLATION_FUTURE,
                                                  TfErrorCode.EXTRAPOLATION_PAST))
assert _OK < _FUTURE < _PAST  # _worse relies on it


class TransformError(LookupError):
    """A transform that cannot be had or a record that cannot be stored.

    Attributes:
        code: the :class:`TfErrorCode`.
        target, source: the frames of the lookup (``T(target ← source)``), or parent and child of a rejected record.
        stamp_ns: the stamp asked for (ns), None where the failure does not depend on it.
    """

    def __init__(self, code: TfErrorCode, message: str, target: str = "", source: str = "",
                 stamp_ns: int | None = None) -> None:
        super().__init__(f"{code.value}: {message}")
        self.code = code
        self.target = target
        self.source = source
        self.stamp_ns = stamp_ns


@dataclass(frozen=True)
class TransformRecord:
    """One stamped transform ``T(parent ← child)`` (the fields of a ``geometry_msgs/TransformStamped``).

    Attributes:
        stamp_ns: time of the sample, ns (``header.stamp``); ignored for static transforms.
        parent: ``header.frame_id``. child: ``child_frame_id``.
        translation: the child's origin in the parent frame, metres.
        rotation: the child's orientation in the parent frame, quaternion ``(x, y, z, w)`` (normalised on insert).
    """

    stamp_ns: int
    parent: str
    child: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]


@dataclass
class BatchLookup:
    """The answer of :meth:`TransformBuffer.lookup_batch` without raising.

    Attributes:
        matrices: (K, 4, 4) ``T(target ← source)`` per stamp, translation in metres; NaN where not ``ok``.
        status: (K,) int8, index into :data:`TfErrorCode` order (0 = ``OK``); :meth:`codes` names them.
    """

    matrices: np.ndarray
    status: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        """(K,) bool: the stamps that were answered."""
        return np.asarray(self.status == _OK)

    def codes(self) -> list[TfErrorCode]:
        """The status of each stamp as a :class:`TfErrorCode`."""
        return [_CODES[int(s)] for s in self.status]


# -- quaternion helpers (vectorised; (x, y, z, w) order) ----------------------------------------------------------

def quats_to_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (K, 3, 3) from unit quaternions (K, 4) ``(x, y, z, w)`` (normalised here)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty((*q.shape[:-1], 3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - z * w)
    out[..., 0, 2] = 2 * (x * z + y * w)
    out[..., 1, 0] = 2 * (x * y + z * w)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - x * w)
    out[..., 2, 0] = 2 * (x * z - y * w)
    out[..., 2, 1] = 2 * (y * z + x * w)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def matrices_to_quats(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (K, 4) ``(x, y, z, w)``, w ≥ 0, from rotation matrices (K, 3, 3) (Shepperd's method)."""
    r = np.asarray(r, dtype=float)
    m = r.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], tr], axis=1)
    k = np.argmax(diag, axis=1)
    q = np.empty((m.shape[0], 4))
    # Each branch computes the largest component first (numerically stable), then the others from it.
    for case in range(4):
        sel = k == case
        if not np.any(sel):
            continue
        a = m[sel]
        if case == 3:
            s = 2.0 * np.sqrt(1.0 + tr[sel])
            q[sel] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s,
                               (a[:, 1, 0] - a[:, 0, 1]) / s, 0.25 * s], axis=1)
        else:
            i, j, kk = case, (case + 1) % 3, (case + 2) % 3
            s = 2.0 * np.sqrt(np.maximum(1.0 + a[:, i, i] - a[:, j, j] - a[:, kk, kk], 1e-300))
            comp = np.empty((a.shape[0], 4))
            comp[:, i] = 0.25 * s
            comp[:, j] = (a[:, j, i] + a[:, i, j]) / s
            comp[:, kk] = (a[:, kk, i] + a[:, i, kk]) / s
            comp[:, 3] = (a[:, kk, j] - a[:, j, kk]) / s
            q[sel] = comp
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape((*r.shape[:-2], 4))


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (K, 4) at fractions ``u`` (K,), along the shorter arc.

    ``u`` = 0 gives ``q0``, 1 gives ``q1`` (up to sign); values outside [0, 1] extrapolate along the same great
    circle. Under :data:`_SLERP_LINEAR_BELOW` rad the normalised linear interpolation is used (no 0/0).
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    u = np.asarray(u, dtype=float)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin_t = np.sin(theta)
    small = theta < _SLERP_LINEAR_BELOW
    safe = np.where(small, 1.0, sin_t)
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * theta) / safe)
    w1 = np.where(small, u, np.sin(u * theta) / safe)
    out = w0 * q0 + w1 * q1
    return np.asarray(out / np.linalg.norm(out, axis=-1, keepdims=True))


def invert_transforms(t: np.ndarray) -> np.ndarray:
    """Inverses of rigid transforms (…, 4, 4): ``[Rᵀ, −Rᵀ p]``."""
    t = np.asarray(t, dtype=float)
    out = np.zeros_like(t)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _compose(rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """(K, 4, 4) from rotations (K, 3, 3) and translations (K, 3)."""
    out = np.zeros((rot.shape[0], 4, 4))
    out[:, :3, :3] = rot
    out[:, :3, 3] = trans
    out[:, 3, 3] = 1.0
    return out


# -- the edges ---------------------------------------------------------------------------------------------------

class _Edge:
    """``T(parent ← child)``: one sample (static) or a stamp-sorted history (dynamic).

    The history lives in arrays with spare capacity (rows ``lo:hi`` are live): an in-order sample is written in
    place (amortised O(1)), pruning moves ``lo``; only an out-of-order sample rebuilds the arrays."""

    def __init__(self, parent: str, static: bool) -> None:
        self.parent = parent
        self.static = static
        self.matrix: np.ndarray | None = None  # T(parent ← child) of a static edge (4, 4)
        self._t = np.zeros(16, dtype=np.int64)
        self._p = np.zeros((16, 3))
        self._q = np.zeros((16, 4))
        self._lo = self._hi = 0

    @property
    def stamps(self) -> np.ndarray:
        return self._t[self._lo:self._hi]

    @property
    def trans(self) -> np.ndarray:
        return self._p[self._lo:self._hi]

    @property
    def quats(self) -> np.ndarray:
        return self._q[self._lo:self._hi]

    def _set(self, t: np.ndarray, p: np.ndarray, q: np.ndarray) -> None:
        cap = max(16, 2 * t.shape[0])
        self._t, self._p, self._q = np.zeros(cap, dtype=np.int64), np.zeros((cap, 3)), np.zeros((cap, 4))
        n = t.shape[0]
        self._t[:n], self._p[:n], self._q[:n] = t, p, q
        self._lo, self._hi = 0, n

    def insert(self, stamps: np.ndarray, trans: np.ndarray, quats: np.ndarray, cache_ns: int) -> tuple[int, int]:
        """Add samples (sorted or not). Returns (stored, ignored): a stamp already present or older than the
        cache window behind the newest sample is ignored (tf2's TF_REPEATED_DATA / TF_OLD_DATA)."""
        if self.static:
            self._set(stamps[-1:], trans[-1:], quats[-1:])
            self.matrix = _compose(quats_to_matrices(quats[-1:]), trans[-1:])[0]
            return 1, 0
        n_in = stamps.shape[0]
        if n_in > 1:
            order = np.argsort(stamps, kind="stable")
            stamps, trans, quats = stamps[order], trans[order], quats[order]
            _, first = np.unique(stamps, return_index=True)  # one sample per stamp within the input (the first)
            stamps, trans, quats = stamps[first], trans[first], quats[first]
        old = self.stamps
        newest = int(max(stamps[-1], old[-1])) if old.size else int(stamps[-1])
        in_order = old.size == 0 or stamps[0] > old[-1]
        keep = stamps >= newest - cache_ns
        if not in_order:
            keep &= ~np.isin(stamps, old)
        stamps, trans, quats = stamps[keep], trans[keep], quats[keep]
        stored = stamps.shape[0]
        if stored and in_order:  # the common case: append in place
            if self._hi + stored > self._t.shape[0]:
                self._set(np.concatenate([old, stamps]), np.concatenate([self.trans, trans]),
                          np.concatenate([self.quats, quats]))
            else:
                sl = slice(self._hi, self._hi + stored)
                self._t[sl], self._p[sl], self._q[sl] = stamps, trans, quats
                self._hi += stored
        elif stored:
            t_all = np.concatenate([old, stamps])
            o = np.argsort(t_all, kind="stable")
            self._set(t_all[o], np.concatenate([self.trans, trans])[o], np.concatenate([self.quats, quats])[o])
        self._lo += int(np.searchsorted(self.stamps, newest - cache_ns, side="left"))
        return stored, n_in - stored

    def sample(self, t: np.ndarray, max_ex: int) -> tuple[np.ndarray, np.ndarray]:
        """(K, 4, 4) ``T(parent ← child)`` at stamps ``t`` (K,) and the (K,) status (``_OK`` / ``_FUTURE`` /
        ``_PAST``); NaN where not OK."""
        k = t.shape[0]
        if self.matrix is not None:
            return np.broadcast_to(self.matrix, (k, 4, 4)), np.zeros(k, dtype=np.int8)
        s = self.stamps
        n = s.shape[0]
        status = np.zeros(k, dtype=np.int8)
        status[t > s[-1] + max_ex] = _FUTURE
        status[t < s[0] - max_ex] = _PAST
        if n == 1:
            out = np.repeat(_compose(quats_to_matrices(self.quats[:1]), self.trans[:1]), k, axis=0)
        else:
            i0 = np.clip(np.searchsorted(s, t, side="right") - 1, 0, n - 2)
            i1 = i0 + 1
            u = (t - s[i0]).astype(float) / (s[i1] - s[i0]).astype(float)
            # (1 − u)·p0 + u·p1: exact at both samples
            p = (1.0 - u)[:, None] * self.trans[i0] + u[:, None] * self.trans[i1]
            q = slerp(self.quats[i0], self.quats[i1], u)
            out = _compose(quats_to_matrices(q), p)
        out[status != _OK] = np.nan
        return out, status


def _clean(frame: str) -> str:
    return frame[1:] if frame.startswith("/") else frame


# -- the buffer --------------------------------------------------------------------------------------------------

class TransformBuffer:
    """Static and dynamic transforms with a bounded history per edge; lookups at stamps (see the module doc).

    Args:
        cache_time_ns: history kept per dynamic edge, ns behind its newest sample (tf2's default: 10 s).
        max_extrapolation_ns: how far beyond the newest / before the oldest sample of a dynamic edge a lookup is
            still answered (linear extrapolation), ns; 0 = never (tf2's behaviour).
    """

    def __init__(self, cache_time_ns: int = 10_000_000_000, max_extrapolation_ns: int = 0) -> None:
        if not cache_time_ns > 0:
            raise ValueError(f"cache_time_ns must be > 0, got {cache_time_ns}")
        if not max_extrapolation_ns >= 0:
            raise ValueError(f"max_extrapolation_ns must be >= 0, got {max_extrapolation_ns}")
        self.cache_time_ns = int(cache_time_ns)
        self.max_extrapolation_ns = int(max_extrapolation_ns)
        self._edges: dict[str, _Edge] = {}
        self._lock = threading.RLock()
        self.stats = {"stored": 0, "ignored": 0, "reparented": 0, "rejected": 0}
        self._version = 0

    @property
    def version(self) -> int:
        """A number that changes whenever the stored transforms do (a caller waiting for tf can skip retries)."""
        return self._version

    # -- input ---------------------------------------------------------------------------------------------------
    def set_transform(self, record: TransformRecord, static: bool = False) -> None:
        """Store one transform (from /tf, or /tf_static with ``static=True``). Raises :class:`TransformError`
        (``INVALID_TRANSFORM``) on a rejected record; nothing is stored then."""
        self.set_transform_arrays(record.parent, record.child, np.array([record.stamp_ns], dtype=np.int64),
                                  np.asarray([record.translation], dtype=float),
                                  np.asarray([record.rotation], dtype=float), static=static)

    def set_transforms(self, records: Iterable[TransformRecord], static: bool = False) -> int:
        """Store many records (one TFMessage); returns how many were rejected (the others are stored)."""
        rejected = 0
        for r in records:
            try:
                self.set_transform(r, static=static)
            except TransformError:
                rejected += 1
        return rejected

    def set_transform_arrays(self, parent: str, child: str, stamps_ns: np.ndarray | Sequence[int],
                             translations: np.ndarray, rotations: np.ndarray, static: bool = False) -> None:
        """Store many samples of one edge at once: stamps (n,) ns, translations (n, 3) m, quaternions (n, 4)
        ``(x, y, z, w)``. A static edge keeps the last. Raises :class:`TransformError` (``INVALID_TRANSFORM``)."""
        parent, child = _clean(parent), _clean(child)
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        trans = np.asarray(translations, dtype=float).reshape(-1, 3)
        quats = np.asarray(rotations, dtype=float).reshape(-1, 4)

        def bad(msg: str) -> TransformError:
            self.stats["rejected"] += 1
            return TransformError(TfErrorCode.INVALID_TRANSFORM, msg, parent, child)

        with self._lock:
            if not parent or not child or parent == child:
                raise bad(f"frame names must be non-empty and differ (parent {parent!r}, child {child!r})")
            if not (stamps.shape[0] == trans.shape[0] == quats.shape[0]) or stamps.shape[0] == 0:
                raise bad("stamps, translations and rotations must have the same, non-zero length")
            norms = np.linalg.norm(quats, axis=1)
            if not (np.all(np.isfinite(trans)) and np.all(np.isfinite(norms)) and np.all(norms > 1e-9)):
                raise bad(f"{parent} ← {child}: translation or quaternion not finite, or a zero quaternion")
            anc = self._chain(parent)
            if child in anc:
                raise bad(f"{parent} ← {child} would close a loop ({' → '.join(anc)})")
            edge = self._edges.get(child)
            if edge is None or edge.parent != parent or edge.static != static:
                if edge is not None:
                    self.stats["reparented"] += 1
                edge = self._edges[child] = _Edge(parent=parent, static=static)
            stored, ignored = edge.insert(stamps, trans, quats / norms[:, None], self.cache_time_ns)
            self.stats["stored"] += stored
            self.stats["ignored"] += ignored
            self._version += 1

    def clear(self) -> None:
        """Forget every transform (a time jump backwards, e.g. a bag looped)."""
        with self._lock:
            self._edges.clear()
            self._version += 1

    # -- the tree ------------------------------------------------------------------------------------------------
    @property
    def frames(self) -> set[str]:
        """Every frame named so far (parents and children)."""
        with self._lock:
            return set(self._edges) | {e.parent for e in self._edges.values()}

    def parent_of(self, frame: str) -> str | None:
        """The parent of ``frame``, None for a root or an unknown frame."""
        with self._lock:
            e = self._edges.get(_clean(frame))
            return None if e is None else e.parent

    def _chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to its root."""
        out = [frame]
        while (e := self._edges.get(out[-1])) is not None:
            out.append(e.parent)
        return out

    def time_range(self, target: str, source: str) -> tuple[int, int] | None:
        """The stamps (ns) the path answers without extrapolation: (latest oldest sample, earliest newest sample)
        over its dynamic edges; (−2⁶³, 2⁶³ − 1) for an all-static path; None without a path or when empty."""
        with self._lock:
            try:
                up, down = self._path(_clean(target), _clean(source), None)
            except TransformError:
                return None
            lo, hi = np.iinfo(np.int64).min, np.iinfo(np.int64).max
            for f in up + down:
                e = self._edges[f]
                if not e.static:
                    lo, hi = max(lo, int(e.stamps[0])), min(hi, int(e.stamps[-1]))
            return (int(lo), int(hi)) if lo <= hi else None

    def _path(self, target: str, source: str, stamp: int | None) -> tuple[list[str], list[str]]:
        """Edges (their child frames) from ``source`` up to the common ancestor, and from ``target`` up to it."""
        known = set(self._edges) | {e.parent for e in self._edges.values()}
        for f in (target, source):
            if f not in known:
                raise TransformError(TfErrorCode.UNKNOWN_FRAME, f"frame {f!r} is not in the tree (no tf names it)",
                                     target, source, stamp)
        a, b = self._chain(source), self._chain(target)
        common = next((f for f in a if f in set(b)), None)
        if common is None:
            raise TransformError(TfErrorCode.NOT_CONNECTED,
                                 f"{source!r} (root {a[-1]!r}) and {target!r} (root {b[-1]!r}) are not connected",
                                 target, source, stamp)
        return a[: a.index(common)], b[: b.index(common)]

    # -- lookups -------------------------------------------------------------------------------------------------
    def lookup_batch(self, target: str, source: str, stamps_ns: np.ndarray | Sequence[int],
                     raise_on_error: bool = True) -> BatchLookup:
        """``T(target ← source)`` at every stamp (K,), one vectorised pass per edge of the path.

        Raises :class:`TransformError` (``UNKNOWN_FRAME`` / ``NOT_CONNECTED`` always; with ``raise_on_error`` also
        the first stamp's extrapolation failure, ``EXTRAPOLATION_PAST`` before ``EXTRAPOLATION_FUTURE``).
        Without it, per-stamp failures are in :attr:`BatchLookup.status`: ``EXTRAPOLATION_PAST`` where any edge is
        too old (final), else ``EXTRAPOLATION_FUTURE`` where any edge is too new (retry later).
        """
        target, source = _clean(target), _clean(source)
        t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        k = t.shape[0]
        if target == source:  # tf2: the identity, whether or not the frame is known
            return BatchLookup(matrices=np.broadcast_to(np.eye(4), (k, 4, 4)).copy(), status=np.zeros(k, np.int8))
        with self._lock:
            up, down = self._path(target, source, int(t[0]) if k else None)
            status = np.zeros(k, dtype=np.int8)
            t_anc_src = np.broadcast_to(np.eye(4), (k, 4, 4)).copy()
            for f in reversed(up):  # T(anc ← source) = T(anc ← a1) … T(p ← source), source-side edges last
                m, s = self._edges[f].sample(t, self.max_extrapolation_ns)
                t_anc_src = t_anc_src @ m
                status = _worse(status, s)
            t_anc_tgt = np.broadcast_to(np.eye(4), (k, 4, 4)).copy()
            for f in reversed(down):
                m, s = self._edges[f].sample(t, self.max_extrapolation_ns)
                t_anc_tgt = t_anc_tgt @ m
                status = _worse(status, s)
        out = invert_transforms(t_anc_tgt) @ t_anc_src if down else t_anc_src
        out[status != _OK] = np.nan
        if raise_on_error and np.any(status != _OK):
            code = _CODES[_PAST] if np.any(status == _PAST) else _CODES[_FUTURE]
            i = int(np.flatnonzero(status == _CODES.index(code))[0])
            raise TransformError(code, self._extrapolation_message(code, target, source, int(t[i]), up + down),
                                 target, source, int(t[i]))
        return BatchLookup(matrices=out, status=status)

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """``T(target ← source)`` (4, 4), translation in metres, at ``stamp_ns``. Raises :class:`TransformError`."""
        return self.lookup_batch(target, source, [stamp_ns]).matrices[0]

    def check(self, target: str, source: str, stamp_ns: int) -> TfErrorCode:
        """``OK`` when :meth:`lookup` would answer now, else why not (never raises): "can I transform at t yet?"."""
        try:
            res = self.lookup_batch(target, source, [stamp_ns], raise_on_error=False)
        except TransformError as e:
            return e.code
        return _CODES[int(res.status[0])]

    def can_transform(self, target: str, source: str, stamp_ns: int) -> bool:
        """True when ``T(target ← source)`` can be had at ``stamp_ns`` now."""
        return self.check(target, source, stamp_ns) is TfErrorCode.OK

    def _extrapolation_message(self, code: TfErrorCode, target: str, source: str, stamp: int,
                               edges: list[str]) -> str:
        spans = []
        for f in edges:
            e = self._edges[f]
            if not e.static:
                spans.append(f"{e.parent} ← {f}: [{int(e.stamps[0])}, {int(e.stamps[-1])}] ns")
        way = "newer than" if code is TfErrorCode.EXTRAPOLATION_FUTURE else "older than"
        return (f"{target} ← {source} at {stamp} ns is {way} the tf history beyond the "
                f"{self.max_extrapolation_ns} ns extrapolation bound ({'; '.join(spans)})")


def _worse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Combine per-stamp statuses: PAST (final) wins over FUTURE (retryable), which wins over OK (their order in
    :class:`TfErrorCode`, so the larger index)."""
    return np.maximum(a, b)
