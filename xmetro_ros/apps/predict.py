"""`xmetro predict BAG --out OUT.mcap`: the live node's processing, offline, in batch (no DDS); and the node's
outputs read back from bags and compared field by field.

Predict runs :class:`xmetro_ros.ros.node.XmetroCore` — the very object the live node runs in its worker — over the
bag's messages in order: each ScannerSettings message goes to its settings history, each PointCloud2 of the input
topics is judged (``XmetroCore.judge``), and the resulting ``~/quality``, ``~/deviations`` and ``~/corrected``
messages are written under the node's topic names (``/xmetro_node/...``), next to the inputs (``/scan``,
``/scanner_settings``), exactly as ``xmetro replay --record`` records a live run. So both can be read with
:func:`read_outputs` and compared with :func:`compare_outputs`: they are identical field by field except
``ScanQuality.processing_latency`` (wall-clock time; offline = the computing time). Node parameters: the defaults
of :mod:`xmetro_ros.ros.params`, ``--model`` and ``--param name=value`` overrides.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..ros.node_outputs import (
    POINTCLOUD2,
    QUALITY_TYPE,
    SETTINGS_TYPE,
    TF_TYPE,
    OutputSet,
    TopicError,
    classify_topics,
    describe_loss,
)

__all__ = ["PredictError", "PredictResult", "node_values", "predict_bag", "register", "run"]


class PredictError(RuntimeError):
    """The bag cannot be processed offline (no scans, model unavailable, bad parameter)."""


@dataclass
class PredictResult:
    """What ``predict_bag`` did."""

    bag: str
    out: Path
    model_id: str
    outputs: list[OutputSet] = field(default_factory=list)
    inputs: list[str] = field(default_factory=list)  # input topic of each scan
    settings_seen: int = 0
    notes: list[str] = field(default_factory=list)
    losses: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    def summary(self) -> str:
        from ..judge.flags import verdict_name

        n_def = sum(1 for o in self.outputs if o.quality.settings_defaulted)
        lines = [f"predict {self.bag} → {self.out}: {len(self.outputs)} scans, {self.settings_seen} settings, "
                 f"model {self.model_id or '(none)'}, {n_def} with defaulted settings, {self.wall_s:.2f} s"]
        for i, (o, topic) in enumerate(zip(self.outputs, self.inputs, strict=True)):
            q = o.quality
            err = f" error_code={int(q.error_code)}" if int(q.error_code) else ""
            mae = ", ".join(f"{v * 1e6:.1f}" for v in q.mean_abs_error)  # m on the topic, µm for a reader
            lines.append(f"#{i:<3d} {topic:<20s} stamp={o.stamp_ns / 1e9:.3f}s points={q.points_received} -> "
                         f"{verdict_name(int(q.verdict))}{err} valid={q.points_valid} "
                         f"usable={q.usable_fraction:.3f} mean|e|(x,y,z)=({mae}) µm"
                         + (" settings DEFAULTED" if q.settings_defaulted else "")
                         + (f" — {q.message}" if q.message else ""))
        lines += [f"note: {n}" for n in self.notes]
        lines += [f"LOSS: {x}" for x in self.losses]
        return "\n".join(lines)


def node_values(model_dir: str | Path | None = None, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The node's parameter values: defaults of :data:`node_params.PARAMS`, then ``overrides``, then ``model_dir``.

    Raises:
        PredictError: unknown parameter, wrong type or a value the node would refuse.
    """
    from ..ros import params as node_params

    specs = {p.name: p for p in node_params.PARAMS}
    values = {p.name: p.default for p in node_params.PARAMS}
    for k, v in (overrides or {}).items():
        if k not in specs:
            raise PredictError(f"unknown node parameter {k!r}")
        d = specs[k].default
        try:
            if isinstance(d, list):  # "[x, y, z]" or "x,y,z" or "x y z", as a params file would write it
                v = [float(x) for x in v] if isinstance(v, (list, tuple)) else \
                    [float(x) for x in str(v).strip("[] ").replace(",", " ").split()]
            elif isinstance(d, bool):
                v = v if isinstance(v, bool) else str(v).lower() in ("1", "true", "yes")
            elif isinstance(d, int):
                v = int(v)
            elif isinstance(d, float):
                v = float(v)
            else:
                v = str(v)
        except ValueError as e:
            raise PredictError(f"parameter {k}: {e}") from e
        if k == "cad_pose":  # the part pose's one reader: the old 12-number form refused with the pose to use
            from ..scan.part_pose import parse_pose7

            try:
                parse_pose7(v, what="cad_pose", sep=",")
            except ValueError as e:
                raise PredictError(f"invalid parameter: {e}") from e
        values[k] = v
    if model_dir is not None:
        values["model_dir"] = str(Path(model_dir).resolve())
    reason = node_params.validate(values, values)
    if reason:
        raise PredictError(f"invalid parameter: {reason}")
    return values


