"""vla-eval's wire format: every message an envelope, arrays as string-keyed maps, images as PNG.

allenai/vla-evaluation-harness (`vla-eval` on the package index) speaks WebSocket with one
msgpack map per message, `{"type", "payload", "seq", "timestamp"}` (its
`vla_eval/protocol/messages.py`): `type` is one of hello, observation, action,
episode_start, episode_end, error; `seq` counts the sender's messages from 1 and a reply
echoes the seq of the message it answers. Inside the payload (its
`protocol/numpy_codec.py` and `image_codec.py`) a numpy array is
`{"__ndarray__": True, "data": bytes, "dtype": str, "shape": list}` with string keys
(openpi's, policies/wire.py, has bytes keys), numpy scalars travel as plain numbers, and
its client sends an HWC uint8 array with 1, 3 or 4 channels as an image,
`{"__image__": True, "format": "png"|"jpeg"|"raw", "data": bytes, "shape": list}` (PNG
by default). Only bool, integer and float arrays are allowed, as there.

This module encodes and decodes exactly that, checking what comes in more strictly than
vla-eval does (a declared shape must match the data, an image must decode to the shape
it declares and is refused before decoding when it declares more than MAX_IMAGE_PIXELS),
so neither side ever builds an array from a malformed map.
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from policies.vlaeval_protocol import IMAGE_FORMATS, TYPES
from policies.wire import MAX_MESSAGE_BYTES, WireError

MAX_IMAGE_PIXELS = 4096 * 4096  # far above any camera a benchmark renders (LIBERO's is 256 x 256)
_ALLOWED_KINDS = "biuf"  # vla-eval's _ALLOWED_DTYPE_KINDS


@dataclass(frozen=True)
class Envelope:
    """One message: its type, payload map and sequence number."""

    type: str
    payload: dict[str, Any]
    seq: int


def _is_image(array: np.ndarray) -> bool:
    """vla-eval's test for what its client sends as an image."""
    return array.ndim == 3 and array.dtype == np.uint8 and array.shape[2] in (1, 3, 4)


