"""Run a model set (ONNX files + ``card.json``) with ONNX Runtime: per-point errors in mm for the x, y, z axes.

A model set directory holds ``card.json`` and one or more ONNX files; each file covers one or more axes:
* ``kind: "points"`` (DT, SVR, MLP, CatBoost, one axis each): input ``X`` (N, F) float32 → ``y`` (N, 1) mm.
* ``kind: "sets"`` (PointNet): input ``X`` (B, n, F) → ``y`` (B, n, A) mm. The points of one call are treated as
  one cloud, partitioned into sets of ``card["set_size"]`` by a permutation seeded with
  ``card["partition_seed"]`` (see :func:`xmetro_ros.learn.pointnet.partition_sets` and ``card["global_feature"]``).
Features are the card's ``feature_names`` in order, in the units of ``feature_units`` (the study's: mm, deg, ms,
per mm). Predictions are the systematic error nominal − measured, mm, in the scan frame's axes.

Uncertainty (:meth:`ModelSet.predict_with_uncertainty`): a PointNet member with a second ONNX output
``log_sigma`` gives σ̂ per point and axis (mm); a member without one counts as σ̂ = 1 mm (plain absolute-residual
conformal). The card's ``uncertainty`` block (written by :func:`xmetro_ros.learn.uncertainty.calibrate`) holds the
split-conformal multiplier per axis: U (95 %) = multiplier × (σ̂ + σ floor). The card's ``domain_mv`` block is
the multivariate domain: the Mahalanobis distance of the standardized features from the training mean, with a
threshold = a high quantile of the training points' distances; outside it U is widened by the factor
distance / threshold (the
distance in units of the threshold: U grows linearly with how far the point is from what the model learned).
"""

from __future__ import annotations

import hashlib
import json
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .pointsets import partition_sets
from .resources import default_model_dir

__all__ = ["AXES", "CARD_FORMAT", "ModelLoadError", "ModelSet", "UncertainPrediction"]

CARD_FORMAT = "xmetro-model-set/1"
AXES = ("x", "y", "z")
_SET_CHUNK = 128  # sets per ONNX Runtime call: activations stay cache-sized (measured ~2x faster than 1024)


class ModelLoadError(RuntimeError):
    """A model set that cannot be used: missing directory or file, corrupt ONNX, or a card that does not match."""


@dataclass
class _Member:
    family: str
    kind: str  # "points" | "sets"
    axes: tuple[int, ...]
    session: Any
    path: Path
    sigma: bool = False  # the ONNX graph has a second output log_sigma (spread head)


@dataclass
class UncertainPrediction:
    """Predictions with their expanded uncertainty for the rows of one cloud (mm, scan frame axes).

    Attributes:
        errors: (M, 3) predicted systematic error, as ``ModelSet.predict``.
        U: (M, 3) expanded uncertainty (95 % unless the card says otherwise): the true error lies in
            errors ± U with that probability; widened outside the domain.
        sigma: (M, 3) σ̂ of the model (1 where a member has no spread output).
        domain_distance: (M,) multivariate domain distance in units of its threshold (> 1: outside); NaN when
            the card has no multivariate domain.
        out_of_domain: (M,) bool: outside the multivariate domain (the min/max check when there is none).
    """

    errors: np.ndarray
    U: np.ndarray
    sigma: np.ndarray
    domain_distance: np.ndarray
    out_of_domain: np.ndarray


