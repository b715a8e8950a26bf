"""The wire format of remote policies: msgpack with numpy arrays, as openpi encodes them.

openpi's WebSocket policy protocol (its `openpi-client` package; LeRobot and others speak
it too) sends one msgpack message per call, numpy arrays as maps
`{b"__ndarray__": True, b"data": <bytes>, b"dtype": <str>, b"shape": <list>}` and numpy
scalars as `{b"__npgeneric__": True, b"data": <value>, b"dtype": <str>}`. This module
encodes and decodes exactly that, so either side can be openpi's or ours; no pickle is
involved anywhere, and object, void and complex dtypes are refused both ways (they are
how pickle gets in, and no policy needs them).
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

MAX_MESSAGE_BYTES = 64 * 1024 * 1024  # a batch of a few 256 px images fits many times over
_REFUSED_KINDS = ("V", "O", "c")


class WireError(ValueError):
    """A message that is not what the protocol allows; the text says what was wrong."""


def _pack(obj: Any) -> Any:
    if isinstance(obj, np.ndarray | np.generic) and obj.dtype.kind in _REFUSED_KINDS:
        raise WireError(f"dtype {obj.dtype} cannot be sent (object, void and complex arrays are refused)")
    if isinstance(obj, np.ndarray):
        data = np.ascontiguousarray(obj)
        return {b"__ndarray__": True, b"data": data.tobytes(), b"dtype": data.dtype.str, b"shape": data.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise WireError(
        f"{type(obj).__name__} cannot be sent; send numpy arrays, numbers, strings, lists and maps"
    )


def _unpack(obj: dict) -> Any:
    if b"__ndarray__" in obj or b"__npgeneric__" in obj:
        try:
            dtype = np.dtype(obj[b"dtype"])
        except (KeyError, TypeError) as exc:
            raise WireError(f"an array without a valid dtype ({exc})") from None
        if dtype.kind in _REFUSED_KINDS:
            raise WireError(f"dtype {dtype} is refused (object, void and complex arrays)")
        if b"__npgeneric__" in obj:
            return dtype.type(obj[b"data"])
        shape = tuple(int(n) for n in obj[b"shape"])
        data = obj[b"data"]
        if not isinstance(data, bytes) or len(data) != dtype.itemsize * int(np.prod(shape, dtype=np.int64)):
            raise WireError(f"an array of shape {shape} and dtype {dtype} with {len(data)} bytes of data")
        return np.frombuffer(data, dtype=dtype).reshape(shape)
    return obj


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, default=_pack, use_bin_type=True)


def unpack(data: bytes | str) -> Any:
    """A message from the other side; WireError when it is not a msgpack message of the
    allowed types (a str is the openpi server's way of reporting an error)."""
    if isinstance(data, str):
        raise WireError(f"the other side sent text, not a message: {data[:500]}")
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError(f"a message of {len(data)} bytes, over the {MAX_MESSAGE_BYTES}-byte limit")
    try:
        return msgpack.unpackb(data, object_hook=_unpack, raw=False, strict_map_key=False)
    except WireError:
        raise
    except (msgpack.UnpackException, ValueError, TypeError) as exc:
        raise WireError(f"not a msgpack message ({type(exc).__name__}: {exc})") from None
