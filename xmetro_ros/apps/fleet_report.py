"""The tables and page of ``xmetro fleet predict`` (``apps/fleet.py``): per-scan quality rows, the per-bag and
fleet summary Parquet files, and the self-contained HTML overview.

- :class:`BagJob`: one input bag of a fleet run and where its outputs go;
- :func:`quality_row`: one ``ScanQuality`` message as a flat row, generically from its fields (a field added to the
  message becomes a column without a change here);
- :func:`write_summary`: the done bags' per-scan tables concatenated into ``summary.parquet``;
- :func:`write_overview`: ``overview.html``, verdict shares and the median p95 |error| per cell over time (PNGs
  embedded), a table per cell and the bags' statuses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["AXES", "BagJob", "count_rows", "frame", "quality_row", "write_overview", "write_summary"]

AXES = ("x", "y", "z")


@dataclass
class BagJob:
    """One input bag and where its outputs go."""

    bag: str  # input: .mcap file or rosbag2 directory
    name: str  # relative name (no suffix), e.g. "cell3/2026-11-20"
    out: str  # output .mcap
    scans: str  # output per-scan parquet
    cell: str

    def done(self) -> bool:
        """Both outputs exist under their final names (they are renamed there only once complete)."""
        return Path(self.out).is_file() and Path(self.scans).is_file()


def _flatten(prefix: str, value: Any, row: dict[str, Any]) -> None:
    """Message fields as columns: nested messages as ``a_b``, 3-vectors as ``a_x/_y/_z``, other arrays as lists."""
    if hasattr(value, "get_fields_and_field_types"):
        for k in value.get_fields_and_field_types():
            if k == "header":
                continue
            _flatten(f"{prefix}_{k}" if prefix else k, getattr(value, k), row)
    elif isinstance(value, (list, tuple, np.ndarray)) or hasattr(value, "tolist"):
        vals = value.tolist() if hasattr(value, "tolist") else list(value)
        if len(vals) == 3 and all(isinstance(v, (int, float)) for v in vals):
            for a, v in zip(AXES, vals, strict=True):
                row[f"{prefix}_{a}"] = v
        else:
            row[prefix] = vals
    else:
        row[prefix] = value


def quality_row(q: Any) -> dict[str, Any]:
    """One ScanQuality as a flat row, generically from the message's fields (a field added to the message becomes
    a column without a change here): ``stamp_ns``, ``frame_id``; scalars as they are (SI units: metres,
    seconds); ``float64[3]`` per-axis fields as ``<name>_x``, ``_y``, ``_z`` (e.g. ``p95_abs_error_z``, metres);
    the flag counts as ``flag_<name>``; the settings as ``settings_<field>`` (e.g. ``settings_exposure_time``,
    ``settings_head_pose_position_z``); plus ``verdict_name``."""
    from ..judge.flags import verdict_name
    from ..ros.convert import stamp_to_ns

    row: dict[str, Any] = {"stamp_ns": int(stamp_to_ns(q.header.stamp)), "frame_id": q.header.frame_id}
    names = list(q.flag_names)
    for k in q.get_fields_and_field_types():
        if k in ("header", "flag_names", "flag_counts"):
            continue
        _flatten(k, getattr(q, k), row)
    for n, c in zip(names, list(q.flag_counts), strict=True):
        row[f"flag_{n}"] = int(c)
    row["verdict_name"] = verdict_name(int(q.verdict))
    return row


def frame(rows: list[dict[str, Any]]) -> Any:
    """Rows of :func:`quality_row` (plus bag, cell, scan, topic) as a DataFrame with a UTC ``time`` column."""
    import pandas as pd

    df = pd.DataFrame(rows)
    if len(df):
        df["time"] = pd.to_datetime(df["stamp_ns"], unit="ns", utc=True)
    return df


def count_rows(path: str) -> int:
    """Rows of a Parquet file (a done bag's per-scan table); 0 when it cannot be read."""
    import pyarrow.parquet as pq

    try:
        return int(pq.ParquetFile(path).metadata.num_rows)
    except (OSError, ValueError):
        return 0


def write_summary(jobs: list[BagJob], path: str | Path) -> Path | None:
    """Concatenate the done bags' per-scan tables (in job order) into one Parquet file; None when none is done."""
    import pandas as pd

    parts = [pd.read_parquet(j.scans) for j in jobs if j.done()]
    parts = [p for p in parts if len(p)]
    if not parts:
        return None
    df = pd.concat(parts, ignore_index=True)
    path = Path(path)
    df.to_parquet(path, index=False)
    return path


# ---------------------------------------------------------------------------------------------------- HTML
def write_overview(summary: str | Path, path: str | Path, bags: list[dict[str, Any]] | None = None,
                   bin_s: float | None = None) -> Path:
    """A self-contained HTML page: per cell, the share of each verdict and the median of the scans' p95 |error|
    per axis over time (bins of ``bin_s`` seconds; default: the fleet's time span / 30), PNGs embedded; then a
    table per cell and the bags' statuses. Errors in µm. Scans without a time stamp (header stamp 0, as some
    drivers and bags leave it) are counted in the tables but kept off the time axis (a 1970 date is no time); when
    no scan has one, the axis is the scans' order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    from .report_html import _COLOURS, _e, _png, _table

    df = pd.read_parquet(summary)
    stamped = df["stamp_ns"] > 0
    n_unstamped = int((~stamped).sum())
    by_order = not stamped.any()
    if by_order:  # no time at all: the scans' order is the axis (one bin per scan)
        df["bin"] = np.arange(len(df))
        df["bin_time"] = df["bin"]
        bin_s = 1.0
    else:
        st = df.loc[stamped, "stamp_ns"]
        span = float((st.max() - st.min()) / 1e9)
        bin_s = float(bin_s or max(span / 30.0, 1.0))
        t_min = int(st.min())
        df["bin"] = ((df["stamp_ns"] - t_min) // int(bin_s * 1e9)).astype(int)
        df["bin_time"] = pd.to_datetime(t_min + df["bin"] * int(bin_s * 1e9), unit="ns", utc=True)
    timed = df if by_order else df[stamped]
    verdicts = [v for v in _COLOURS if v in set(df["verdict_name"])]
    cells = sorted(df["cell"].unique())
    p95_cols = [c for c in (f"p95_abs_error_{a}" for a in AXES) if c in df]

    fig, axes = plt.subplots(len(cells), 2, figsize=(11, 2.6 * len(cells)), squeeze=False)
    for r, cell in enumerate(cells):
        d = timed[timed["cell"] == cell]
        share = pd.crosstab(d["bin_time"], d["verdict_name"], normalize="index").reindex(columns=verdicts,
                                                                                          fill_value=0.0)
        ax = axes[r][0]
        bottom = np.zeros(len(share))
        x = share.index.to_numpy() if by_order else share.index.to_pydatetime()
        width = 0.9 if by_order else bin_s / 86400.0 * 0.9  # days, matplotlib's date unit
        for v in verdicts:
            ax.bar(x, share[v].to_numpy(), width=width, bottom=bottom, color=_COLOURS[v], label=v)
            bottom += share[v].to_numpy()
        ax.set_ylabel(f"{cell}\nshare of scans")
        ax.set_ylim(0, 1)
        ax = axes[r][1]
        ok = d[d["verdict_name"] != "ERROR"]
        for c, a in zip(p95_cols, AXES, strict=False):
            med = ok.groupby("bin_time")[c].median() * 1e6  # m → µm
            ax.plot(med.index.to_numpy() if by_order else med.index.to_pydatetime(), med.to_numpy(), marker="o",
                    ms=3, label=a)
        ax.set_ylabel("median p95 |error| (µm)")
        if r == 0:
            axes[r][0].legend(fontsize=7, ncol=len(verdicts))
            ax.legend(fontsize=7, title="axis")
        for ax in axes[r]:
            ax.tick_params(axis="x", labelrotation=30, labelsize=7)
            if by_order:
                ax.set_xlabel("scan (order in the fleet; no time stamps)")
    fig.tight_layout()
    trend = _png(fig)

    rows = []
    for cell in cells:
        d = df[df["cell"] == cell]
        n = len(d)
        counts = d["verdict_name"].value_counts()
        ok = d[d["verdict_name"] != "ERROR"]
        rows.append([cell, d["bag"].nunique(), n, *(f"{100.0 * counts.get(v, 0) / n:.1f}" for v in verdicts),
                     *(f"{ok[c].median() * 1e6:.1f}" if len(ok) else "" for c in p95_cols)])
    header = ["cell", "bags", "scans", *(f"{v} %" for v in verdicts), *(f"median p95 {a} (µm)" for a in AXES[:len(
        p95_cols)])]
    if by_order:
        when = "no scan has a time stamp (header stamp 0): plotted in the order of the fleet"
    else:
        when = (f"{_e(str(timed['time'].min()))} to {_e(str(timed['time'].max()))}; time bins of {bin_s:g} s"
                + (f"; {n_unstamped} scans without a time stamp (header stamp 0) are in the tables, not on the time "
                   "axis" if n_unstamped else ""))
    bag_rows = [[b["name"], b.get("cell", ""), b["status"], b.get("scans", ""),
                 b.get("error") or "; ".join(b.get("losses") or [])] for b in (bags or [])]
    html = (
        "<!doctype html><html><head><meta charset='utf-8'><title>xmetro fleet overview</title><style>"
        "body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;font-size:13px}"
        "td,th{border:1px solid #ccc;padding:3px 8px}</style></head><body>"
        f"<h1>Fleet overview</h1><p>{len(df)} scans from {df['bag'].nunique()} bags, {len(cells)} cells; "
        f"{when}. "
        f"Errors are the model's predicted per-scan p95 |error| (ERROR scans excluded).</p>"
        f"<h2>Verdicts and error per cell over time</h2><img alt='trend' src='data:image/png;base64,{trend}'/>"
        f"<h2>Per cell</h2>{_table(header, rows)}"
        + (f"<h2>Bags</h2>{_table(['bag', 'cell', 'status', 'scans', 'error / data lost'], bag_rows)}"
           if bag_rows else "")
        + "</body></html>")
    path = Path(path)
    path.write_text(html)
    return path

