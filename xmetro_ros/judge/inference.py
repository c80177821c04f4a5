"""Run a model set (ONNX files + ``card.json``) with ONNX Runtime: per-point errors in mm for the x, y, z axes.

A model set directory holds ``card.json`` and one or more ONNX files; each file covers one or more axes:
* ``kind: "points"`` (DT, SVR, MLP, CatBoost, one axis each): input ``X`` (N, F) float32 → ``y`` (N, 1) mm.
* ``kind: "sets"`` (PointNet): input ``X`` (B, n, F) → ``y`` (B, n, A) mm. The points of one call are treated as
  one cloud, partitioned into sets of ``card["set_size"]`` by a permutation seeded with
  ``card["partition_seed"]`` (see :func:`xmetro_ros.learn.pointnet.partition_sets` and ``card["global_feature"]``).
How a cloud runs (``predict``, ``predict_with_sigma``, ``predict_with_uncertainty``, ``predict_batch``): the finite
rows are gathered once, straight into set order (:func:`xmetro_ros.judge.pointsets.set_order`, cached by point count),
ONNX Runtime is fed slices of that contiguous buffer (``set_chunk`` sets per run, the runs side by side on the model
set's ``threads``), both outputs of the spread head come from the same run, and the per-slot outputs are read back to
point order in one pass (``set_kernels``): the same sets and bit for bit the same predictions as the gather/scatter
implementation before it (test/test_inference_sets.py against test/reference_inference.py).

Features are the card's ``feature_names`` in order, in the units of ``feature_units`` (the study's: mm, deg, ms,
per mm). Predictions are the systematic error nominal − measured, mm, in the scan frame's axes.

Uncertainty (:meth:`ModelSet.predict_with_uncertainty`): a PointNet member with a second ONNX output
``log_sigma`` gives σ̂ per point and axis (mm); a member without one counts as σ̂ = 1 mm (plain absolute-residual
conformal). The card's ``uncertainty`` block (written by :func:`xmetro_ros.learn.uncertainty.calibrate`) holds the
split-conformal multiplier per axis, and per calibration condition (incidence bin × exposure level,
:mod:`.conditions`) where the card has them: U (95 %) = multiplier × (σ̂ + σ floor). The card's ``domain_mv`` block is
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
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from ..compute.threads import parallel_for
from ..scan.resources import default_model_dir
from .conditions import interior_edges, multiplier_table, row_multipliers
from .measured_noise import NORMAL_FEATURES, effective_sigma
from .pointsets import set_order
from .set_kernels import expand_u as _expand_u
from .set_kernels import expand_u_conditional as _expand_u_cond
from .set_kernels import finite_rows as _finite_rows
from .set_kernels import from_sets as _from_sets
from .set_kernels import to_sets as _to_sets
from .set_kernels import warm_up as _warm_kernels
from .set_kernels import whitened_norm

__all__ = ["AXES", "CARD_FORMAT", "LEGACY_SCANNER_ID", "SIGMA_CAP_FACTOR", "ModelLoadError", "ModelSet",
           "UncertainPrediction", "load_pose_model", "model_scanner_id", "session_options", "update_card"]

CARD_FORMAT = "xmetro-model-set/1"
AXES = ("x", "y", "z")
# Sets per ONNX Runtime run: 32-256 are equally fast, 512 and 1024 10-16 % slower (activations leave the cache);
# any chunk gives the same bits (bench/bench_uncertainty.py measures and checks both; test_inference_sets.py).
_SET_CHUNK = 128
# With several threads, a cloud's sets are cut into this many chunks per thread, never more than _SET_CHUNK sets
# each: on 16 cores 1 or 2 per thread ran the 3,326 sets of the 55 mm sphere in 7.1-7.6 ms, 4 in 8.7, 8 in 14.5
# (bench/results/onnx_side_by_side_16core.json).
_CHUNKS_PER_THREAD = 2
#: σ̂ is capped at this multiple of the largest σ̂ of the calibration clouds (card ``uncertainty.sigma_max_mm``).
SIGMA_CAP_FACTOR = 2.0


def update_card(model_dir: str | Path, **blocks: Any) -> None:
    """Write ``blocks`` (name → JSON-able value) into the card of ``model_dir``, its other entries unchanged (the
    calibration steps add ``uncertainty``, ``domain_mv``, ``domain_shape`` to an exported model set)."""
    p = Path(model_dir) / "card.json"
    card = json.loads(p.read_text())
    card.update(blocks)
    p.write_text(json.dumps(card, indent=1, sort_keys=True))


def session_options(threads: int = 1) -> Any:
    """ONNX Runtime session options of a model member: ``threads`` intra-op threads, one inter-op thread, sequential
    execution, all graph optimisations, memory pattern and CPU arena on (ONNX Runtime's defaults; the alternatives
    measured by bench/bench_uncertainty.py were no faster, see docs/performance.md). PointNet members get one
    intra-op thread: :class:`ModelSet` runs their chunks of sets side by side on its own threads instead."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(1, int(threads))
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # The intra-op threads spin during a run but stop at its end: the judge's compiled kernels run right after the
    # ONNX call on the same cores, and threads left spinning took a core from them (the judge at 2 threads here:
    # 0.62-0.65x open3d's normals left spinning, 0.47-0.57x stopped; never spinning made the ONNX call itself
    # slower, bench/bench_threads.py)
    opts.add_session_config_entry("session.force_spinning_stop", "1")
    return opts


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
    outputs: tuple[str, ...] = ()  # the error output first, then log_sigma when there is one


