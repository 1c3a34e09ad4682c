"""openpi's own Python code as chunkrt's protocol peer (the tests' other side).

  check   openpi-client (PyPI 0.1.2, unmodified) against a `chunkrt serve`: metadata, /healthz,
          the api key, two clients at once, every kind of bad input (each answered with an error,
          the server keeps serving), and one request saved with its reply for a parity check.
  serve   openpi's own WebsocketPolicyServer (PyPI openpi-server) serving a small Python policy
          that replays a known chunk, for a chunkrt controller with policy.source = "remote".
  serve-instant, bench-client
          the remote bench's reference: openpi's server answering at once, openpi-client timing
          the round trips of a 3 x 224x224 observation.
  robots  openpi-client sending what openpi's LIBERO and DROID example clients send (their keys,
          224x224 HWC views, their state widths; the LIBERO loop's replanning) to a server with an
          openpi config: the chunk has the robot's columns (LIBERO 7, DROID 8) and the config's horizon.
  latency one openpi-client against a server with a real model (the GPU run's `chunkrt serve`):
          waits for it to come up, then times round trips of new 3 x 224x224 observations and
          prints their p50 / p99 / max beside the server's own `policy_timing` / `server_timing`.

Each check prints one line "ok NAME ..." or "FAIL NAME ..."; the exit code is 1 when any failed.
"""

import argparse
import json
import sys
import threading
import time
import urllib.error
import urllib.request

import numpy as np
from openpi_client import msgpack_numpy
from openpi_client import websocket_client_policy as wcp

FAILED = []


def report(name, ok, detail=""):
    print(("ok " if ok else "FAIL ") + name + (": " + detail if detail else ""), flush=True)
    if not ok:
        FAILED.append(name)


def observation(rng, images, state_dim, prompt="reach the red target", size=64):
    obs = {f"observation/{n}": rng.integers(0, 255, size=(size, size, 3), dtype=np.uint8) for n in images}
    obs["observation/state"] = rng.uniform(-0.5, 0.5, size=state_dim)
    obs["prompt"] = prompt
    return obs


def expect_error(url, api_key, obs, want, name, raw=None):
    """Sends one bad request on its own connection: the server must answer with an error text."""
    client = wcp.WebsocketClientPolicy(host=url, api_key=api_key)
    try:
        if raw is not None:
            client._ws.send(raw)
            resp = client._ws.recv()
            if isinstance(resp, str):
                raise RuntimeError("Error in inference server:\n" + resp)
            report(name, False, "no error for a malformed message")
            return
        client.infer(obs)
        report(name, False, "the bad request was served")
    except RuntimeError as e:
        report(name, want in str(e), str(e).splitlines()[-1][:160])
    finally:
        close(client)


def close(client):
    """Closes a client's websocket: openpi-client has no close of its own, and a server that
    bounds the connections one address holds (`chunkrt serve`: 4) counts an abandoned one."""
    try:
        client._ws.close()
    except Exception:  # noqa: BLE001 - already closed by the server
        pass


