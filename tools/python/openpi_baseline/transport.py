"""msgpack-numpy packing and the websocket client, from openpi-client when it is installed.

openpi's policy server talks websocket + msgpack with numpy arrays packed as
{b"__ndarray__": True, b"data": bytes, b"dtype": str, b"shape": tuple}. When the `openpi-client`
package (PyPI) is importable we use its `msgpack_numpy` and `WebsocketClientPolicy`; otherwise we
mirror that wire format with `msgpack` + `websockets` and say so in SUBSTITUTION.
"""

import functools

import numpy as np

SUBSTITUTION = None
OPENPI_CLIENT_VERSION = None

try:
    from openpi_client import msgpack_numpy  # noqa: F401
    from openpi_client.websocket_client_policy import WebsocketClientPolicy  # noqa: F401

    try:
        from importlib.metadata import version

        OPENPI_CLIENT_VERSION = version("openpi-client")
    except Exception:  # pragma: no cover - metadata missing is not fatal
        OPENPI_CLIENT_VERSION = "unknown"
except ImportError:
    import msgpack
    import websockets.sync.client

    SUBSTITUTION = "openpi-client not importable: mirrored its msgpack_numpy format with msgpack + websockets"

    class _MsgpackNumpy:
        """Same wire format as openpi_client.msgpack_numpy."""

        @staticmethod
        def _pack(obj):
            if isinstance(obj, np.ndarray):
                return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
            if isinstance(obj, np.generic):
                return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
            return obj

        @staticmethod
        def _unpack(obj):
            if b"__ndarray__" in obj:
                return np.ndarray(buffer=obj[b"data"], dtype=np.dtype(obj[b"dtype"]), shape=obj[b"shape"])
            if b"__npgeneric__" in obj:
                return np.dtype(obj[b"dtype"]).type(obj[b"data"])
            return obj

        def __init__(self):
            self.Packer = functools.partial(msgpack.Packer, default=self._pack)
            self.unpackb = functools.partial(msgpack.unpackb, object_hook=self._unpack)

    msgpack_numpy = _MsgpackNumpy()

    class WebsocketClientPolicy:
        """Minimal stand-in for openpi_client's client: metadata first, then send obs / recv reply."""

        def __init__(self, host, port):
            self._ws = websockets.sync.client.connect(f"ws://{host}:{port}", compression=None, max_size=None)
            self._packer = msgpack_numpy.Packer()
            self._meta = msgpack_numpy.unpackb(self._ws.recv())

        def infer(self, obs):
            self._ws.send(self._packer.pack(obs))
            return msgpack_numpy.unpackb(self._ws.recv())
