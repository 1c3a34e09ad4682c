"""Client side of the ipc_latency baseline: openpi-client's WebsocketClientPolicy sends the same
observations the iceoryx2 bench publishes and records one-way (send -> server unpacked) and
round-trip latencies in ns, written as JSON to --out.

Cases are given as NAME:CAMERAS:WIDTH:HEIGHT (CAMERAS = 0: a joint-state observation of 48 float64).
"""

import argparse
import json
import sys
import time

import numpy as np

import transport
from transport import WebsocketClientPolicy


def observation(cameras, width, height, rng):
    if cameras == 0:
        return {"observation/state": rng.standard_normal(48)}
    return {
        f"observation/image_{i}": rng.integers(0, 255, size=(height, width, 3), dtype=np.uint8) for i in range(cameras)
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--case", action="append", default=[])
    ap.add_argument("--iters", type=int, default=1000)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--gap-us", type=int, default=1000)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()

    policy = WebsocketClientPolicy(host="127.0.0.1", port=args.port)
    rng = np.random.default_rng(0)
    result = {
        "transport": "websocket + msgpack-numpy (openpi-client %s)" % transport.OPENPI_CLIENT_VERSION
        if transport.SUBSTITUTION is None
        else "websocket + msgpack-numpy (mirror)",
        "substitution": transport.SUBSTITUTION,
        "python": sys.version.split()[0],
        "cases": {},
    }
    for spec in args.case:
        name, cams, width, height = spec.split(":")
        obs = observation(int(cams), int(width), int(height), rng)
        one_way, rtt = [], []
        for i in range(args.warmup + args.iters):
            obs["seq"] = i
            t0 = time.monotonic_ns()
            reply = policy.infer(obs)
            t1 = time.monotonic_ns()
            if reply["seq"] != i:
                raise RuntimeError(f"reply for seq {reply['seq']}, expected {i}")
            if i >= args.warmup:
                one_way.append(reply["t_recv_ns"] - t0)
                rtt.append(t1 - t0)
            time.sleep(args.gap_us / 1e6)
        result["cases"][name] = {"one_way_ns": one_way, "rtt_ns": rtt}
    ws = getattr(policy, "_ws", None)
    if ws is not None:
        ws.close()
    with open(args.out, "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    main()
