#!/usr/bin/env python3
"""rrd_check: what a chunkrt recording (``chunkrt_record.py``'s ``.rrd``) holds, read back with
Rerun's own SDK (``rerun.chunk.RrdReader``).

Prints a human summary, then one JSON line: ``series`` (entity path -> rows, first and last
``robot_time`` in s, whether the times only rise in the order the file holds them),
``chunk_series`` (predicted-chunk series, one per chunk and joint), ``frames`` (camera images),
``text_logs`` (chunk log lines), ``styles`` (each series' static ``SeriesLines`` style: colour
``#rrggbb``, or ``#rrggbbaa`` when not opaque, width, name) and ``chunk_styles`` (the distinct
styles of the predicted-chunk series, each with how many series carry it; ``null`` for a series
without one). Exits 1 when the file holds no recording.

    python3 tools/python/rrd_check.py run.rrd
"""

import json
import re
import sys

import numpy as np
import rerun as rr


def series_lines(rb):
    """A static row's ``SeriesLines`` (colour ``#rrggbb[aa]``, width, name), or None."""
    names = rb.schema.names
    if "SeriesLines:colors" not in names:
        return None

    def first(col):
        if col not in names:
            return None
        vals = [v for row in rb.column(col).to_pylist() if row for v in row]
        return vals[-1] if vals else None

    rgba = first("SeriesLines:colors")
    return {
        "color": None if rgba is None else (f"#{(rgba >> 8) & 0xFFFFFF:06x}"
                                            + ("" if rgba & 0xFF == 0xFF else f"{rgba & 0xFF:02x}")),
        "width": first("SeriesLines:widths"),
        "name": first("SeriesLines:names"),
    }


def main():
    if len(sys.argv) != 2:
        print(__doc__)
        return 2
    reader = rr.chunk.RrdReader(sys.argv[1])
    if not reader.recordings():
        print(f"{sys.argv[1]}: no recording in the file")
        return 1
    times = {}
    rows = {}
    styles = {}
    for chunk in reader.stream():
        path = chunk.entity_path.lstrip("/")
        rows[path] = rows.get(path, 0) + chunk.num_rows
        if chunk.is_static:
            style = series_lines(chunk.to_record_batch())
            if style is not None:
                styles[path] = style
        if chunk.is_static or "robot_time" not in chunk.timeline_names:
            continue
        col = chunk.to_record_batch().column("robot_time")
        t = np.asarray(col.cast("int64").to_numpy(zero_copy_only=False), dtype=np.int64)
        times.setdefault(path, []).append(t)
    series = {}
    chunk_series = frames = text_logs = 0
    chunk_styles = {}
    for path, n in sorted(rows.items()):
        ts = np.concatenate(times[path]) if path in times else np.zeros(0, dtype=np.int64)
        rising = bool(np.all(np.diff(ts) >= 0)) if len(ts) else True
        if re.fullmatch(r"joints/\d+/chunks/(\d+-)?\d+", path):
            chunk_series += 1
            key = json.dumps(styles.get(path), sort_keys=True)
            chunk_styles[key] = chunk_styles.get(key, 0) + 1
            continue
        if path.startswith("cameras/"):
            frames += n
        if path == "chunks/log":
            text_logs += n
        series[path] = {
            "rows": n,
            "first_s": float(ts[0]) * 1e-9 if len(ts) else None,
            "last_s": float(ts[-1]) * 1e-9 if len(ts) else None,
            "rising": rising,
            "style": styles.get(path),
        }
    for path, s in series.items():
        print(f"{path:40} {s['rows']:8} rows  rising {s['rising']}")
    print(f"chunk series {chunk_series}, frames {frames}, chunk log lines {text_logs}")
    chunk_styles = [{"style": json.loads(k), "series": v} for k, v in sorted(chunk_styles.items())]
    for c in chunk_styles:
        print(f"chunk style {c['style']}: {c['series']} series")
    print(json.dumps({"series": series, "chunk_series": chunk_series, "frames": frames,
                      "text_logs": text_logs, "chunk_styles": chunk_styles}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