def _encoder(image_format: str):
    def encode(obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            if obj.dtype.kind not in _ALLOWED_KINDS:
                raise WireError(f"dtype {obj.dtype} cannot be sent (bool, integer and float arrays only)")
            if image_format != "raw" and _is_image(obj):
                data = _compress(obj, image_format)
                return {"__image__": True, "format": image_format, "data": data, "shape": list(obj.shape)}
            data = np.ascontiguousarray(obj)
            return {
                "__ndarray__": True,
                "data": data.tobytes(),
                "dtype": data.dtype.str,
                "shape": list(obj.shape),
            }
        if isinstance(obj, np.bool_):
            return bool(obj)
        if isinstance(obj, np.integer | np.floating):
            return obj.item()
        raise WireError(
            f"{type(obj).__name__} cannot be sent; send numpy arrays, numbers, text, lists and maps"
        )

    return encode


def _compress(image: np.ndarray, image_format: str) -> bytes:
    from PIL import Image

    pixels = image[:, :, 0] if image.shape[2] == 1 else image
    buf = io.BytesIO()
    if image_format == "jpeg":
        if image.shape[2] != 3:
            raise WireError(f"JPEG takes RGB images, not {image.shape[2]} channels; use png")
        Image.fromarray(np.ascontiguousarray(pixels)).save(
            buf, format="JPEG", quality=95
        )  # vla-eval's quality
    else:
        Image.fromarray(np.ascontiguousarray(pixels)).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def pack(kind: str, payload: dict[str, Any], seq: int, image_format: str = "png") -> bytes:
    """One envelope as bytes; uint8 HWC images compressed as `image_format` (png, as
    vla-eval's client sends them, or raw, or jpeg)."""
    message = {"type": kind, "payload": payload, "seq": seq, "timestamp": time.time()}
    return msgpack.packb(message, default=_encoder(image_format), use_bin_type=True)


def _decode_image(obj: dict) -> np.ndarray:
    fmt, data, shape = obj.get("format"), obj.get("data"), obj.get("shape")
    if fmt not in IMAGE_FORMATS or not isinstance(data, bytes):
        raise WireError(f"an image needs a format ({'|'.join(IMAGE_FORMATS)}) and bytes of data")
    if shape is not None:
        if not (
            isinstance(shape, list) and len(shape) == 3 and all(isinstance(n, int) and n > 0 for n in shape)
        ):
            raise WireError(f"an image's shape must be [height, width, channels], got {shape!r}")
        if shape[0] * shape[1] > MAX_IMAGE_PIXELS:
            raise WireError(f"an image of {shape[0]} x {shape[1]} pixels, over the {MAX_IMAGE_PIXELS} limit")
    if fmt == "raw":
        if shape is None:
            raise WireError("a raw image without its shape")
        return _array({"data": data, "dtype": obj.get("dtype", "|u1"), "shape": shape})
    from PIL import Image, UnidentifiedImageError

    try:
        image = Image.open(io.BytesIO(data))
        if image.width * image.height > MAX_IMAGE_PIXELS:  # read from the header, before decoding
            raise WireError(
                f"an image of {image.height} x {image.width} pixels, over the {MAX_IMAGE_PIXELS} limit"
            )
        pixels = np.asarray(image)
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
        if isinstance(exc, WireError):
            raise
        raise WireError(f"an image that does not decode as {fmt} ({type(exc).__name__}: {exc})") from None
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if pixels.dtype != np.uint8 or (shape is not None and list(pixels.shape) != shape):
        raise WireError(f"an image declared {shape} decoded to {list(pixels.shape)} {pixels.dtype}")
    return pixels


def _array(obj: dict) -> np.ndarray:
    try:
        dtype = np.dtype(obj["dtype"])
        shape = tuple(int(n) for n in obj["shape"])
    except (KeyError, TypeError, ValueError) as exc:
        raise WireError(f"an array without a valid dtype and shape ({type(exc).__name__}: {exc})") from None
    if dtype.kind not in _ALLOWED_KINDS:
        raise WireError(f"dtype {dtype} is refused (bool, integer and float arrays only)")
    data = obj.get("data")
    if any(n < 0 for n in shape) or not isinstance(data, bytes):
        raise WireError(f"an array of shape {shape} with no bytes of data")
    if len(data) != dtype.itemsize * int(np.prod(shape, dtype=np.int64)):
        raise WireError(f"an array of shape {shape} and dtype {dtype} with {len(data)} bytes of data")
    return np.frombuffer(data, dtype=dtype).reshape(shape).copy()


def _decode(obj: dict) -> Any:
    if "__image__" in obj:
        return _decode_image(obj)
    if "__ndarray__" in obj:
        return _array(obj)
    return obj


def unpack(data: bytes | str) -> Envelope:
    """An envelope from the other side, or WireError saying what is wrong with it."""
    if isinstance(data, str):
        raise WireError(f"the other side sent text, not a vla-eval message: {data[:300]}")
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError(f"a message of {len(data)} bytes, over the {MAX_MESSAGE_BYTES}-byte limit")
    try:
        raw = msgpack.unpackb(data, object_hook=_decode, raw=False)
    except WireError:
        raise
    except (msgpack.UnpackException, ValueError, TypeError) as exc:
        raise WireError(f"not a msgpack message ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise WireError(f"a message must be a map, got {type(raw).__name__}")
    missing = [key for key in ("type", "payload", "seq", "timestamp") if key not in raw]
    if missing:
        raise WireError(f"a message without {', '.join(missing)} (keys: {sorted(map(str, raw))})")
    kind, payload, seq = raw["type"], raw["payload"], raw["seq"]
    if kind not in TYPES:
        raise WireError(f"unknown message type {kind!r}; vla-eval's types: {', '.join(TYPES)}")
    if not isinstance(seq, int) or isinstance(seq, bool):
        raise WireError(f"seq must be an integer, got {seq!r}")
    if not isinstance(payload, dict):
        raise WireError(f"a {kind} message's payload must be a map, got {type(payload).__name__}")
    return Envelope(kind, payload, seq)
