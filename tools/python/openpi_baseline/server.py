"""Minimal openpi-style policy server for the ipc_latency baseline (loopback only).

Like openpi's WebsocketPolicyServer: sends msgpack metadata on connect, then for every message
unpacks the observation (msgpack-numpy), and replies with a small msgpack dict carrying the
CLOCK_MONOTONIC time right after unpacking, so the client can compute one-way latency.

Prints the listening port on stdout, exits when stdin closes (the parent went away).
"""

import argparse
import asyncio
import os
import sys
import threading
import time

import numpy as np
import websockets.asyncio.server
import websockets.exceptions

from transport import msgpack_numpy


async def handler(ws):
    packer = msgpack_numpy.Packer()
    await ws.send(packer.pack({"server": "chunkrt-openpi-baseline"}))
    try:
        async for msg in ws:
            obs = msgpack_numpy.unpackb(msg)
            t_recv = time.monotonic_ns()
            nbytes = sum(v.nbytes for v in obs.values() if isinstance(v, np.ndarray))
            await ws.send(packer.pack({"seq": obs["seq"], "t_recv_ns": t_recv, "bytes": nbytes}))
    except websockets.exceptions.ConnectionClosed:
        pass


def _exit_when_parent_goes():
    sys.stdin.read()
    os._exit(0)


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, default=0)
    args = ap.parse_args()
    threading.Thread(target=_exit_when_parent_goes, daemon=True).start()
    async with websockets.asyncio.server.serve(
        handler, "127.0.0.1", args.port, compression=None, max_size=None
    ) as server:
        port = server.sockets[0].getsockname()[1]
        print(port, flush=True)
        await server.serve_forever()


if __name__ == "__main__":
    asyncio.run(main())