class ModelSet:
    """A loaded model set. ``predict`` is thread-safe (ONNX Runtime sessions are)."""

    def __init__(self, model_dir: Path, card: dict, members: list[_Member]) -> None:
        self.model_dir = model_dir
        self.card = card
        self.id: str = str(card["id"])
        self.feature_names: list[str] = list(card["feature_names"])
        self.feature_units: list[str] = list(card.get("feature_units") or [""] * len(self.feature_names))
        self.axes = AXES
        self.members = members
        self.set_size = int(card.get("set_size", 50))
        self.partition_seed = int(card.get("partition_seed", 0))
        dom = card.get("domain") or {}
        if dom:
            lo, hi = np.asarray(dom["lo"], np.float64), np.asarray(dom["hi"], np.float64)
        else:
            lo = np.full(len(self.feature_names), -np.inf)
            hi = np.full(len(self.feature_names), np.inf)
        # Feature min/max seen in training (card); the node widens it by its domain_margin (card "margin").
        self.domain: tuple[np.ndarray, np.ndarray] = (lo, hi)
        self.domain_margin = float(dom.get("margin", 0.05)) if dom else 0.0
        self._lock = threading.Lock()
        self._mv: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, model_dir: str | Path | None = None, *, threads: int = 1) -> ModelSet:
        """Load ``model_dir`` (None → the packaged default model). Raises ModelLoadError with the reason."""
        d = Path(model_dir) if model_dir is not None else default_model_dir()
        if not d.is_dir():
            raise ModelLoadError(f"model directory {d} does not exist")
        card_path = d / "card.json"
        try:
            card = json.loads(card_path.read_text())
        except FileNotFoundError as e:
            raise ModelLoadError(f"model directory {d} has no card.json") from e
        except (OSError, json.JSONDecodeError) as e:
            raise ModelLoadError(f"{card_path} cannot be read as JSON: {e}") from e
        cls._check_card(card, card_path)
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(threads))
        opts.inter_op_num_threads = 1
        members: list[Any] = []
        covered: list[int] = []
        for m in card["models"]:
            p = d / m["file"]
            if not p.is_file():
                raise ModelLoadError(f"model file {p} listed in the card is missing")
            if m.get("sha256") and hashlib.sha256(p.read_bytes()).hexdigest() != m["sha256"]:
                raise ModelLoadError(f"model file {p} does not match the card's sha256 (modified or corrupt)")
            try:
                sess = ort.InferenceSession(str(p), sess_options=opts, providers=["CPUExecutionProvider"])
            except Exception as e:
                raise ModelLoadError(f"ONNX Runtime cannot load {p}: {e}") from e
            shape = sess.get_inputs()[0].shape
            if isinstance(shape[-1], int) and shape[-1] != len(card["feature_names"]):
                raise ModelLoadError(
                    f"{p.name} takes {shape[-1]} features but the card lists {len(card['feature_names'])}"
                )
            axes = tuple(AXES.index(a) for a in m["axes"])
            covered.extend(axes)
            has_sigma = any(o.name == "log_sigma" for o in sess.get_outputs())
            members.append(_Member(m["family"], m["kind"], axes, sess, p, has_sigma))
        if sorted(covered) != [0, 1, 2]:
            raise ModelLoadError(f"{card_path}: the models must cover each of the axes x, y, z exactly once")
        return cls(d, card, members)

    @staticmethod
    def _check_card(card: Any, where: Path) -> None:
        if not isinstance(card, dict):
            raise ModelLoadError(f"{where}: card must be a JSON object")
        for key in ("id", "feature_names", "models"):
            if key not in card:
                raise ModelLoadError(f"{where}: card has no {key!r}")
        if card.get("format", CARD_FORMAT) != CARD_FORMAT:
            raise ModelLoadError(f"{where}: unsupported card format {card.get('format')!r} (expected {CARD_FORMAT})")
        names = card["feature_names"]
        if not names or not all(isinstance(n, str) for n in names) or len(set(names)) != len(names):
            raise ModelLoadError(f"{where}: feature_names must be a non-empty list of distinct strings")
        for m in card["models"]:
            if m.get("kind") not in ("points", "sets") or not m.get("file") or not m.get("axes"):
                raise ModelLoadError(f"{where}: model entry {m!r} needs file, kind (points|sets) and axes")
            if any(a not in AXES for a in m["axes"]):
                raise ModelLoadError(f"{where}: model entry {m.get('file')} has unknown axes {m['axes']}")
        dom = card.get("domain")
        if dom and (len(dom.get("lo", [])) != len(names) or len(dom.get("hi", [])) != len(names)):
            raise ModelLoadError(f"{where}: domain lo/hi must have one value per feature")

    # ------------------------------------------------------------------ features
    def required_fields(self) -> set[str]:
        """Per-point cloud fields the features need (e.g. ``intensity`` for ``field_intensity``)."""
        try:
            from .features import required_fields

            return set(required_fields(self.feature_names))
        except (ImportError, KeyError, ValueError):  # unknown features: check_features names them
            return {n[len("field_"):] for n in self.feature_names if n.startswith("field_")}

    def check_features(self, registry: Any) -> None:
        """Raise ModelLoadError naming the card's features that ``registry`` cannot compute."""
        missing = []
        for name in self.feature_names:
            if name.startswith("field_"):
                continue  # resolved dynamically from the cloud's fields
            try:
                registry.get(name)
            except (KeyError, ValueError):
                missing.append(name)
        if missing:
            raise ModelLoadError(f"model set {self.id!r} needs features the registry cannot compute: {missing}")

    def out_of_domain(self, X: np.ndarray, margin: float | None = None) -> np.ndarray:
        """(M,) bool: some feature outside the training range widened by ``margin`` (None → card's) × range."""
        lo, hi = self.domain
        m = self.domain_margin if margin is None else float(margin)
        pad = m * np.where(np.isfinite(hi - lo), hi - lo, 0.0)
        X = np.asarray(X)
        return np.any((X < lo - pad) | (X > hi + pad), axis=1)

    def domain_distance(self, X: np.ndarray) -> np.ndarray:
        """(M,) Mahalanobis distance of the rows from the training features, in units of the card's threshold
        (> 1: outside the multivariate domain); NaN rows for non-finite features; all NaN without ``domain_mv``."""
        dom = self.card.get("domain_mv")
        if not dom:
            return np.full(len(X), np.nan)
        if self._mv is None:
            # float32 and the mean folded into a bias: z = X·W − mean·W is one GEMM on the raw rows; dividing W by
            # the threshold gives the distance in threshold units directly.
            w = np.asarray(dom["whiten"], np.float64) / float(dom["threshold"])
            self._mv = (w.astype(np.float32), (np.asarray(dom["mean"], np.float64) @ w).astype(np.float32))
        w, b = self._mv
        z = np.asarray(X, np.float32) @ w
        z -= b
        return np.sqrt(np.einsum("ij,ij->i", z, z))

    def out_of_domain_mv(self, X: np.ndarray, distance: np.ndarray | None = None) -> np.ndarray:
        """(M,) bool: outside the multivariate domain (distance > threshold; ``distance`` = domain_distance(X) when
        already computed); the per-feature min/max check (:meth:`out_of_domain`) when the card has no
        multivariate domain."""
        if not self.card.get("domain_mv"):
            return self.out_of_domain(X)
        d = self.domain_distance(X) if distance is None else distance
        with np.errstate(invalid="ignore"):
            return d > 1.0

    # ------------------------------------------------------------------ prediction
    def _check_X(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float32)
        if X.ndim != 2 or X.shape[1] != len(self.feature_names):
            raise ValueError(
                f"model set {self.id!r} expects features of shape (M, {len(self.feature_names)}) "
                f"({', '.join(self.feature_names)}), got {X.shape}"
            )
        return X

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Errors (M, 3) float64 mm for the feature rows X (M, F) of ONE cloud/scan.

        Rows with a non-finite feature get NaN (they are also kept out of every PointNet set).
        """
        X = self._check_X(X)
        ok = np.all(np.isfinite(X), axis=1)
        if ok.all():
            return self.predict_batch(X[None])[0]
        out = np.full((len(X), 3), np.nan)
        if ok.any():
            out[ok] = self.predict_batch(X[ok][None])[0]
        return out

    def predict_batch(self, Xq: np.ndarray, output: str = "error") -> np.ndarray:
        """(Q, P, F) → (Q, P, 3): Q versions of the same P-point cloud, each predicted as ``predict`` would
        (same set partition for every version). Used by the SHAP explainer and the recommender. Rows must be
        finite. ``output="uncertainty"``: U as :meth:`predict_with_uncertainty` instead of the errors."""
        Xq = np.asarray(Xq, dtype=np.float32)
        q, p, f = Xq.shape
        out = np.empty((q, p, 3))
        if p == 0:
            return out
        idx, _ = partition_sets(p, self.set_size, self.partition_seed)
        sets = Xq[:, idx].reshape(-1, self.set_size, f)  # (Q*K, n, F); point-wise members ignore the grouping
        ys = self.predict_sets(sets) if output == "error" else self.predict_sets_uncertainty(sets)
        # Real entries are the first p of each version's flattened sets (only the last set is padded).
        out[:, idx.reshape(-1)[:p]] = ys.reshape(q, -1, 3)[:, :p]
        return out

    def predict_sets(self, sets: np.ndarray) -> np.ndarray:
        """(K, n, F) → (K, n, 3) mm: each of the K sets predicted as one PointNet set (the global feature is the
        max over its n rows); point-wise members predict every row on its own. Rows must be finite. This is how
        ``predict`` predicts each set of its partition, so a set of the partition given here gets exactly the
        published predictions of its points (the explainer relies on it)."""
        sets = np.asarray(sets, dtype=np.float32)
        k, n, f = sets.shape
        out = np.empty((k, n, 3))
        for m in self.members:
            if m.kind == "points":
                out[:, :, m.axes[0]] = m.session.run(None, {"X": sets.reshape(k * n, f)})[0].reshape(k, n)
                continue
            ys = np.empty((k, n, len(m.axes)), np.float32)
            for i in range(0, k, _SET_CHUNK):
                ys[i : i + _SET_CHUNK] = m.session.run(None, {"X": sets[i : i + _SET_CHUNK]})[0]
            out[:, :, list(m.axes)] = ys
        return out

    def predict_sets_sigma(self, sets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, n, F) → (errors (K, n, 3), σ̂ (K, n, 3)) mm, as :meth:`predict_sets`; σ̂ = 1 on the axes of members
        without a spread output."""
        sets = np.asarray(sets, dtype=np.float32)
        k, n, f = sets.shape
        out = np.empty((k, n, 3))
        sig = np.ones((k, n, 3))
        for m in self.members:
            if m.kind == "points":
                out[:, :, m.axes[0]] = m.session.run(None, {"X": sets.reshape(k * n, f)})[0].reshape(k, n)
                continue
            ys = np.empty((k, n, len(m.axes)), np.float32)
            ss = np.empty((k, n, len(m.axes)), np.float32)
            for i in range(0, k, _SET_CHUNK):
                res = m.session.run(None, {"X": sets[i : i + _SET_CHUNK]})
                ys[i : i + _SET_CHUNK] = res[0]
                if m.sigma:
                    ss[i : i + _SET_CHUNK] = res[1]
            out[:, :, list(m.axes)] = ys
            if m.sigma:
                sig[:, :, list(m.axes)] = np.exp(ss)
        return out, sig

    def predict_with_sigma(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(errors (M, 3), σ̂ (M, 3)) mm for the rows of ONE cloud, with the set partition of :meth:`predict`
        (same errors); NaN rows for non-finite features."""
        X = self._check_X(X)
        ok = np.all(np.isfinite(X), axis=1)
        p = int(ok.sum())
        if p == len(X):
            return self._predict_sigma_finite(X)
        err = np.full((len(X), 3), np.nan)
        sig = np.full((len(X), 3), np.nan)
        if p:
            err[ok], sig[ok] = self._predict_sigma_finite(X[ok])
        return err, sig

    def _predict_sigma_finite(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = len(X)
        if p == 0:
            return np.empty((0, 3)), np.empty((0, 3))
        idx, _ = partition_sets(p, self.set_size, self.partition_seed)
        e, s = self.predict_sets_sigma(X[idx])
        # One scatter of both outputs side by side (measured: two fancy-index scatters cost ~10 ms on 180k).
        both = np.empty((p, 6))
        both[idx.reshape(-1)[:p]] = np.concatenate([e, s], axis=-1).reshape(-1, 6)[:p]
        return both[:, :3], both[:, 3:]

    @property
    def calibrated(self) -> bool:
        """True when the card carries a conformal calibration (``uncertainty`` block)."""
        return bool(self.card.get("uncertainty", {}).get("multiplier"))

    def _expand(self, sig: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(U (M, 3), domain distance (M,)) from σ̂ (M, 3) and the feature rows X (M, F): the one formula of U."""
        if not self.calibrated:
            raise ModelLoadError(f"model set {self.id!r} has no uncertainty calibration (card 'uncertainty')")
        mult = np.asarray(self.card["uncertainty"]["multiplier"], np.float64)
        dist = self.domain_distance(X)
        with np.errstate(invalid="ignore"):
            widen = np.where(dist > 1.0, dist, 1.0)  # NaN distance (no domain_mv) → no widening
        floor = float(self.card["uncertainty"].get("sigma_floor_mm", 0.0))
        U = sig + floor
        U *= mult
        U *= widen[:, None]
        return U, dist

    def predict_sets_uncertainty(self, sets: np.ndarray) -> np.ndarray:
        """(K, n, F) → U (K, n, 3) mm of each set's rows predicted as one PointNet set (as :meth:`predict_sets`);
        a set of the partition of :meth:`predict_with_uncertainty` gets exactly the published U of its points (the
        explainer of U relies on it). Raises ModelLoadError without a calibration."""
        sets = np.asarray(sets, dtype=np.float32)
        k, n, f = sets.shape
        if not self.calibrated:
            raise ModelLoadError(f"model set {self.id!r} has no uncertainty calibration (card 'uncertainty')")
        _, sig = self.predict_sets_sigma(sets)
        U, _ = self._expand(sig.reshape(k * n, 3), sets.reshape(k * n, f))
        return U.reshape(k, n, 3)

    def predict_with_uncertainty(self, X: np.ndarray) -> UncertainPrediction:
        """Errors and their expanded uncertainty U (mm) for the feature rows X (M, F) of ONE cloud.

        U = the card's conformal multiplier per axis × (σ̂ + its sigma_floor_mm), times max(1, domain distance)
        outside the multivariate domain. Raises ModelLoadError when the model set has no calibration."""
        if not self.calibrated:
            raise ModelLoadError(f"model set {self.id!r} has no uncertainty calibration (card 'uncertainty')")
        X = self._check_X(X)
        err, sig = self.predict_with_sigma(X)
        U, dist = self._expand(sig, X)
        return UncertainPrediction(err, U, sig, dist, self.out_of_domain_mv(X, dist))

    @property
    def has_sets(self) -> bool:
        """True when a member is a PointNet (a point's prediction depends on the other points of its set)."""
        return any(m.kind == "sets" for m in self.members)

    def __repr__(self) -> str:
        fams = ", ".join(f"{m.family}[{''.join(AXES[a] for a in m.axes)}]" for m in self.members)
        return f"ModelSet(id={self.id!r}, features={len(self.feature_names)}, models={fams})"
