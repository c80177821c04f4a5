"""Inputs of the loop → LoopData: our scans (MCAP bags or in-memory ``Scan``s), measured files (NIST TLS spheres,
AT C5 profiler sphere) through ``xmetro_ros.scan.measured``, and lists of single laser-line profiles of a certified
sphere (``scan.profiles``, ``calibrate.profile_table``). Lengths mm, artifact frame (profiles: sensor frame).

Ground truth: ``targets.errors_with_fit`` = nominal − measured with the nominal radius; ``center=fit`` fits the
centre per cloud (scans, NIST spheres: one placement each) or once over all profiles (AT C5: one sphere seen by 15
robot poses). A radius far from the data raises ``targets.FitError``. Profile lists: the arc is always fitted per
profile (centre and radius r ≤ R: the laser plane cuts the sphere at an unknown offset), whatever ``center`` says.
Features of the current model: the study's 14 (``features.STUDY_FEATURES``) for scans; for measured sets, whose
scan settings are unknown, the study's geometric features only (``MEASURED_FEATURES``); for profile lists, the
profile features (``calibrate.profile_table.PROFILE_FEATURES``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ..scan.artifact_specs import parse_artifact
from ..scan.artifacts import Artifact
from ..scan.geometry import unit, vec3
from ..scan.scan import Scan
from .data import LoopData, LoopInputError

__all__ = ["MEASURED_FEATURES", "PROFILE_SUFFIXES", "check_inputs", "detect_kind", "from_atc5", "from_campaign",
           "from_nist", "from_profiles", "from_scans", "load_inputs", "load_path"]

# Study features that need no scan settings (measured sets do not declare them).
MEASURED_FEATURES = ["N_x", "N_y", "N_z", "Inc", "ViewAng", "R_y", "ang"]
#: Profile files a profile list (``.txt``) may name (``scan.profiles``).
PROFILE_SUFFIXES = (".csv", ".npy", ".npz")


def _errors(points: np.ndarray, artifact: Artifact, fit_center: bool) -> tuple[np.ndarray, Artifact]:
    from ..scan.artifacts import Sphere
    from ..scan.fitting import fit_sphere
    from ..scan.targets import errors_with_fit

    if fit_center and isinstance(artifact, Sphere):
        # Start the fixed-radius fit from a free sphere fit: measured frames put the sphere far from the origin.
        c0, _r, _rms = fit_sphere(points)
        artifact = Sphere(artifact.radius, vec3(c0))
    return errors_with_fit(points, artifact, fit_center)


def _nominal_normals(points: np.ndarray, art: Artifact) -> np.ndarray:
    return np.asarray(art.normals(art.project(points)), dtype=float)


def from_scans(
    scans: list[Scan], artifact: Artifact | None = None, fit_center: bool = False,
    feature_names: list[str] | None = None, preprocess_cfg=None, names: list[str] | None = None,
    scanner=None,
) -> LoopData:
    """Table of organized / unorganized scans (each one group). ``artifact`` None → each scan's own artifact.
    ``scanner``: the scanner model whose geometry the features use (None: the packaged one)."""
    from ..judge.features import STUDY_FEATURES, FeatureContext, compute_features
    from ..preprocess import prepare_scan

    if not scans:
        raise LoopInputError("no scans in the input")
    feats = list(feature_names or STUDY_FEATURES)
    parts = []
    for i, scan in enumerate(scans):
        art = artifact or scan.artifact
        if art is None:
            raise LoopInputError(f"scan {i} has no nominal artifact: give one with --artifact")
        prep = prepare_scan(scan, preprocess_cfg, scanner=scanner)
        E, art_used = _errors(prep.points, art, fit_center)
        ctx = FeatureContext.from_prepared(prep)
        X = compute_features(feats, ctx)
        g = prep.geometry
        n = len(prep.points)
        parts.append(LoopData(
            points=prep.points, normals=_nominal_normals(prep.points, art_used), errors=E, X=X, feature_names=feats,
            fields={k: np.asarray(v, dtype=float) for k, v in prep.fields.items()},
            group=np.zeros(n, dtype=np.int64), order=np.asarray(prep.index, dtype=np.int64),
            geometry={"source_distance": np.asarray(g.source_distance, float), "L": np.asarray(g.L, float),
                      "V": np.asarray(g.V, float), "u": np.asarray(g.u, float), "s": np.asarray(g.s, float)},
            group_names=[names[i] if names else f"scan{i}"], source="scans", hold_by="cloud",
            artifact={"nominal": art.to_dict(), "fit_center": fit_center},
        ))
    return LoopData.concat(parts)


def from_campaign(path: str | Path, read_bag: Callable[..., list[Scan]],
                  feature_names: list[str] | None = None) -> LoopData:
    """A calibration campaign (``campaign_file``, several artifacts, known or fitted positions) → LoopData: the
    campaign is assembled and checked by ``campaign_data.assemble`` (one measurement per sphere and scan, the
    artifact placed at its known centre or fitted with its certified size), each measurement is one group, and the
    features use the campaign scanner's geometry. ``read_bag(recording, scanner)`` reads a recording's scans
    (``ros.scan_io.read_scans`` with its topics; injected so that this core module needs no ROS). Groups with a
    fitted position are marked (``artifact.per_group[i].position == "fitted"``): the loop then never selects a
    position-like candidate (``candidates.POSITION_LIKE``). Raises CampaignError naming the scan and the cause."""
    from ..calibrate.campaign_data import assemble
    from ..calibrate.campaign_file import load_campaign

    camp = load_campaign(path)
    # The loop traces residuals; it trains no model over the settings levels: uncovered levels are only noted.
    cdata = assemble(camp, lambda rec: read_bag(rec, camp.scanner), require_levels=False)
    parts = []
    for it in cdata.scans:
        part = from_scans([it.scan], None, False, feature_names=feature_names, names=[it.label],
                          scanner=cdata.scanner)
        art = it.scan.artifact
        part.artifact = {"nominal": art.to_dict() if art is not None else None, "artifact_id": it.placement.artifact,
                         "position": "fitted" if it.placement.fitted else "known",
                         "position_source": it.placement.source, "recording": it.recording, "scan": it.index}
        part.source = "campaign"
        parts.append(part)
    data = LoopData.concat(parts)
    data.artifact = {"campaign": camp.path.name, "sha256": camp.sha256, "scanner": camp.scanner_id,
                     "fitted_groups": [i for i, p in enumerate(parts) if p.artifact["position"] == "fitted"],
                     "per_group": [p.artifact for p in parts]}
    return data


def _measured_features(points: np.ndarray, L: np.ndarray, V: np.ndarray, standoff: np.ndarray,
                       fields: dict, feats: list[str]) -> np.ndarray:
    """Study geometric features of measured points: normals estimated from the points (open3d), oriented toward
    the sensor; no scan settings."""
    from ..judge.features import FeatureContext, compute_features
    from ..preprocess import estimate_normals

    normals, _q = estimate_normals(points, radius_mm=2.0, max_nn=30, toward=L)
    ctx = FeatureContext(normals=normals, L=L.astype(np.float32), V=V.astype(np.float32),
                         standoff=standoff.astype(np.float32),
                         source_distance=np.linalg.norm(points - 0, axis=1).astype(np.float32), settings=None,
                         fields=fields, points=points, u=np.zeros(len(points), np.float32),
                         s=np.zeros(len(points), np.float32))
    return compute_features(feats, ctx)


def from_nist(path: Path, artifact: Artifact, fit_center: bool) -> LoopData:
    """NIST TLS sphere scans (a directory of SPH*.xyz or single files): one group per cloud, scanner at origin."""
    from ..scan import measured

    path = Path(path)
    clouds = measured.load_nist_set(path) if path.is_dir() else [measured.load_nist_sphere(path)]
    parts = []
    for i, c in enumerate(clouds):
        p = np.asarray(c.points, dtype=float)
        E, art_used = _errors(p, artifact, fit_center)
        L = unit(-p)
        dist = np.linalg.norm(p, axis=1)
        X = _measured_features(p, L, L, dist, {}, MEASURED_FEATURES)
        n = len(p)
        parts.append(LoopData(
            points=p, normals=_nominal_normals(p, art_used), errors=E, X=X, feature_names=list(MEASURED_FEATURES),
            fields={}, group=np.zeros(n, dtype=np.int64), order=np.arange(n),
            geometry={"source_distance": dist, "L": L, "V": L},
            group_names=[getattr(c, "name", f"cloud{i}")], source="nist_tls", hold_by="cloud",
            artifact={"nominal": artifact.to_dict(), "fit_center": fit_center},
        ))
    return LoopData.concat(parts)


def from_atc5(path: Path, artifact: Artifact, fit_center: bool) -> LoopData:
    """AT C5 profiler sphere: 15 profiles taken to the robot base (pose × hand-eye); one group per profile; the
    sphere centre (``center=fit``) is fitted once over all profiles."""
    from ..scan import measured

    profiles = measured.load_atc5(Path(path))
    pts, L, u, rng_, grp, order, names = [], [], [], [], [], [], []
    for i, pr in enumerate(profiles):
        pb = np.asarray(pr.to_base(), dtype=float)
        T = np.asarray(pr.flange_pose, dtype=float) @ np.asarray(pr.hand_eye, dtype=float)
        origin = T[:3, 3]
        xz = np.asarray(pr.xz, dtype=float)
        pts.append(pb)
        L.append(unit(origin - pb))
        u.append(xz[:, 0])
        rng_.append(np.hypot(xz[:, 0], xz[:, 1]))
        grp.append(np.full(len(pb), i, dtype=np.int64))
        order.append(np.argsort(np.argsort(xz[:, 0])))
        names.append(str(getattr(pr, "id", f"p{i + 1}")))
    P = np.concatenate(pts)
    E, art_used = _errors(P, artifact, fit_center)
    Lc = np.concatenate(L)
    dist = np.concatenate(rng_)
    X = _measured_features(P, Lc, Lc, dist, {}, MEASURED_FEATURES)
    return LoopData(
        points=P, normals=_nominal_normals(P, art_used), errors=E, X=X, feature_names=list(MEASURED_FEATURES),
        fields={}, group=np.concatenate(grp), order=np.concatenate(order),
        geometry={"source_distance": dist, "L": Lc, "V": Lc, "u": np.concatenate(u)}, group_names=names,
        source="atc5_profiler", hold_by="profile",
        artifact={"nominal": artifact.to_dict(), "fit_center": fit_center,
                  "fitted": art_used.to_dict() if hasattr(art_used, "to_dict") else None},
    )


def from_profiles(path: Path, artifact: Artifact, fit_center: bool = True) -> LoopData:
    """A list file of single laser-line profiles of a certified sphere (``scan.profiles.load_profile_list``) →
    LoopData through ``calibrate.profile_table.build_profile_table``; sensor frame, mm.

    The artifact must be a sphere; only its radius is used (the certified R). The arc is **always fitted per
    profile** (centre (x, z) and radius r ≤ R: the laser plane cuts the sphere at an unknown out-of-plane offset), so
    ``fit_center`` (and a given centre) changes nothing; the description says so (``fit_center`` True). Rows: the
    table's ``kept`` points (the sphere points the product keeps). Points (x, 0, z), normals (n_x, 0, n_z), errors the
    table's (nominal − measured along the arc's normal, per axis; y carries none), X the table's
    ``PROFILE_FEATURES``; one group per profile (``hold_by="profile"``), ``order`` the rank along x in the profile.
    Field ``pose``: an id of the sensor position the repeats of a profile share (an identity the loop tests across
    the repeats: ``candidates``). Geometry: ``u`` = x; ``L`` = ``V`` = the sensor axis (0, 0, ±1) toward the sensor
    (the side the arc faces): the laser fan's origin and the camera of a profilometer known only from its data are
    unknown, so the incidence / viewing angles are the in-plane angle from the sensor axis (|``inc_plane``|), and no
    ``source_distance`` (the range coordinate is the feature ``w``). Profiles without an arc are left out (counted
    in ``artifact.failures``); none with an arc → LoopInputError."""
    from ..calibrate.profile_table import PROFILE_FEATURES, build_profile_table
    from ..scan.artifacts import Sphere
    from ..scan.profiles import load_profile_list

    path = Path(path)
    if not isinstance(artifact, Sphere):
        raise LoopInputError(f"profile list {path}: the artifact must be a sphere (its certified radius), "
                             f"got {artifact.kind}")
    records = load_profile_list(path)
    try:
        tab = build_profile_table(records, artifact.radius)
    except ValueError as e:  # no profile holds an arc of the sphere
        raise LoopInputError(f"profile list {path}: {e}") from e
    k = np.flatnonzero(tab.kept)
    prof = tab.profile[k]
    used, group = np.unique(prof, return_inverse=True)
    group = group.reshape(-1)
    xz = tab.xz[k]
    n2 = tab.normals[k]
    n = len(k)
    zeros = np.zeros(n)
    points = np.column_stack([xz[:, 0], zeros, xz[:, 1]])
    normals = np.column_stack([n2[:, 0], zeros, n2[:, 1]])
    # The sensor's side: the kept arc faces it (normals within ARC_MAX_ANGLE_DEG of its axis).
    side = np.asarray(tab.toward, dtype=float)[used]  # per profile, from the segmentation (the side the arc faces)
    L = np.zeros((n, 3))
    L[:, 2] = side[group]
    # Rank along x inside each profile.
    srt = np.lexsort((xz[:, 0], group))
    order = np.empty(n, dtype=np.int64)
    order[srt] = np.arange(n) - np.searchsorted(group[srt], group[srt])
    # One id per sensor position, the same in every list of the same folder (lists read apart, e.g. on Dask workers,
    # or a training and a validation list given together, keep repeats of one position under one id).
    root = path.resolve().parent
    pos_ids = {p_: _position_id(root, p_) for p_ in sorted({tab.positions[i] for i in used})}
    pose = np.array([pos_ids[tab.positions[i]] for i in used], dtype=float)[group]
    fails = dict(tab.failures)
    return LoopData(
        points=points, normals=normals, errors=np.asarray(tab.errors[k], dtype=float),
        X=np.asarray(tab.X[k], dtype=np.float32), feature_names=list(PROFILE_FEATURES), fields={"pose": pose},
        group=group.astype(np.int64), order=order, geometry={"u": xz[:, 0].copy(), "L": L, "V": L.copy()},
        group_names=[tab.names[i] for i in used], source="profiles", hold_by="profile",
        artifact={"nominal": Sphere(artifact.radius).to_dict(), "fit_center": True,
                  "fit": "arc fitted per profile (centre x, z and radius r <= R), certified radius R",
                  "frame": "sensor", "list": path.name, "n_profiles": len(used), "n_positions": len(pos_ids),
                  "failures": {"count": len(fails), "examples": dict(list(fails.items())[:5])}},
    )


def _position_id(root: Path, position: str) -> float:
    """A stable id (< 2⁴⁰, exact in float64) of a sensor position of the profiles under ``root``: keyed on the last
    two components of the real folder of its files (links resolved) and the position, so that a list naming the
    same files from elsewhere (a copy of the list, a folder of links, another machine's mount) gives the same ids —
    and so the same roles and results. Keyed on the list's own folder, the ids (and the loop's role draw) changed
    with where the list was written."""
    import hashlib

    folder, _, pid = position.rpartition("/")
    real = (root / folder).resolve() if folder else root.resolve()
    key = "/".join((*real.parts[-2:], pid))
    return float(int.from_bytes(hashlib.blake2b(key.encode(), digest_size=5).digest(), "big"))


def detect_kind(path: Path) -> str:
    """"bag" (.mcap or rosbag2 dir), "nist" (.xyz file or dir of them), "atc5" (dir with RobPoses.rob), "profiles"
    (a .txt list whose lines name profile files, ``PROFILE_SUFFIXES``)."""
    path = Path(path)
    if not path.exists():
        raise LoopInputError(f"input {path} does not exist")
    if path.is_file():
        if path.suffix == ".mcap":
            return "bag"
        if path.suffix == ".xyz":
            return "nist"
        if path.suffix == ".txt":
            _check_profile_list(path)
            return "profiles"
    elif (path / "RobPoses.rob").exists():
        return "atc5"
    elif (path / "metadata.yaml").exists() or any(path.glob("*.mcap")):
        return "bag"
    elif any(path.glob("*.xyz")):
        return "nist"
    raise LoopInputError(f"cannot tell what {path} holds (expected an .mcap bag, NIST .xyz files, an AT C5 "
                         "profile directory with RobPoses.rob or a .txt list of profile files)")


def _check_profile_list(path: Path) -> None:
    """A profile list names profile files only (one per line; blank and ``#`` lines skipped): else LoopInputError
    naming the list, the line and what it holds."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise LoopInputError(f"cannot read the profile list {path}: {e}") from e
    named = 0
    for i, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if Path(s).suffix.lower() not in PROFILE_SUFFIXES:
            raise LoopInputError(f"{path}:{i}: {s[:60]!r} is not a profile file ({', '.join(PROFILE_SUFFIXES)}): "
                                 "a .txt input must list profile files, one per line")
        named += 1
    if not named:
        raise LoopInputError(f"{path}: the profile list names no profile file")


def check_inputs(paths: list[str | Path], artifact_spec: str | None, feature_names: list[str] | None = None
                 ) -> tuple[str, Artifact | None, bool]:
    """The checks of :func:`load_inputs` before any data is read: ``(kind, artifact, fit_center)`` of the inputs
    (one kind for all)."""
    if not paths:
        raise LoopInputError("no input given")
    art, fit = (parse_artifact(artifact_spec) if artifact_spec else (None, False))
    kinds = {detect_kind(Path(p)) for p in paths}
    if len(kinds) > 1:
        raise LoopInputError(f"inputs of different kinds {sorted(kinds)}: run the loop once per kind")
    kind = kinds.pop()
    if kind != "bag" and art is None:
        raise LoopInputError("measured inputs need --artifact (e.g. sphere:radius=50,center=fit)")
    if kind == "profiles":
        from ..calibrate.profile_table import PROFILE_FEATURES
        from ..scan.artifacts import Sphere

        if not isinstance(art, Sphere):
            raise LoopInputError(f"profile lists are profiles of a certified sphere: give --artifact "
                                 f"sphere:radius=<R>,center=fit (got {art.kind if art is not None else None})")
        if feature_names is not None and list(feature_names) != PROFILE_FEATURES:
            raise LoopInputError(f"profile lists give only the profile features {PROFILE_FEATURES} (sensor frame, "
                                 f"no scan settings); the model needs {list(feature_names)}")
        return kind, art, fit
    if kind != "bag" and feature_names is not None and list(feature_names) != MEASURED_FEATURES:
        raise LoopInputError(f"measured {kind} data give only the features {MEASURED_FEATURES} (no scan settings); "
                             f"the model needs {list(feature_names)}")
    return kind, art, fit


def load_path(p: str | Path, kind: str, art: Artifact | None, fit: bool, feature_names: list[str] | None = None,
              read_bag: Callable[[Path], Iterable[Scan]] | None = None) -> LoopData:
    """One input of :func:`load_inputs` (after :func:`check_inputs`) → LoopData. A bag's scans are taken one at a
    time from ``read_bag`` (an iterator such as ``ros.scan_io.iter_scans`` keeps one raw scan in memory): the table
    of ``from_scans`` over all of them, groups named ``<stem>#<index>``."""
    from ..scan.measured import MeasuredDataError
    from ..scan.profiles import ProfileDataError

    try:
        if kind == "bag":
            if read_bag is None:
                raise LoopInputError("bag inputs need a bag reader (read_bag=xmetro_ros.ros.scan_io.read_scans)")
            parts = []
            for i, scan in enumerate(read_bag(Path(p))):
                if (art or scan.artifact) is None:
                    raise LoopInputError(f"scan {i} has no nominal artifact: give one with --artifact")
                parts.append(from_scans([scan], art, fit, feature_names=feature_names, names=[f"{Path(p).stem}#{i}"]))
            if not parts:
                raise LoopInputError("no scans in the input")
            return LoopData.concat(parts)
        if art is None:  # checked by check_inputs: measured inputs need an artifact
            raise LoopInputError("measured inputs need --artifact")
        if kind == "nist":
            return from_nist(Path(p), art, fit)
        if kind == "profiles":
            return from_profiles(Path(p), art, fit)
        return from_atc5(Path(p), art, fit)
    except (OSError, UnicodeDecodeError, MeasuredDataError, ProfileDataError) as e:
        raise LoopInputError(f"cannot read {p}: {e}") from e


def load_inputs(paths: list[str | Path], artifact_spec: str | None, feature_names: list[str] | None = None,
                read_bag: Callable[[Path], Iterable[Scan]] | None = None) -> LoopData:
    """All inputs of one run (they must be of one kind). ``artifact_spec`` (parse_artifact syntax) is required for
    measured files; for bags it overrides the scans' own artifact. ``feature_names``: the features of a given model
    (bags: any registry features; measured sets: only ``MEASURED_FEATURES``, they declare no scan settings; profile
    lists: only ``PROFILE_FEATURES``).
    ``read_bag``: reads the scans of a bag (``xmetro_ros.ros.scan_io.iter_scans`` or ``read_scans``; injected so
    that this core module needs no ROS). The same table, input by input on Dask workers:
    ``loop.inputs_dask.load_inputs_dask``."""
    kind, art, fit = check_inputs(paths, artifact_spec, feature_names)
    return LoopData.concat([load_path(p, kind, art, fit, feature_names, read_bag) for p in paths])