def _recorded_qos(reader: Any, topics: list[str]) -> list[dict[str, Any]]:
    """The offered QoS profiles the source bag recorded for ``topics`` (v9 mappings, duplicates merged); [] when
    it recorded none or something unreadable (then the caller uses the live default)."""
    from ..bag.qos import offered_qos_list

    out: list[dict[str, Any]] = []
    for t in topics:
        try:
            profiles = offered_qos_list(reader.offered_qos(t))
        except Exception:  # malformed YAML or profiles in someone else's bag: fall back to the live default
            continue
        out += [p for p in profiles if p not in out]
    return out


def predict_bag(
    bag: str | Path,
    out: str | Path,
    *,
    model_dir: str | Path | None = None,
    params: dict[str, Any] | None = None,
    topics: list[str] | None = None,
    node_name: str = "xmetro_node",
    log: Any = None,
    include: tuple[str, ...] = ("inputs", "deviations", "corrected"),
    keep_clouds: bool = True,
    deterministic: bool = False,
) -> PredictResult:
    """Judge every scan of ``bag`` as the live node would and write the outputs to ``out`` (.mcap).

    Args:
        bag: .mcap file or rosbag2 directory.
        out: output .mcap (must not exist).
        model_dir: model set directory (default: the shipped default model).
        params: node parameter overrides (SI units, as in config/xmetro.yaml).
        topics: PointCloud2 topics to judge (default: all but node outputs, as ``xmetro replay``).
        node_name: the node name used for the output topics.
        log: callable for one line per scan.
        include: what to write besides ``~/quality``: ``inputs`` (/scan, /scanner_settings), ``deviations``,
            ``corrected`` (the goldens keep only quality and deviations).
        keep_clouds: False → ``PredictResult.outputs`` keeps only each scan's ScanQuality (deviations and corrected
            None): memory stays bounded by one scan whatever the bag's length (``xmetro fleet predict``).
        deterministic: True → ``ScanQuality.processing_latency`` is written as 0.0, the one wall-clock value of
            the outputs, and the messages' CDR padding as zeros (:mod:`xmetro_ros.ros.cdr_canonical`), so the same
            bag, model and parameters give the same output file byte for byte.

    Raises:
        PredictError: no model (the reason), no input scans. FileNotFoundError / BagFormatError: unreadable bag.
        FileExistsError: ``out`` exists.
    """
    from ..bag import qos_profiles
    from ..bag.reader import BagReader
    from ..bag.writer import BagWriter
    from ..ros.cdr_canonical import canonical_cdr
    from ..ros.core import XmetroCore
    from ..ros.profile_stream import error_quality, stream_from_values

    t_start = time.monotonic()
    if Path(out).exists():
        raise FileExistsError(f"output {out} already exists")
    values = node_values(model_dir, params)
    bag = Path(bag)
    reader = BagReader(bag)
    bag_topics = reader.topics()
    try:
        scan_topics, settings_topics = classify_topics(bag_topics, topics)
    except TopicError as e:
        raise PredictError(str(e)) from e
    if not scan_topics:
        raise PredictError(f"bag {bag} has no {POINTCLOUD2} input topic (topics: "
                           + (", ".join(f"{t} [{ty}]" for t, ty in sorted(bag_topics.items())) or "none") + ")")
    core = XmetroCore(values, logger=None)
    if core.model is None:
        raise PredictError(f"no usable model: {core.degraded}")
    if core.cad_error:
        raise PredictError(core.cad_error)
    out = Path(out)
    res = PredictResult(bag=str(bag), out=out, model_id=core.model_id)
    if not settings_topics:
        res.notes.append(f"the bag has no {SETTINGS_TYPE} messages: every scan used the configured default settings "
                         f"(default_* parameters, head {core.scanner.standoff_mm:g} mm above the frame origin, "
                         "looking down); ScanQuality.settings_defaulted = true")
    enc = canonical_cdr if deterministic else (lambda msg: msg)
    ns = "/" + node_name.strip("/")
    out_topics = {"quality": f"{ns}/quality", "deviations": f"{ns}/deviations", "corrected": f"{ns}/corrected"}
    with BagWriter(out, compression="zstd") as w:
        # Inputs as recorded in the source bag (else as a live scanner offers them); outputs as the node offers them.
        w.add_topic("/scan", POINTCLOUD2, _recorded_qos(reader, scan_topics) or [qos_profiles.CLOUD])
        w.add_topic("/scanner_settings", SETTINGS_TYPE,
                    _recorded_qos(reader, settings_topics) or [qos_profiles.SETTINGS])
        w.add_topic(out_topics["quality"], QUALITY_TYPE, [qos_profiles.output()])
        w.add_topic(out_topics["deviations"], POINTCLOUD2, [qos_profiles.cloud_output()])
        w.add_topic(out_topics["corrected"], POINTCLOUD2, [qos_profiles.cloud_output()])
        if core.cad is not None:  # the cad_mesh parameter (--param cad_mesh=PART.stl): the node's ~/cad_deviations
            out_topics["cad"] = f"{ns}/cad_deviations"
            w.add_topic(out_topics["cad"], POINTCLOUD2, [qos_profiles.cloud_output()])
        # profile_input: the PointCloud2 topics are profile streams, posed by the bag's /tf and /tf_static and
        # assembled as the node does (xmetro_ros.ros.profile_stream); their scans are judged with each row's pose.
        stream = stream_from_values(values) if values["profile_input"] else None
        tf_topics = {t: t == "/tf_static" for t, ty in bag_topics.items() if ty == TF_TYPE} if stream else {}
        if stream is not None:
            w.add_topic("/profiles", POINTCLOUD2, _recorded_qos(reader, scan_topics) or [qos_profiles.CLOUD])
            for t in tf_topics:
                w.add_topic(t, TF_TYPE, _recorded_qos(reader, [t]) or [qos_profiles.SETTINGS])
            if not tf_topics:
                res.notes.append("profile_input: the bag has no /tf or /tf_static: no profile can be posed")

        def judged(o: Any, log_ns: int, topic: str) -> None:
            if deterministic:
                o.quality.processing_latency = 0.0
            for kind in ("deviations", "corrected"):
                if kind in include and getattr(o, kind) is not None:
                    w.write(out_topics[kind], enc(getattr(o, kind)), log_ns)
            w.write(out_topics["quality"], enc(o.quality), log_ns)
            if o.cad is not None:
                w.write(out_topics["cad"], enc(o.cad), log_ns)
            elif o.cad_error:
                res.notes.append(f"scan at log time {log_ns} ns: {o.cad_error}")
            res.outputs.append(OutputSet(o.quality, o.deviations if keep_clouds else None,
                                         o.corrected if keep_clouds else None))
            res.inputs.append(topic)
            if log is not None:
                log(f"#{len(res.outputs) - 1} {topic}: {o.log}")

        def streamed(scans: list[Any], errors: list[Any], log_ns: int, topic: str) -> None:
            assert stream is not None
            for scan in scans:
                msg, posed = core.posed_input(scan)
                judged(core.judge(msg, posed=posed), log_ns, topic)
                stream.done(posed.profiles, judged=True)
            for err in errors:
                w.write(out_topics["quality"], enc(error_quality(err, core.model_id)), log_ns)
                res.notes.append(f"{err.code}: {err.message}")

        last_ns = 0
        for m in reader.messages(topics=set(scan_topics) | set(settings_topics) | set(tf_topics)):
            last_ns = m.log_time_ns
            if m.topic in tf_topics:
                assert stream is not None
                if "inputs" in include:
                    w.write(m.topic, m.raw, m.log_time_ns)
                scans, errors, _refused = stream.tf(m.msg, tf_topics[m.topic], m.log_time_ns / 1e9)
                streamed(scans, errors, m.log_time_ns, m.topic)
                continue
            if stream is not None and m.topic in scan_topics:
                if "inputs" in include:
                    w.write("/profiles", m.raw, m.log_time_ns)
                streamed(*stream.profile(m.msg, m.log_time_ns / 1e9), m.log_time_ns, m.topic)
                streamed(*stream.poll(m.log_time_ns / 1e9), m.log_time_ns, m.topic)
                continue
            if m.topic in settings_topics:
                err = core.add_settings(m.msg)
                res.settings_seen += 1
                if "inputs" in include:
                    w.write("/scanner_settings", m.raw, m.log_time_ns)
                if err:
                    res.notes.append(f"invalid ScannerSettings at log time {m.log_time_ns} ns: {err}")
                continue
            if "inputs" in include:
                w.write("/scan", m.raw, m.log_time_ns)
            judged(core.judge(m.msg), m.log_time_ns, m.topic)
        if stream is not None:  # the bag's end ends the stream: the open scan is judged, held profiles reported
            streamed(*stream.flush(last_ns / 1e9), last_ns, "/profiles")
            res.notes.append("profiles: " + ", ".join(f"{k} {v}" for k, v in stream.values().items()))
    res.losses = describe_loss(reader.report)
    res.wall_s = time.monotonic() - t_start
    return res