def check(args):
    url = args.url
    images = args.images.split(",")
    rng = np.random.default_rng(0)

    # /healthz
    health = url.replace("ws://", "http://") + "/healthz"
    with urllib.request.urlopen(health, timeout=5) as r:
        body = r.read().decode()
        report("healthz", r.status == 200 and body.strip() == "OK", f"{r.status} {body.strip()!r}")

    # the api key: refused without it, before any model work
    try:
        wcp.WebsocketClientPolicy(host=url)
        report("api_key_required", False, "connected without the key")
    except Exception as e:  # websockets' InvalidStatus (HTTP 401)
        report("api_key_required", "401" in str(e), type(e).__name__ + ": " + str(e)[:80])
    try:
        wcp.WebsocketClientPolicy(host=url, api_key="wrong")
        report("api_key_wrong", False, "connected with a wrong key")
    except Exception as e:
        report("api_key_wrong", "401" in str(e), type(e).__name__)

    # metadata
    client = wcp.WebsocketClientPolicy(host=url, api_key=args.api_key)
    meta = client.get_server_metadata()
    m = meta.get("chunkrt", {})
    report(
        "metadata",
        m.get("action_horizon", 0) > 0 and m.get("image_inputs") == images,
        json.dumps(meta)[:200],
    )
    horizon = m.get("action_horizon")

    # one request saved with its reply: the parity check against `chunkrt sample --request`
    obs = observation(rng, images, args.state_dim)
    obs["chunkrt/reseed"] = 7
    with open(args.request_out, "wb") as f:
        f.write(msgpack_numpy.packb(obs))
    reply = client.infer(obs)
    with open(args.reply_out, "wb") as f:
        f.write(msgpack_numpy.packb({"actions": reply["actions"]}))
    a = reply["actions"]
    report(
        "reply",
        a.shape == (horizon, args.state_dim)
        and a.dtype == np.float32
        and np.isfinite(a).all()
        and "infer_ms" in reply.get("server_timing", {})
        and "infer_ms" in reply.get("policy_timing", {}),
        f"actions {a.shape} {a.dtype}, timings {reply.get('server_timing')}",
    )
    reply2 = client.infer(observation(rng, images, args.state_dim))
    report("prev_total_ms", "prev_total_ms" in reply2.get("server_timing", {}), str(reply2.get("server_timing")))

    # two clients at once: both get their chunks, in any interleaving
    results = {}

    def worker(i):
        c = wcp.WebsocketClientPolicy(host=url, api_key=args.api_key)
        local = np.random.default_rng(100 + i)
        n = 0
        for _ in range(4):
            r = c.infer(observation(local, images, args.state_dim))
            n += r["actions"].shape == (horizon, args.state_dim)
        close(c)
        results[i] = n

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    report("two_clients", results == {0: 4, 1: 4}, str(results))

    # every bad input gets an error the client can read, and the server keeps serving
    good = observation(rng, images, args.state_dim)
    bad = []
    o = dict(good)
    del o["observation/state"]
    bad.append(("missing_key", o, "missing key", None))
    o = dict(good)
    o["observation/state"] = np.array([np.nan] + [0.0] * (args.state_dim - 1))
    bad.append(("nan_state", o, "not finite", None))
    o = dict(good)
    o[f"observation/{images[0]}"] = np.zeros((64, 64, 3), dtype=np.int32)
    bad.append(("wrong_dtype", o, "expected uint8", None))
    o = dict(good)
    o[f"observation/{images[0]}"] = np.zeros((64, 64, 4), dtype=np.uint8)
    bad.append(("wrong_shape", o, "expected [H, W, 3]", None))
    o = dict(good)
    o["observation/state"] = "not numbers"
    bad.append(("state_not_array", o, "expected a float array", None))
    o = dict(good)
    o[f"observation/{images[0]}"] = np.zeros((args.big_side, args.big_side, 3), dtype=np.uint8)
    bad.append(("too_large", o, "larger than the server's limit", None))
    bad.append(("malformed_msgpack", None, "malformed msgpack-numpy", b"\xc1\x00\x01"))
    bad.append(("text_frame", None, "expected a binary msgpack frame", "hello"))
    for name, o, want, raw in bad:
        expect_error(url, args.api_key, o, want, name, raw)
        r = client.infer(observation(rng, images, args.state_dim))
        report(name + "_then_served", r["actions"].shape == (horizon, args.state_dim))
    return 1 if FAILED else 0


class ReplayPolicy:
    """Replays one known chunk, whatever the observation (a test double, named as such)."""

    def __init__(self, chunk):
        self.chunk = chunk
        self.calls = 0

    def infer(self, obs):
        self.calls += 1
        state = np.asarray(obs["observation/state"])
        assert state.shape == (self.chunk.shape[1],), state.shape
        return {"actions": self.chunk.copy(), "policy_timing": {"infer_ms": 0.1}}


def serve(args):
    from openpi_server import WebsocketPolicyServer

    chunk = np.array(json.loads(args.chunk), dtype=np.float32)
    policy = ReplayPolicy(chunk)
    server = WebsocketPolicyServer(policy, host="127.0.0.1", port=args.port, metadata={"replay": True})
    print(f"openpi server on ws://127.0.0.1:{args.port}", flush=True)
    server.serve_forever()


class InstantPolicy:
    """Answers at once with a fixed (50, 7) chunk: the reference exchange is all wire."""

    chunk = np.zeros((50, 7), dtype=np.float32)

    def infer(self, obs):
        return {"actions": self.chunk.copy(), "policy_timing": {"infer_ms": 0.0}}


def serve_instant(args):
    from openpi_server import WebsocketPolicyServer

    WebsocketPolicyServer(InstantPolicy(), host="127.0.0.1", port=args.port).serve_forever()


