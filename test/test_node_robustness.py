"""xmetro_node under hostile and unlucky input (issue 12) and its /diagnostics conventions (issue 11), over
localhost DDS: non-physical coordinates flagged (never NaN with flags 0), every scan of a burst accounted for, the
watchdog (cooperative TIMEOUT and a stalled worker abandoned and replaced), diagnostics named after the node with a
stale check; and a stress run against a real ``xmetro_node`` process (malformed layouts, big count claims, oversize
and absurd clouds, bursts): node alive, every bad input answered with a documented code within a bound, the next
good scan judged, no published point with NaN deviation and flags 0.

Every ``~/deviations`` received is checked with ``assert_points_accounted`` (test_node_helpers)."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from test_node_helpers import (
    TIMEOUT,
    NodeClient,
    absurd_scan,
    bad_inputs,
    cloud_of,
    settings_msg,
    sim_scan,
    stamp_ns_of,
)

from xmetro_ros.judge import flags as fl
from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros.cloud import xyz_fields
from xmetro_ros.ros.convert import ns_to_stamp
from xmetro_ros.ros.dds_env import fresh_domain_id
from xmetro_ros.ros.node import XmetroNode
from xmetro_ros.ros.rclpy_util import NodeProcess, NodeSpinner, wait_for

S = 1_000_000_000
OK, WARN, ERROR = 0, 1, 2
NAME = "cell3_judge"  # a renamed node: the diagnostics status must carry this name
# Thresholds under which the simulated sphere scan is judged OK (so that "back to OK" is observable).
RELAXED = {"tolerance": 0.1, "grazing_incidence_deg": 90.0, "grazing_view_deg": 90.0, "warn_flagged_fraction": 1.0,
           "rescan_usable_fraction": 0.0, "normal_quality_min": 0.0, "domain_margin": 10.0, "min_valid_points": 50}
COUNTERS = ("scans_received", "scans_judged", "scans_dropped", "scans_lost")


@pytest.fixture(scope="module")
def rig():
    values = {**RELAXED, "scan_timeout": 1.5, "diagnostics_period": 0.2, "max_processing_time": 5.0,
              "loss_warn_period": 1.0,  # < scan_timeout: OK is seen between a loss and staleness
              "model_dir": os.environ.get("XMETRO_TEST_MODEL_DIR", "")}
    overrides = [Parameter(k, value=v) for k, v in values.items()]
    node_sp = NodeSpinner(lambda ctx: XmetroNode(NAME, context=ctx, parameter_overrides=overrides))
    cli_sp = NodeSpinner(lambda ctx: Node("xmetro_robustness_tester", context=ctx))
    client = NodeClient(cli_sp.node, target=NAME)
    try:
        client.wait_matched(node_sp.node)
        yield node_sp.node, client
        assert client.assert_all_outputs_accounted() > 0
    finally:
        cli_sp.close()
        node_sp.close()


def _vals(diag) -> dict[str, str]:
    return {kv.key: kv.value for kv in diag.status[0].values}


def _counters(q: ScanQuality) -> dict[str, int]:
    return {k: int(getattr(q, k)) for k in COUNTERS}


def _set(node: XmetroNode, **kw) -> None:
    assert all(r.successful for r in node.set_parameters([Parameter(k, value=v) for k, v in kw.items()]))


def _with_settings(node: XmetroNode, client: NodeClient, stamp_ns: int) -> None:
    client.pub_settings.publish(settings_msg(sim_scan(0), stamp_ns))
    assert wait_for(lambda: (e := node.core.settings_for(stamp_ns)) is not None and e.stamp_ns == stamp_ns, TIMEOUT)


def test_diagnostics_named_after_node_settings_never_arrived_stale_and_resume(rig):
    node, client = rig
    # no scan yet, for longer than scan_timeout: WARN (a dead scanner is visible), under the node's actual name
    d = client.wait_diag_level(WARN, 0, lambda st: "stale" in st.message)
    st = d.status[0]
    assert st.name == f"{NAME}: scan processing" and st.hardware_id == node.core.scanner.id == "xm-ls90"
    assert _vals(d)["seconds_since_last_scan"] == "never"
    # scans arrive, but no ScannerSettings ever did: judged on defaults, /diagnostics ERROR
    mark = client.diag_mark()
    q, _, _ = client.send(cloud_of(sim_scan(5 * S)))
    assert q.settings_defaulted and q.error_code == ScanQuality.ERROR_NONE
    client.wait_diag_level(ERROR, mark, lambda st: "no ScannerSettings ever arrived" in st.message)
    # settings, then good scans: OK
    _with_settings(node, client, 9 * S)
    for k in range(3):
        q, _, _ = client.send(cloud_of(sim_scan(10 * S + k)))
        assert q.verdict == ScanQuality.VERDICT_OK, q.message
    mark = client.diag_mark()
    d = client.wait_diag_level(OK, mark)
    assert int(_vals(d)["settings_received"]) >= 1
    # scans stop: WARN "stale" after scan_timeout
    mark = client.diag_mark()
    d = client.wait_diag_level(WARN, mark, lambda st: "stale" in st.message)
    assert float(_vals(d)["seconds_since_last_scan"]) > 1.5
    # scans resume: back to OK
    mark = client.diag_mark()
    q, _, _ = client.send(cloud_of(sim_scan(11 * S)))
    assert q.verdict == ScanQuality.VERDICT_OK
    d = client.wait_diag_level(OK, mark)
    assert d.status[0].name == f"{NAME}: scan processing"


def test_absurd_coordinates_flagged_never_silent_nan(rig):
    node, client = rig
    _with_settings(node, client, 19 * S)
    sc = absurd_scan(20 * S)  # 3e38 m on every third finite point
    msg = cloud_of(sc)
    q, dev, corr = client.send(msg)
    assert q.error_code == ScanQuality.ERROR_NONE, q.message
    xyz, f = xyz_fields(dev, ["dx", "dy", "dz", "flags"])
    flags = np.asarray(f["flags"]).astype(np.uint16)
    absurd = (np.abs(np.asarray(xyz)) > node.core.values["working_volume"]).any(axis=1)
    n_abs = int(absurd.sum())
    assert n_abs > 0.3 * np.isfinite(sc.points.reshape(-1, 3)).all(axis=1).sum() * 0.9
    assert np.all(flags[absurd] & fl.FLAG_OUT_OF_VOLUME)
    assert np.isnan(np.asarray(f["dx"])[absurd]).all()
    assert q.flag_counts[fl.FLAG_BITS.index(fl.FLAG_OUT_OF_VOLUME)] == n_abs
    assert list(q.flag_names) == list(fl.FLAG_NAMES) and "out_of_volume" in q.flag_names
    finite = np.isfinite(np.asarray(xyz)).all(axis=1)
    assert q.points_valid == int(finite.sum()) - n_abs
    assert np.isfinite(q.mean_abs_error).all() and np.isfinite(q.p95_abs_error).all()
    # the other points are judged; the absurd ones are left unchanged in ~/corrected
    assert np.isfinite(np.asarray(f["dx"])[~absurd & finite]).mean() > 0.9
    cxyz, _ = xyz_fields(corr)
    np.testing.assert_array_equal(np.asarray(cxyz)[absurd], np.asarray(xyz)[absurd])
    # only absurd points: NO_VALID_POINTS, saying why
    q, _, _ = client.send(cloud_of(absurd_scan(21 * S, share=1)), outputs=False)
    assert q.error_code == ScanQuality.ERROR_NO_VALID_POINTS and "working volume" in q.message
    # a 65536 x 65536 claim: BAD_LAYOUT, and points_received is the full 64-bit count
    claim = next(m for name, m, _ in bad_inputs(lambda: 22 * S, stall=False) if name == "65536 x 65536 claim")
    q, _, _ = client.send(claim, outputs=False)
    assert q.error_code == ScanQuality.ERROR_BAD_LAYOUT and q.points_received == 65536 * 65536


def test_burst_of_50_every_scan_accounted_for(rig):
    node, client = rig
    _with_settings(node, client, 29 * S)
    q0, _, _ = client.send(cloud_of(sim_scan(30 * S)))  # the publisher's baseline sequence number
    c0 = _counters(q0)
    mark0 = client.diag_mark()
    msg = cloud_of(sim_scan(31 * S))
    stamps = [31 * S + k for k in range(50)]
    for t in stamps:  # back to back: publish() serialises the message at once, so one object serves
        msg.header.stamp = ns_to_stamp(t)
        client.pub_scan.publish(msg)
    # a last scan after the burst: the queue is FIFO, so when its quality comes every burst scan is settled
    q1, _, _ = client.send(cloud_of(sim_scan(40 * S)))
    c1 = _counters(q1)
    d = {k: c1[k] - c0[k] for k in COUNTERS}
    received = d["scans_received"] - 1
    print(f"burst of 50: received {received} (judged {d['scans_judged'] - 1}, dropped {d['scans_dropped']}), "
          f"lost before the callback {d['scans_lost']}")
    assert received + d["scans_lost"] == 50
    assert c1["scans_received"] == c1["scans_judged"] + c1["scans_dropped"]  # nothing left queued or in progress
    assert received == d["scans_judged"] - 1 + d["scans_dropped"]
    # dropped scans are answered too: ERROR QUEUE_OVERFLOW (qualities may still be arriving)
    def answered() -> list[ScanQuality]:
        with client.lock:
            return [q for q in client.quality if stamp_ns_of(q) in set(stamps)]
    wait_for(lambda: len(answered()) >= received, 10.0)
    got = answered()
    assert len(got) == received
    drops = [q for q in got if q.error_code == ScanQuality.ERROR_QUEUE_OVERFLOW]
    assert len(drops) == d["scans_dropped"] and all(q.verdict == ScanQuality.VERDICT_ERROR for q in drops)
    # scans lost before the callback are said on /diagnostics (WARN for loss_warn_period, with the cause)
    if d["scans_lost"] > 0:
        client.wait_diag_level(WARN, mark0, lambda st: "lost in transport" in st.message)
    # /diagnostics carries the same accounting (OK again once loss_warn_period has passed)
    mark = client.diag_mark()
    diag = client.wait_diag_level(OK, mark, lambda st: {kv.key: kv.value for kv in st.values}
                                  .get("scans_received") == str(c1["scans_received"]))
    v = _vals(diag)
    assert [int(v[k]) for k in COUNTERS] == [c1[k] for k in COUNTERS]
    assert v["scans_queued"] == "0" and v["scans_in_progress"] == "0"


def test_watchdog_timeout_and_stalled_worker(rig):
    node, client = rig
    _with_settings(node, client, 49 * S)
    # cooperative: a bound shorter than the work → ERROR TIMEOUT, no outputs, the node goes on
    _set(node, max_processing_time=0.001)
    q, _, _ = client.send(cloud_of(sim_scan(50 * S)), outputs=False)
    assert q.error_code == ScanQuality.ERROR_TIMEOUT and "max_processing_time" in q.message, q.message
    _set(node, max_processing_time=0.5)
    assert wait_for(lambda: not node._abandoned or not node._abandoned[0].is_alive(), TIMEOUT)
    # a stage that does not come back (stands for a slow C call Python cannot interrupt)
    stall = 51 * S
    release = threading.Event()
    orig = node.core.judge

    def slow_judge(msg, t0=None, deadline=None, reference=False, posed=None):
        if stamp_ns_of(msg) == stall:
            release.wait(60.0)
        return orig(msg, t0, deadline, reference=reference, posed=posed)

    node.core.judge = slow_judge
    try:
        mark = client.diag_mark()
        t = time.monotonic()
        q, _, _ = client.send(cloud_of(sim_scan(stall)), outputs=False)
        waited = time.monotonic() - t
        assert q.error_code == ScanQuality.ERROR_TIMEOUT and "abandoned" in q.message, q.message
        assert waited < 10.0  # 2 x max_processing_time + a diagnostics period, plus DDS and a busy machine
        d = client.wait_diag_level(ERROR, mark, lambda st: "abandoned worker" in st.message)
        assert int(_vals(d)["workers_abandoned"]) >= 1
        # the replacement worker judges the next scan while the abandoned one is still blocked
        q2, _, _ = client.send(cloud_of(sim_scan(52 * S)))
        assert q2.verdict == ScanQuality.VERDICT_OK and not release.is_set()
        release.set()
        assert wait_for(lambda: not any(t.is_alive() for t in node._abandoned), TIMEOUT)
        q3, _, _ = client.send(cloud_of(sim_scan(53 * S)))
        assert q3.verdict == ScanQuality.VERDICT_OK
        mark = client.diag_mark()
        client.wait_diag_level(OK, mark)
        with client.lock:  # the abandoned worker's late result was discarded: one answer for the stalled scan
            assert sum(stamp_ns_of(m) == stall for m in client.quality) == 1
            assert not any(stamp_ns_of(m) == stall for m in client.deviations)
    finally:
        release.set()
        node.core.judge = orig
        _set(node, max_processing_time=5.0)
    c = node.diag.counters()
    assert c["scans_received"] == c["scans_judged"] + c["scans_dropped"]


def test_stress_real_node_process():
    """Bursts, oversize, absurd values, malformed layouts, big count claims against a real ``xmetro_node``."""
    domain = fresh_domain_id() % 100 + 101
    # reliable scan QoS: this test counts every scan it sends (the default best-effort one may drop under load)
    params = {**RELAXED, "max_processing_time": 1.0, "diagnostics_period": 0.5, "max_points": 100_000,
              "reliability": "reliable"}
    if os.environ.get("XMETRO_TEST_MODEL_DIR"):
        params["model_dir"] = os.environ["XMETRO_TEST_MODEL_DIR"]
    proc = NodeProcess(params=params, domain_id=domain, node_name=NAME).start(timeout=90.0)
    old = os.environ.get("ROS_DOMAIN_ID")
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    try:
        cli_sp = NodeSpinner(lambda ctx: Node("xmetro_stress_tester", context=ctx))
    finally:
        if old is None:
            os.environ.pop("ROS_DOMAIN_ID")
        else:
            os.environ["ROS_DOMAIN_ID"] = old
    t = [100 * S]

    def stamp() -> int:
        t[0] += 1000
        return t[0]

    slow: list[str] = []
    try:
        client = NodeClient(cli_sp.node, target=NAME)
        client.wait_matched()
        client.pub_settings.publish(settings_msg(sim_scan(0), 99 * S))
        good = cloud_of(sim_scan(0))

        def judge_good() -> ScanQuality:
            good.header.stamp = ns_to_stamp(stamp())
            q, dev, _ = client.send(good)
            assert q.error_code == ScanQuality.ERROR_NONE and dev is not None, q.message
            return q

        assert wait_for(lambda: not judge_good().settings_defaulted, TIMEOUT, period=0.5)
        over = cloud_of(sim_scan(stamp(), radius=27.5))  # 172 x 487 cells, twice side by side: > max_points
        rows = np.frombuffer(bytes(over.data), np.uint8).reshape(over.height, -1)
        over.width *= 2
        over.row_step = over.width * over.point_step
        over.data = np.concatenate([rows, rows], axis=1).tobytes()
        cases = [("oversize", over, {ScanQuality.ERROR_TOO_MANY_POINTS}),
                 ("absurd third", cloud_of(absurd_scan(stamp())), {ScanQuality.ERROR_NONE}),
                 *bad_inputs(stamp)]
        for name, msg, codes in cases:
            t0 = time.monotonic()
            q, _, _ = client.send(msg)
            dt = time.monotonic() - t0
            print(f"stress: {name}: code {q.error_code} in {dt * 1e3:.0f} ms ({q.message[:80]})")
            assert q.error_code in codes, (name, q.error_code, q.message)
            # every case is a cap, layout or value check (~20-100 ms here, issue 12's stall input included: no
            # case needs the watchdog any more); the limit leaves slack for DDS and a busy shared machine
            limit = 2.0
            if dt > limit:
                slow.append(f"{name}: {dt:.1f} s > {limit:g} s")
            assert proc.proc.poll() is None, f"node died on {name}"
            judge_good()  # the next good scan is processed normally
        assert not slow, f"answers too slow: {slow}"
        # a burst of 20 big scans, then a good scan: every one accounted for
        q0 = judge_good()
        big = cloud_of(sim_scan(0, radius=27.5))
        for _ in range(20):
            big.header.stamp = ns_to_stamp(stamp())
            client.pub_scan.publish(big)
        q1 = judge_good()
        d = {k: int(getattr(q1, k)) - int(getattr(q0, k)) for k in COUNTERS}
        print(f"stress: burst of 20 big scans: {d}")
        assert d["scans_received"] - 1 + d["scans_lost"] == 20, d
        assert int(q1.scans_received) == int(q1.scans_judged) + int(q1.scans_dropped)
        assert client.assert_all_outputs_accounted() >= len(cases)
        assert proc.proc.poll() is None
    finally:
        cli_sp.close()
        code = proc.stop()
    assert code == 0 or code == -9, "\n".join(proc.lines[-20:])
