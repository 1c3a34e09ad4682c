#!/usr/bin/env python3
"""Compares `chunkrt sample` outputs with a fixture's openpi outputs (numpy + safetensors only).

    python3 scripts/gpu-compare.py EXPECTED.safetensors GOT.safetensors [--rel-tol 0.03] [--actions-only]

Prints, per tensor both files hold (actions, v_t_step0), the max abs difference and that
difference relative to the expected tensor's RMS; exits 1 when one exceeds --rel-tol
(--actions-only: only the actions are held to it, v_t_step0 is printed).
"""
import argparse
import sys

import numpy as np
from safetensors.numpy import load_file

ap = argparse.ArgumentParser()
ap.add_argument("expected")
ap.add_argument("got")
ap.add_argument("--rel-tol", type=float, default=0.03)
ap.add_argument("--actions-only", action="store_true")
a = ap.parse_args()
exp, got = load_file(a.expected), load_file(a.got)
bad = False
for k in ("actions", "v_t_step0"):
    if k not in exp or k not in got:
        continue
    e, g = exp[k].astype(np.float64), got[k].astype(np.float64)
    if e.shape != g.shape:
        print(f"{k}: shape {g.shape} != expected {e.shape}")
        bad = True
        continue
    d = float(np.max(np.abs(e - g)))
    rms = float(np.sqrt(np.mean(e * e)))
    rel = d / max(rms, 1e-30)
    held = k == "actions" or not a.actions_only
    ok = bool(np.isfinite(d)) and (rel <= a.rel_tol or not held)
    bad |= not ok
    verdict = ("ok" if ok else "FAIL") if held else "not held to the tolerance"
    print(f"{k}: max |diff| {d:.3e}, {100 * rel:.4f} % of the RMS {rms:.3e} ({verdict})")
sys.exit(1 if bad else 0)