def bench_client(args):
    """Round trips (ns, one per line) of 3 + N requests' last N, openpi-client to a server."""
    t0 = time.time()
    while True:
        try:
            client = wcp.WebsocketClientPolicy(host=args.url)
            break
        except OSError:
            if time.time() - t0 > 30:
                raise
            time.sleep(0.1)
    rng = np.random.default_rng(7)
    names = ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"][: args.cameras]
    obs = {f"observation/{n}": rng.integers(0, 255, size=(224, 224, 3), dtype=np.uint8) for n in names}
    obs["observation/state"] = np.zeros(7)
    obs["prompt"] = "reach the red target"
    for i in range(args.requests + 3):
        t = time.perf_counter_ns()
        client.infer(obs)
        dt = time.perf_counter_ns() - t
        if i >= 3:
            print(dt)


def pct(v, p):
    s = sorted(v)
    return s[min(len(s) - 1, max(0, int(np.ceil(p * len(s))) - 1))]


def latency(args):
    """Round trips of `--requests` new observations after `--warmup`, with the server's timings."""
    t0 = time.time()
    while True:
        try:
            client = wcp.WebsocketClientPolicy(host=args.url)
            break
        except OSError:
            if time.time() - t0 > args.wait:
                raise
            time.sleep(0.5)
    print(f"connected after {time.time() - t0:.1f} s; metadata: {json.dumps(client.get_server_metadata())[:400]}",
          flush=True)
    rng = np.random.default_rng(7)
    names = ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"][: args.cameras]
    rt, infer, server = [], [], []
    shape = None
    for i in range(args.warmup + args.requests):
        obs = {f"observation/{n}": rng.integers(0, 255, size=(args.size, args.size, 3), dtype=np.uint8)
               for n in names}
        obs["observation/state"] = rng.uniform(-0.5, 0.5, size=args.state_dim)
        obs["prompt"] = "pick up the red block"
        t = time.perf_counter()
        reply = client.infer(obs)
        dt = (time.perf_counter() - t) * 1e3
        a = np.asarray(reply["actions"])
        if not np.all(np.isfinite(a)):
            report("latency", False, f"non-finite actions in reply {i}")
            return 1
        shape = a.shape
        if i >= args.warmup:
            rt.append(dt)
            infer.append(reply.get("policy_timing", {}).get("infer_ms", float("nan")))
            server.append(reply.get("server_timing", {}).get("infer_ms", float("nan")))
    print(f"actions {shape}; {len(rt)} round trips after {args.warmup} warm-ups")
    for name, v in (("round trip (openpi-client)", rt), ("policy_timing.infer_ms", infer),
                    ("server_timing.infer_ms", server)):
        print(f"{name:28} p50 {pct(v, 0.5):8.2f} ms  p99 {pct(v, 0.99):8.2f} ms  max {max(v):8.2f} ms")
    report("latency", True, f"p50 {pct(rt, 0.5):.2f} ms p99 {pct(rt, 0.99):.2f} ms")
    return 0


def robots(args):
    """openpi's LIBERO / DROID client requests (examples/libero/main.py, examples/droid/main.py)."""
    rng = np.random.default_rng(5)
    client = wcp.WebsocketClientPolicy(host=args.url)
    view = lambda: rng.integers(0, 255, size=(224, 224, 3), dtype=np.uint8)  # noqa: E731
    if args.robot == "libero":
        plan = []
        shapes = set()
        for step in range(args.steps):
            if not plan:
                obs = {
                    "observation/image": view(),
                    "observation/wrist_image": view(),
                    "observation/state": np.concatenate(
                        [rng.uniform(-0.3, 0.3, 3), rng.uniform(-3, 3, 3), rng.uniform(0, 0.04, 2)]
                    ),
                    "prompt": "put the bowl on the plate",
                }
                chunk = client.infer(obs)["actions"]
                shapes.add(tuple(chunk.shape))
                # the example's own check and replanning
                assert len(chunk) >= args.replan, f"chunk of {len(chunk)} < replan_steps"
                plan = list(chunk[: args.replan])
            action = plan.pop(0)
            assert np.asarray(action).shape == (7,), np.asarray(action).shape
    else:
        shapes = set()
        for _ in range(args.steps):
            obs = {
                "observation/exterior_image_1_left": view(),
                "observation/wrist_image_left": view(),
                "observation/joint_position": rng.uniform(-1, 1, 7),
                "observation/gripper_position": rng.uniform(0, 1, 1),
                "prompt": "pick up the marker",
            }
            shapes.add(tuple(client.infer(obs)["actions"].shape))
    want = tuple(int(x) for x in args.shape.split("x"))
    report(f"{args.robot} chunk shape", shapes == {want}, f"{sorted(shapes)} (want {want})")
    return 1 if FAILED else 0