def _parse_params(items: list[str] | None) -> dict[str, str]:
    out = {}
    for it in items or []:
        k, sep, v = it.partition("=")
        if not sep or not k:
            raise PredictError(f"--param expects name=value, got {it!r}")
        out[k.strip()] = v.strip()
    return out


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro predict`` to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser("predict", help="judge a bag's scans offline, as the live node would",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", help="a .mcap file or a rosbag2 directory")
    p.add_argument("--out", required=True, metavar="OUT.mcap", help="output MCAP (must not exist)")
    p.add_argument("--model", default=None, metavar="DIR", help="model directory (default: the shipped model)")
    p.add_argument("--topic", action="append", help="PointCloud2 topic to judge (repeatable; default: all inputs)")
    p.add_argument("--param", action="append", metavar="NAME=VALUE", help="node parameter override (repeatable)")
    p.add_argument("--allow-partial", action="store_true",
                   help="exit 0 when the bag lost data and what it held was judged (default: exit 1; the output still "
                        "holds every readable scan)")
    p.add_argument("--deterministic", action="store_true",
                   help="processing_latency written as 0 and CDR padding zeroed: identical bytes run after run")
    p.add_argument("--cad", default=None, metavar="PART.stl",
                   help="deviation map of each scan against this CAD mesh (STL/PLY/OBJ, mm), before and after "
                        "compensation (needs open3d; xmetro_ros.apps.predict_cad)")
    p.add_argument("--cad-pose", default=None, metavar="X,Y,Z,QX,QY,QZ,QW",
                   help="CAD pose part → scan frame: m + quaternion, as cad_pose (default identity)")
    p.add_argument("--cad-register", action="store_true", help="register the CAD on each compensated scan (ICP)")
    p.add_argument("--cad-report", default=None, metavar="OUT.json", help="CAD report (default OUT.cad.json)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``xmetro predict``: judge the bag offline and print the summary; returns the exit code."""
    from tqdm import tqdm

    from ..bag.reader import BagFormatError
    from .predict_cad import parse_pose

    try:  # a bad pose is said before the bag is judged
        cad_pose = parse_pose(getattr(args, "cad_pose", None))
    except ValueError as e:
        print(f"xmetro predict: error: {e}", file=sys.stderr)
        return 1
    # Progress on a terminal only (a log file or a pipe gets the summary alone).
    with tqdm(desc="xmetro predict", unit="scan", file=sys.stderr, disable=not sys.stderr.isatty(),
              leave=False) as bar:
        try:
            res = predict_bag(args.bag, args.out, model_dir=args.model, params=_parse_params(args.param),
                              topics=args.topic, deterministic=getattr(args, "deterministic", False),
                              log=lambda _line: bar.update(1))
        except (PredictError, BagFormatError, OSError) as e:
            print(f"xmetro predict: error: {e}", file=sys.stderr)
            return 1
    print(res.summary())
    if getattr(args, "cad", None):
        from .predict_cad import cad_reports, summary_lines

        try:
            rows = cad_reports(res.outputs, args.cad, pose=cad_pose, register=args.cad_register,
                               report=args.cad_report or str(Path(args.out).with_suffix(".cad.json")))
        except (ValueError, OSError) as e:
            print(f"xmetro predict: --cad: error: {e}", file=sys.stderr)
            return 1
        print("\n".join(summary_lines(rows)))
    from ..msg import ScanQuality

    foreign = [i for i, o in enumerate(res.outputs) if int(o.quality.error_code) == ScanQuality.ERROR_NOT_A_LASER_SCAN]
    if foreign:
        print(f"xmetro predict: error: {len(foreign)} of {len(res.outputs)} scans are not laser line scans of this "
              f"scanner (ERROR_NOT_A_LASER_SCAN, scans {', '.join(f'#{i}' for i in foreign[:8])}"
              f"{' ...' if len(foreign) > 8 else ''}): {res.outputs[foreign[0]].quality.message}", file=sys.stderr)
        return 1
    if res.losses and not getattr(args, "allow_partial", False):
        print(f"xmetro predict: error: the bag lost data ({len(res.losses)} LOSS line(s) above); {args.out} holds "
              "every scan that could be read. --allow-partial accepts a partial bag (exit 0).", file=sys.stderr)
        return 1
    return 0
