#!/usr/bin/env python3
"""rrd_export: a chunkrt recording's joint series and predicted chunks as one CSV, read with
Rerun's own SDK (``rerun.chunk.RrdReader``), for ``chunkrt report run.rrd``.

Writes ``path,t_ns,value`` rows: ``joints/J/measured``, ``joints/J/command``, ``joints/J/target``
(each decimated to at most ``--max-points`` rows, evenly by row) and the predicted chunks
``joints/J/chunks/ID`` in full (at most ``--max-chunks`` per joint, evenly spaced: a long run's file
stays bounded); then a comment line ``# rows PATH N`` per joint series with the rows the file
holds (before the thinning: the report says both), and ``# chunks N`` with the chunk log's count.

    python3 tools/python/rrd_export.py run.rrd out.csv [--max-points 20000] [--max-chunks 2000]
"""

import argparse
import re
import sys

import numpy as np
import rerun as rr

SERIES = re.compile(r"joints/\d+/(measured|command|target)")
CHUNK = re.compile(r"joints/\d+/chunks/(\d+-)?\d+")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("rrd")
    ap.add_argument("out")
    ap.add_argument("--max-points", type=int, default=20000)
    ap.add_argument("--max-chunks", type=int, default=2000)
    a = ap.parse_args()
    reader = rr.chunk.RrdReader(a.rrd)
    if not reader.recordings():
        print(f"{a.rrd}: no recording in the file", file=sys.stderr)
        return 1
    parts = {}
    chunk_logs = 0
    for chunk in reader.stream():
        path = chunk.entity_path.lstrip("/")
        if path == "chunks/log":
            chunk_logs += chunk.num_rows
            continue
        if not (SERIES.fullmatch(path) or CHUNK.fullmatch(path)):
            continue
        if chunk.is_static or "robot_time" not in chunk.timeline_names:
            continue
        rb = chunk.to_record_batch()
        if "Scalars:scalars" not in rb.schema.names:
            continue
        t = np.asarray(rb.column("robot_time").cast("int64").to_numpy(zero_copy_only=False),
                       dtype=np.int64)
        v = np.asarray(rb.column("Scalars:scalars").flatten().to_numpy(zero_copy_only=False),
                       dtype=np.float64)
        if len(v) != len(t):
            continue  # a row holding several scalars is not one of chunkrt's series
        parts.setdefault(path, []).append((t, v))
    # at most --max-chunks predicted chunks per joint, evenly spaced over the run
    chunk_paths = {}
    for path in parts:
        if CHUNK.fullmatch(path):
            chunk_paths.setdefault(path.split("/")[1], []).append(path)
    drop = set()
    for paths in chunk_paths.values():
        if len(paths) > a.max_chunks:
            paths.sort(key=lambda p: min(int(t[0].min()) for t in parts[p]))
            keep = set(np.linspace(0, len(paths) - 1, a.max_chunks).astype(np.int64).tolist())
            drop.update(p for i, p in enumerate(paths) if i not in keep)
    rows = 0
    recorded = {}
    with open(a.out, "w") as f:
        f.write("path,t_ns,value\n")
        for path in sorted(set(parts) - drop):
            t = np.concatenate([p[0] for p in parts[path]])
            v = np.concatenate([p[1] for p in parts[path]])
            order = np.argsort(t, kind="stable")
            t, v = t[order], v[order]
            if SERIES.fullmatch(path):
                recorded[path] = len(t)
            if SERIES.fullmatch(path) and len(t) > a.max_points:
                keep = np.linspace(0, len(t) - 1, a.max_points).astype(np.int64)
                t, v = t[keep], v[keep]
            for ti, vi in zip(t.tolist(), v.tolist()):
                f.write(f"{path},{ti},{vi:.9g}\n")
            rows += len(t)
        for path, n in sorted(recorded.items()):
            f.write(f"# rows {path} {n}\n")
        f.write(f"# chunks {chunk_logs}\n")
    print(f"{a.rrd}: {len(parts)} series, {rows} rows, {chunk_logs} chunks -> {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