def lockout(args):
    """A peer on another loopback address holds every connection it can: 50 TCP connections that
    never finish their HTTP request and 16 websockets (with the api key) that never send a
    request. Then an unmodified openpi-client on 127.0.0.1 must be served; its time is printed.
    The peer's connections stay open until this process is killed."""
    import socket

    from websockets.sync import client as wsc

    host, port = args.url.removeprefix("ws://").split(":")
    port = int(port)
    held = []
    opened = 0
    for _ in range(16):
        s = socket.socket()
        s.bind((args.peer, 0))
        try:
            s.connect((host, port))
            held.append(wsc.connect(args.url, sock=s, additional_headers={"Authorization": f"Api-Key {args.api_key}"}, open_timeout=3))
            opened += 1
        except Exception:  # noqa: BLE001 - refused: the server's limit
            held.append(s)
    for _ in range(50):
        s = socket.socket()
        s.bind((args.peer, 0))
        try:
            s.connect((host, port))
            s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n")  # never finished
        except OSError:
            pass
        held.append(s)
    print(f"peer {args.peer}: {opened} of 16 idle websockets open, then 50 half-sent requests", flush=True)
    t = time.monotonic()
    client = wcp.WebsocketClientPolicy(host=args.url, api_key=args.api_key)
    rng = np.random.default_rng(1)
    client.infer(observation(rng, args.images.split(","), args.state_dim))
    print(f"served in {time.monotonic() - t:.3f} s", flush=True)
    time.sleep(60)
    return 0


def main():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("check")
    c.add_argument("--url", required=True)
    c.add_argument("--api-key", required=True)
    c.add_argument("--images", required=True, help="the model's image inputs, comma separated")
    c.add_argument("--state-dim", type=int, default=4)
    c.add_argument("--big-side", type=int, default=1024)
    c.add_argument("--request-out", required=True)
    c.add_argument("--reply-out", required=True)
    s = sub.add_parser("serve")
    s.add_argument("--port", type=int, required=True)
    s.add_argument("--chunk", required=True, help="JSON [[...], ...]: the chunk to replay")
    i = sub.add_parser("serve-instant")
    i.add_argument("--port", type=int, required=True)
    b = sub.add_parser("bench-client")
    b.add_argument("--url", required=True)
    b.add_argument("--cameras", type=int, default=3)
    b.add_argument("--requests", type=int, default=40)
    r = sub.add_parser("robots")
    r.add_argument("--url", required=True)
    r.add_argument("--robot", choices=["libero", "droid"], required=True)
    r.add_argument("--steps", type=int, default=20)
    r.add_argument("--replan", type=int, default=5)
    r.add_argument("--shape", required=True, help="HxW the chunk must have, e.g. 10x7")
    lo = sub.add_parser("lockout")
    lo.add_argument("--url", required=True)
    lo.add_argument("--api-key", required=True)
    lo.add_argument("--peer", default="127.0.0.2", help="the hostile peer's source address")
    lo.add_argument("--images", required=True)
    lo.add_argument("--state-dim", type=int, default=4)
    la = sub.add_parser("latency")
    la.add_argument("--url", required=True)
    la.add_argument("--cameras", type=int, default=3)
    la.add_argument("--size", type=int, default=224)
    la.add_argument("--state-dim", type=int, default=7)
    la.add_argument("--warmup", type=int, default=5)
    la.add_argument("--requests", type=int, default=50)
    la.add_argument("--wait", type=float, default=120.0, help="seconds to wait for the server")
    args = ap.parse_args()
    if args.cmd == "latency":
        sys.exit(latency(args))
    if args.cmd == "robots":
        sys.exit(robots(args))
    if args.cmd == "lockout":
        sys.exit(lockout(args))
    if args.cmd == "check":
        sys.exit(check(args))
    if args.cmd == "serve-instant":
        serve_instant(args)
    elif args.cmd == "bench-client":
        bench_client(args)
    else:
        serve(args)


if __name__ == "__main__":
    main()