def _as_sets(a: np.ndarray, order: np.ndarray, q: int) -> np.ndarray:
    """Per-point values (P,) of every version, or (Q, P), laid out as the Q versions' sets end to end."""
    return np.tile(a[order], q) if a.ndim == 1 else a[:, order].reshape(-1)


def _run_chunk(m: _Member, want: tuple[str, ...], x: np.ndarray, y: np.ndarray) -> None:
    """One ONNX run of a set member on the contiguous sets ``x`` (c, n, F), its outputs written into ``y`` (o, c, n,
    3): through I/O binding (no copies) when the member covers x, y and z, else copied into its axes."""
    if m.axes == (0, 1, 2):
        io = m.session.io_binding()  # one per run: runs of the same session go side by side
        io.bind_input("X", "cpu", 0, np.float32, x.shape, x.ctypes.data)
        for o, name in enumerate(want):
            io.bind_output(name, "cpu", 0, np.float32, (len(x), x.shape[1], 3), y[o].ctypes.data)
        m.session.run_with_iobinding(io)
        return
    for o, r in enumerate(m.session.run(want, {"X": x})):
        y[o][..., list(m.axes)] = r


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
    """A loaded model set. ``predict`` is thread-safe (ONNX Runtime sessions are).

    ``threads``: how many ONNX runs go side by side. A PointNet member's sets are independent of each other, so its
    chunks of sets run side by side on ``threads`` threads (``compute.threads.parallel_for``), each run on one ONNX
    Runtime thread: no synchronisation inside a run, where ONNX Runtime's intra-op threads split every small layer
    of a 6,400-point chunk and stopped gaining beyond 4 threads (16 cores: 80 ms at 1 thread, 47 at 8 and at 16
    for the 55 mm sphere's 166k points, bench/results/scaling_16core_before.json). A point-wise member runs once
    over all rows, on ``threads`` intra-op threads. The chunks never change a result (each set's run is the same
    computation).
    """

    def __init__(self, model_dir: Path, card: dict, members: list[_Member], threads: int = 1) -> None:
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
        self.set_chunk = _SET_CHUNK
        self.threads = max(1, int(threads))
        self._lock = threading.Lock()
        self._mv: tuple[np.ndarray, np.ndarray] | None = None
        # σ̂ ceiling per axis: SIGMA_CAP_FACTOR × the largest σ̂ of the calibration clouds (card
        # "uncertainty.sigma_max_mm"). Beyond the data the spread head extrapolates exponentially (σ̂ = exp(log σ̂)
        # reaches float32 inf on a far-away scene); there the widening by the domain distance, not an extrapolated
        # σ̂, is what U says. The factor leaves room for the tail of a whole scan (the calibration samples 300 points
        # per cloud): on the shipped bags σ̂ reaches 1.03× the calibration's largest. None: no ceiling.
        smax = (card.get("uncertainty") or {}).get("sigma_max_mm")
        self.log_sigma_max: np.ndarray | None = (
            np.log(SIGMA_CAP_FACTOR * np.asarray(smax, np.float64)).astype(np.float32) if smax is not None else None)

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

        opts = {"points": session_options(threads), "sets": session_options(1)}  # sets: the pool's threads
        members: list[Any] = []
        covered: list[int] = []
        for m in card["models"]:
            p = d / m["file"]
            if not p.is_file():
                raise ModelLoadError(f"model file {p} listed in the card is missing")
            if m.get("sha256") and hashlib.sha256(p.read_bytes()).hexdigest() != m["sha256"]:
                raise ModelLoadError(f"model file {p} does not match the card's sha256 (modified or corrupt)")
            try:
                sess = ort.InferenceSession(str(p), sess_options=opts[m["kind"]], providers=["CPUExecutionProvider"])
            except Exception as e:
                raise ModelLoadError(f"ONNX Runtime cannot load {p}: {e}") from e
            shape = sess.get_inputs()[0].shape
            if isinstance(shape[-1], int) and shape[-1] != len(card["feature_names"]):
                raise ModelLoadError(
                    f"{p.name} takes {shape[-1]} features but the card lists {len(card['feature_names'])}"
                )
            axes = tuple(AXES.index(a) for a in m["axes"])
            covered.extend(axes)
            names = [o.name for o in sess.get_outputs()]
            has_sigma = "log_sigma" in names
            outputs = (names[0], "log_sigma") if has_sigma and names[0] != "log_sigma" else (names[0],)
            members.append(_Member(m["family"], m["kind"], axes, sess, p, has_sigma, outputs))
        if sorted(covered) != [0, 1, 2]:
            raise ModelLoadError(f"{card_path}: the models must cover each of the axes x, y, z exactly once")
        _warm_kernels()  # compile or load the row kernels now, not on the first scan (once per process)
        return cls(d, card, members, threads=threads)

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
            # float32 and the mean folded into a bias: z = X·W − mean·W on the raw rows; dividing W by the threshold
            # gives the distance in threshold units directly.
            w = np.asarray(dom["whiten"], np.float64) / float(dom["threshold"])
            self._mv = (w.astype(np.float32), (np.asarray(dom["mean"], np.float64) @ w).astype(np.float32))
        w, b = self._mv
        # one compiled pass, each row alone in a fixed order (no BLAS: its kernels change a row's last bit with the
        # rows beside it), on the numba threads of the caller's budget: the same bits at any count
        return whitened_norm(X, w, b)

    def out_of_domain_mv(self, X: np.ndarray, distance: np.ndarray | None = None, margin: float = 0.0) -> np.ndarray:
        """(M,) bool: outside the multivariate domain (distance > threshold × (1 + ``margin``), the node's
        ``domain_margin`` widening it as it widens each feature's range; ``distance`` = domain_distance(X) when
        already computed); the per-feature min/max check (:meth:`out_of_domain`, the card's margin) when the card
        has no multivariate domain."""
        if not self.card.get("domain_mv"):
            return self.out_of_domain(X)
        d = self.domain_distance(X) if distance is None else np.asarray(distance)
        with np.errstate(invalid="ignore"):
            return d > 1.0 + margin

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
        return self._predict_cloud(self._check_X(X), sigma=False)[0]

    def _predict_cloud(self, X: np.ndarray, sigma: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """(errors (M, 3), σ̂ (M, 3) or None) float64 mm for the float32 rows X of one cloud; NaN rows for
        non-finite features. One pass copying the finite rows straight into set order (the cached partition of their
        count), the ONNX runs on contiguous slices of that buffer, one pass writing the per-slot outputs back in point
        order: no (M, F) intermediate copies, and error and σ̂ come from the same ONNX run."""
        m = len(X)
        rows = _finite_rows(X)  # None: every row finite
        p = m if rows is None else len(rows)
        # every row is written when all are finite; NaN rows otherwise. Errors and σ̂ in two contiguous arrays: the
        # flags, the scatter and the statistics read them without a copy.
        out = [np.empty((m, 3)) if rows is None else np.full((m, 3), np.nan) for _ in range(2 if sigma else 1)]
        if p == 0:
            return out[0], (out[1] if sigma else None)
        order, pos = set_order(p, self.set_size, self.partition_seed)
        flat = _to_sets(X, pos, order, rows)
        # σ̂ = numpy's float32 exp of log σ̂, as before, on the runs' threads
        y = self._run_sets(flat.reshape(-1, self.set_size, flat.shape[1]), sigma, exp_sigma=True)
        for o in range(len(y)):
            _from_sets(y[o].reshape(-1, 3), order, out[o], rows)
        return out[0], (out[1] if sigma else None)

    def predict_batch(self, Xq: np.ndarray, output: str = "error", surface_class: np.ndarray | None = None,
                      noise: np.ndarray | None = None) -> np.ndarray:
        """(Q, P, F) → (Q, P, 3): Q versions of the same P-point cloud, each predicted as ``predict`` would
        (same set partition for every version). Used by the SHAP explainer and the recommender. Rows must be
        finite. ``output="uncertainty"``: U as :meth:`predict_with_uncertainty` instead of the errors (with the
        points' surface classes ``surface_class`` and measured noise ``noise``: (P,) in every version, or (Q, P))."""
        if output != "error":  # U as predict_with_uncertainty computes it, from the same run's log σ̂
            return self.predict_batch_with_uncertainty(Xq, surface_class, noise)[1]
        Xq = np.asarray(Xq, dtype=np.float32)
        q, p, f = Xq.shape
        out = np.empty((q, p, 3))
        if p == 0:
            return out
        order, pos = set_order(p, self.set_size, self.partition_seed)
        sets = _to_sets(Xq, pos, order).reshape(-1, self.set_size, f)  # the versions' sets end to end
        _from_sets(self._run_sets(sets, False)[0].reshape(q, -1, 3), order, out)
        return out

    def predict_batch_with_uncertainty(self, Xq: np.ndarray, surface_class: np.ndarray | None = None,
                                       noise: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(Q, P, F) → (errors (Q, P, 3), U (Q, P, 3)) mm: each version as :meth:`predict_with_uncertainty` would give
        it (with the points' classes ``surface_class`` and measured ``noise``: (P,) in every version, or (Q, P)),
        errors and U from ONE ONNX run per chunk of sets (the recommender's candidates; ``predict_batch``'s U). Rows
        must be finite. Raises ModelLoadError without a calibration."""
        if not self.calibrated:
            raise ModelLoadError(f"model set {self.id!r} has no uncertainty calibration (card 'uncertainty')")
        Xq = np.asarray(Xq, dtype=np.float32)
        q, p, f = Xq.shape
        err, unc = np.empty((q, p, 3)), np.empty((q, p, 3))
        if p == 0:
            return err, unc
        order, pos = set_order(p, self.set_size, self.partition_seed)
        sets = _to_sets(Xq, pos, order).reshape(-1, self.set_size, f)
        y = self._run_sets(sets, True, exp_sigma=True)  # float32 exp, as predict_with_uncertainty
        cls, nz = (None if a is None else _as_sets(np.asarray(a), order, q) for a in (surface_class, noise))
        U, _ = self._expand(y[1].astype(np.float64).reshape(-1, 3), sets.reshape(-1, f), cls, nz)
        _from_sets(y[0].reshape(q, -1, 3), order, err)
        _from_sets(U.reshape(q, -1, 3), order, unc)
        return err, unc

    def predict_sets(self, sets: np.ndarray) -> np.ndarray:
        """(K, n, F) → (K, n, 3) mm: each of the K sets predicted as one PointNet set (the global feature is the
        max over its n rows); point-wise members predict every row on its own. Rows must be finite. This is how
        ``predict`` predicts each set of its partition, so a set of the partition given here gets exactly the
        published predictions of its points (the explainer relies on it)."""
        return self._run_sets(np.ascontiguousarray(sets, dtype=np.float32), False)[0].astype(np.float64)

    def predict_sets_sigma(self, sets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, n, F) → (errors (K, n, 3), σ̂ (K, n, 3)) mm, as :meth:`predict_sets`; σ̂ = 1 on the axes of members
        without a spread output."""
        y = self._run_sets(np.ascontiguousarray(sets, dtype=np.float32), True, exp_sigma=True)
        return y[0].astype(np.float64), y[1].astype(np.float64)

    def _run_sets(self, sets: np.ndarray, sigma: bool, exp_sigma: bool = False) -> np.ndarray:
        """Contiguous float32 sets (K, n, F) → float32 (1, K, n, 3) errors, or with ``sigma`` (2, K, n, 3): errors
        and log σ̂ (log σ̂ = 0, σ̂ = 1, on the axes of members without a spread output), both outputs of the same ONNX
        run; with ``exp_sigma`` σ̂ itself (numpy's float32 exp of the capped log σ̂). Every member's runs are fed
        slices of ``sets`` itself; a set member covering x, y, z writes its outputs straight into the result (ONNX
        Runtime I/O binding: no copies); without ``sigma`` only the error output is asked for."""
        if sets.dtype != np.float32 or not sets.flags.c_contiguous:
            raise ValueError("_run_sets needs C-contiguous float32 sets (the I/O binding reads the buffer)")
        k, n, f = sets.shape
        y = np.empty((2 if sigma else 1, k, n, 3), np.float32)
        # One PointNet member covering x, y and z (the shipped kind): its runs write every output value, and each
        # chunk's run caps and exponentiates its own log σ̂ right after, on its thread (element-wise: the same bits).
        own = sigma and len(self.members) == 1 and self.members[0].kind == "sets"
        if sigma and not own:
            y[1] = 0.0
        chunk = self._chunk(k)
        cap = self.log_sigma_max

        def post(ys: np.ndarray) -> None:  # log σ̂ (rows of y[1], contiguous) capped, then σ̂ when asked
            if cap is not None:
                # NaN stays NaN (np.minimum propagates it). On (sets, points·3) rows against the cap tiled per
                # point: numpy's loop over 3-value spans took 37 µs a chunk of 128 sets, this 6.5
                rows = ys.reshape(len(ys), -1)
                np.minimum(rows, np.tile(cap, ys.shape[1]), out=rows)
            if exp_sigma:
                np.exp(ys, out=ys)

        for m in self.members:
            want = m.outputs if sigma and m.sigma else m.outputs[:1]
            if m.kind == "points":
                y[0].reshape(k * n, 3)[:, m.axes[0]] = m.session.run(want, {"X": sets.reshape(k * n, f)})[0][:, 0]
                continue

            def one(c: int, m: _Member = m, want: tuple[str, ...] = want) -> None:
                _run_chunk(m, want, sets[c * chunk : (c + 1) * chunk], y[:, c * chunk : (c + 1) * chunk])
                if own:
                    post(y[1, c * chunk : (c + 1) * chunk])

            parallel_for(one, -(-k // chunk), self.threads)
        if sigma and not own:
            post(y[1])
        return y

    def _chunk(self, k: int) -> int:
        """Sets per ONNX run for ``k`` sets: ``set_chunk``, or fewer when that leaves threads idle."""
        if self.threads == 1:
            return self.set_chunk
        return max(1, min(self.set_chunk, -(-k // (_CHUNKS_PER_THREAD * self.threads))))

    def predict_with_sigma(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(errors (M, 3), σ̂ (M, 3)) mm for the rows of ONE cloud, with the set partition of :meth:`predict`
        (same errors, from the same ONNX run as σ̂); NaN rows for non-finite features."""
        err, sig = self._predict_cloud(self._check_X(X), sigma=True)
        assert sig is not None
        return err, sig

    @property
    def calibrated(self) -> bool:
        """True when the card carries a conformal calibration (``uncertainty`` block)."""
        return bool(self.card.get("uncertainty", {}).get("multiplier"))

    @cached_property
    def _conditions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int] | None:
        """(multiplier table, cos of the interior incidence edges, interior exposure edges, column of Inc, column of
        exposure_time) of a card calibrated per condition; None otherwise."""
        cond = (self.card.get("uncertainty") or {}).get("conditional")
        if not cond:
            return None
        cos_e, exp_e = interior_edges(cond["incidence_edges_deg"], cond["exposure_edges_ms"])
        names = list(self.feature_names)
        return (multiplier_table(self.card["uncertainty"]), cos_e, exp_e, names.index("Inc"),
                names.index("exposure_time"))

    @property
    def by_surface(self) -> bool:
        """True when U is calibrated per surface class too (card ``uncertainty.conditional.by_surface``): the judge
        then gives :meth:`predict_with_uncertainty` each point's class (:mod:`.surface_class`)."""
        return bool(self._by_surface_block)

    @property
    def noise_in_u(self) -> bool:
        """True when the card's per-class multipliers were calibrated on max(σ̂, measured noise·|N|)
        (``uncertainty.conditional.by_surface.noise``, :mod:`.measured_noise`): the judge then gives
        :meth:`predict_with_uncertainty` each point's measured noise (:mod:`xmetro_ros.preprocess.noise`)."""
        return bool((self._by_surface_block or {}).get("noise"))

    @cached_property
    def along_normal(self) -> Any:
        """The card's d and U along the measured normal (:class:`.along_normal.AlongNormal`), None when it has none:
        the judge then carries each row's d and U onto its normal (:meth:`ScanHandler.process`)."""
        from .along_normal import AlongNormal

        return AlongNormal.from_card(self.card)

    def along_normal_rows(self, X: np.ndarray, surface_class: np.ndarray | None, noise: np.ndarray | None,
                          settings: Any, domain_distance: np.ndarray | None = None,
                          tilt: np.ndarray | None = None) -> Any:
        """What the card's :attr:`along_normal` block does to the feature rows X (M, F) of one scan taken with
        ``settings`` (:class:`.along_normal.AlongNormalRows`), with the rows' surface classes and measured noise (mm),
        their multivariate domain distance (None: computed) and measured tilt noise (M, 3) radians (the
        ``measured_tilt`` allowance; :mod:`xmetro_ros.preprocess.tilt_noise`): the normals are the features N_x, N_y,
        N_z. None when the card has no block or the scan no classes or noise. The judge and the explainer both use
        it."""
        an = self.along_normal
        if an is None or surface_class is None or noise is None:
            return None
        from .along_normal import grid_spacings_mm

        X = np.asarray(X)
        dist = self.domain_distance(X) if domain_distance is None else domain_distance
        return an.rows(X[:, self._normal_columns], noise, surface_class, float(settings.exposure_ms),
                       grid_spacings_mm(float(settings.lateral_density), float(settings.direction_density)), dist,
                       X[:, list(self.feature_names).index("Inc")] if "Inc" in self.feature_names else None, tilt)

    @cached_property
    def _normal_columns(self) -> list[int]:
        """Columns of the unit normal (N_x, N_y, N_z) in the feature rows."""
        names = list(self.feature_names)
        return [names.index(c) for c in NORMAL_FEATURES]

    @property
    def _by_surface_block(self) -> dict | None:
        """The card's ``uncertainty.conditional.by_surface`` block (None: not calibrated per class)."""
        return ((self.card.get("uncertainty") or {}).get("conditional") or {}).get("by_surface")

    def surface_classes(self, kappa: np.ndarray) -> np.ndarray:
        """(M,) int8 surface class of each point from its (M, 2) principal curvatures (1/mm), with the classes and
        thresholds the card was calibrated with (:func:`.surface_class.card_surface_class`); all −1 (the all-class
        multiplier) for a card not calibrated per class."""
        from .surface_class import card_surface_class

        by = self._by_surface_block
        if not by:
            return np.full(len(np.asarray(kappa).reshape(-1, 2)), -1, np.int8)
        return card_surface_class(kappa, by)

    def multipliers(self, X: np.ndarray, surface_class: np.ndarray | None = None) -> np.ndarray:
        """The conformal multiplier of each feature row and axis: (3,) for a card calibrated per axis only, (M, 3)
        for one calibrated per condition (incidence × exposure, :mod:`.conditions`, and the row's surface class
        when given and calibrated; NaN: no U for that row)."""
        block = self.card["uncertainty"]
        if not block.get("conditional"):
            return np.asarray(block["multiplier"], np.float64)
        return row_multipliers(block, X, self.feature_names, surface_class)

    def _expand(self, sig: np.ndarray, X: np.ndarray, surface_class: np.ndarray | None = None,
                noise: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(U (M, 3), domain distance (M,)) from σ̂ (M, 3) and the feature rows X (M, F) (and their surface classes
        and measured noise, mm along the normal): the one formula of U."""
        if not self.calibrated:
            raise ModelLoadError(f"model set {self.id!r} has no uncertainty calibration (card 'uncertainty')")
        dist = self.domain_distance(X)
        if self.noise_in_u and surface_class is not None and noise is not None:
            sig, surface_class = effective_sigma(sig, np.asarray(X)[:, self._normal_columns], surface_class, noise)
        floor = float(self.card["uncertainty"].get("sigma_floor_mm", 0.0))
        if self._conditions is not None:  # the row's condition found and its multiplier applied in one pass
            table, cos_e, exp_e, i_inc, i_exp = self._conditions
            Xa = np.asarray(X)
            cls = surface_class if self.by_surface else None
            return _expand_u_cond(np.asarray(sig, np.float64), floor, table, cos_e, exp_e, Xa[:, i_inc], Xa[:, i_exp],
                                  dist, cls), dist
        mult = self.multipliers(X)
        # (σ̂ + floor) × mult × max(1, distance), in that order (NaN distance: no widening), one compiled pass
        return _expand_u(np.asarray(sig, np.float64), floor, mult, dist), dist

    def predict_sets_uncertainty(self, sets: np.ndarray, surface_class: np.ndarray | None = None,
                                 noise: np.ndarray | None = None) -> np.ndarray:
        """(K, n, F) → U (K, n, 3) mm of each set's rows predicted as one PointNet set (as :meth:`predict_sets`),
        with the rows' surface classes ``surface_class`` and measured ``noise`` (K, n) when given; a set of the
        partition of :meth:`predict_with_uncertainty` with its points' classes and noise gets exactly the published
        U of its points (the explainer of U relies on it). Raises ModelLoadError without a calibration."""
        sets = np.asarray(sets, dtype=np.float32)
        k, n, f = sets.shape
        if not self.calibrated:
            raise ModelLoadError(f"model set {self.id!r} has no uncertainty calibration (card 'uncertainty')")
        _, sig = self.predict_sets_sigma(sets)
        cls = None if surface_class is None else np.asarray(surface_class).reshape(k * n)
        nz = None if noise is None else np.asarray(noise, np.float64).reshape(k * n)
        U, _ = self._expand(sig.reshape(k * n, 3), sets.reshape(k * n, f), cls, nz)
        return U.reshape(k, n, 3)

    def predict_with_uncertainty(self, X: np.ndarray, surface_class: np.ndarray | None = None,
                                 noise: np.ndarray | None = None) -> UncertainPrediction:
        """Errors and their expanded uncertainty U (mm) for the feature rows X (M, F) of ONE cloud.

        U = the card's conformal multiplier (per axis, or per condition: :meth:`multipliers`; per surface class too
        when the card has them and ``surface_class`` (M,) int8 gives each row's, −1 for none) × (σ̂ + its
        sigma_floor_mm), times max(1, domain distance) outside the multivariate domain. With the rows' measured
        ``noise`` (M,) mm along the normal (:mod:`xmetro_ros.preprocess.noise`, NaN: none) and a card calibrated with
        it (:attr:`noise_in_u`), σ̂ is max(σ̂, noise·|N|) per axis (:mod:`.measured_noise`). Raises ModelLoadError
        when the model set has no calibration."""
        if not self.calibrated:
            raise ModelLoadError(f"model set {self.id!r} has no uncertainty calibration (card 'uncertainty')")
        X = self._check_X(X)
        err, sig = self.predict_with_sigma(X)
        U, dist = self._expand(sig, X, surface_class, noise)
        return UncertainPrediction(err, U, sig, dist, self.out_of_domain_mv(X, dist))

    @cached_property
    def training_rotations(self) -> list[np.ndarray] | None:
        """Head orientations (3×3 rotations, head frame relative to looking down) of the simulated campaign the
        model set was trained on: the card's campaign ``poses``, looking down only when it names none; None when the
        card does not say (e.g. trained on recorded bags). Read once (the router asks on every scan)."""
        dm = self.card.get("data_manifest") or {}
        poses = (dm.get("campaign_args") or {}).get("poses")
        if poses:
            return [np.asarray(r, np.float64).reshape(3, 3) for r in poses]
        return [np.eye(3)] if dm.get("source") == "simulated" else None

    @property
    def shape_domain(self) -> tuple[float, float, float] | None:
        """(lo, hi, radius_mm) of the mean curvature (1/mm) the calibration clouds covered (card ``domain_shape``,
        :mod:`xmetro_ros.learn.shape_domain`), or None when the card has none (then no shape check)."""
        d = self.card.get("domain_shape")
        if not d:
            return None
        return float(d["lo"]), float(d["hi"]), float(d.get("radius_mm", 1.0))

    @cached_property
    def principal_domain(self) -> tuple[np.ndarray, float, float] | None:
        """(occupied cells (n, n) bool, lo, bin) in 1/mm of the (κmin, κmax) plane the calibration clouds covered
        (card ``domain_shape.principal``, :mod:`.surface_class`), or None when the card has none."""
        d = (self.card.get("domain_shape") or {}).get("principal")
        if not d:
            return None
        from .surface_class import principal_domain_grid

        return principal_domain_grid(d)

    @property
    def has_sets(self) -> bool:
        """True when a member is a PointNet (a point's prediction depends on the other points of its set)."""
        return any(m.kind == "sets" for m in self.members)

    def __repr__(self) -> str:
        fams = ", ".join(f"{m.family}[{''.join(AXES[a] for a in m.axes)}]" for m in self.members)
        return f"ModelSet(id={self.id!r}, features={len(self.feature_names)}, models={fams})"


#: Cards written before 0.2.0 record no scanner: they were all trained on the packaged virtual scanner.
LEGACY_SCANNER_ID = "xm-ls90"


def model_scanner_id(card: dict[str, Any]) -> str:
    """The id of the scanner a model set was trained for (its card's ``scanner.id``; legacy cards: xm-ls90)."""
    return str((card.get("scanner") or {}).get("id") or LEGACY_SCANNER_ID)


def load_pose_model(path: str | Path, primary: ModelSet, threads: int = 1) -> ModelSet:
    """The second ("pose") model set at ``path``, to judge next to ``primary`` (``ScanHandler.route``) and to search
    with (docs/services.md, "Two model sets"): it must take the primary's features and be trained for the same scanner.
    Raises ModelLoadError (or what ``ModelSet.load`` raises) when it cannot."""
    pm = ModelSet.load(path, threads=threads)
    if list(pm.feature_names) != list(primary.feature_names):
        raise ModelLoadError(f"its features {list(pm.feature_names)} are not the primary model's")
    if model_scanner_id(pm.card) != model_scanner_id(primary.card):
        raise ModelLoadError(f"it was trained for scanner {model_scanner_id(pm.card)!r}, the primary model for "
                             f"{model_scanner_id(primary.card)!r}")
    return pm
