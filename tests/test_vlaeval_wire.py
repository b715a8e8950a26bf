"""vla-eval's wire format (policies/vlaeval_wire.py) against vla-eval's own codec (the
`vla-eval` package's protocol modules): what either side encodes, the other decodes to
the same arrays and images; and malformed messages are refused with their reason."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

pytest.importorskip("vla_eval")

from vla_eval.protocol import image_codec, numpy_codec
from vla_eval.protocol.messages import Message, MessageType, pack_message, unpack_message

from policies.vlaeval_protocol import fold_axis_angle
from policies.vlaeval_wire import MAX_IMAGE_PIXELS, pack, unpack
from policies.wire import MAX_MESSAGE_BYTES, WireError


def _observation() -> dict:
    rng = np.random.default_rng(3)
    return {
        "images": {
            "agentview": rng.integers(0, 256, (256, 256, 3), dtype=np.uint8),
            "gray": rng.integers(0, 256, (16, 12, 1), dtype=np.uint8),
            "rgba": rng.integers(0, 256, (8, 8, 4), dtype=np.uint8),
        },
        "states": rng.normal(size=8),
        "mask": np.array([True, False]),
        "ids": np.arange(6, dtype=np.int32).reshape(2, 3),
        "task_description": "put the bowl on the plate",
        "count": np.int64(4),
        "scale": np.float32(0.5),
    }


@pytest.mark.parametrize("image_format", ["png", "raw"])
def test_vla_eval_decodes_what_we_encode(image_format):
    sent = _observation()
    got = unpack_message(pack("observation", sent, 5, image_format))
    assert (got.type, got.seq) == (MessageType.OBSERVATION, 5)
    for key, image in sent["images"].items():
        # PNG is lossless; vla-eval's decoder gives a 1-channel image back 2-D (its own
        # encoder cannot write one: Pillow refuses an (H, W, 1) array)
        assert got.payload["images"][key].dtype == np.uint8
        np.testing.assert_array_equal(got.payload["images"][key].reshape(image.shape), image)
    np.testing.assert_array_equal(got.payload["states"], sent["states"])
    assert got.payload["states"].dtype == np.float64
    np.testing.assert_array_equal(got.payload["mask"], sent["mask"])
    np.testing.assert_array_equal(got.payload["ids"], sent["ids"])
    assert got.payload["task_description"] == sent["task_description"]
    assert got.payload["count"] == 4 and got.payload["scale"] == 0.5


@pytest.mark.parametrize("image_format", ["png", "raw", "jpeg"])
def test_we_decode_what_vla_eval_encodes(image_format, monkeypatch):
    monkeypatch.setattr(numpy_codec, "_image_format", image_format)
    sent = _observation()
    sent["images"].pop("gray")  # vla-eval's encoder cannot write a 1-channel image
    if image_format == "jpeg":  # RGB only, and lossy: compared with its own decoding
        sent["images"] = {"agentview": sent["images"]["agentview"]}
    got = unpack(pack_message(Message(MessageType.ACTION, sent, seq=9)))
    assert (got.type, got.seq) == ("action", 9)
    for key, image in sent["images"].items():
        if image_format == "jpeg":  # lossy: what vla-eval's own decoder makes of it
            image = image_codec.decode_image(image_codec.encode_image(image, "jpeg"))
        np.testing.assert_array_equal(got.payload["images"][key], image)  # 1 channel stays 3-D here
    np.testing.assert_array_equal(got.payload["states"], sent["states"])
    np.testing.assert_array_equal(got.payload["ids"], sent["ids"])
    assert got.payload["count"] == 4


def _raw(message: dict) -> bytes:
    return msgpack.packb(message, use_bin_type=True)


def _envelope(payload, **fields) -> bytes:
    return _raw({"type": "observation", "payload": payload, "seq": 1, "timestamp": 0.0} | fields)


def _png(width: int, height: int) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (width, height)).save(buf, format="PNG")
    return buf.getvalue()


ARRAY = {"__ndarray__": True, "data": np.zeros(3, np.float32).tobytes(), "dtype": "<f4", "shape": [3]}


MALFORMED = [
    (b"\xc1 not msgpack", "not a msgpack message"),
    ("a text frame", "sent text"),
    (_raw([1, 2]), "must be a map"),
    (_raw({"type": "observation", "payload": {}}), "without seq, timestamp"),
    (_envelope({}, type="launch"), "unknown message type 'launch'"),
    (_envelope({}, seq="1"), "seq must be an integer"),
    (_envelope({}, seq=True), "seq must be an integer"),
    (_envelope([1]), "payload must be a map"),
    (_envelope({"a": ARRAY | {"dtype": "|O"}}), "refused"),
    (_envelope({"a": ARRAY | {"dtype": "<c8", "shape": [1]}}), "refused"),
    (_envelope({"a": ARRAY | {"shape": [4]}}), "with 12 bytes of data"),
    (_envelope({"a": ARRAY | {"shape": [-3]}}), "no bytes of data"),
    (_envelope({"a": {"__ndarray__": True, "data": b""}}), "without a valid dtype and shape"),
    (_envelope({"i": {"__image__": True, "format": "gif", "data": b""}}), "needs a format"),
    (_envelope({"i": {"__image__": True, "format": "png", "data": b"not png"}}), "does not decode as png"),
    (
        _envelope({"i": {"__image__": True, "format": "png", "data": _png(4, 4), "shape": [5, 4, 3]}}),
        "decoded to",
    ),
    (
        _envelope(
            {"i": {"__image__": True, "format": "png", "data": _png(4, 4), "shape": [10**5, 10**5, 3]}}
        ),
        "over the",
    ),
    (_envelope({"i": {"__image__": True, "format": "png", "data": _png(4097, 4097)}}), "over the"),
    (_envelope({"i": {"__image__": True, "format": "raw", "data": b"\x00"}}), "raw image without its shape"),
]


@pytest.mark.parametrize(("data", "needle"), MALFORMED, ids=[needle for _, needle in MALFORMED])
def test_malformed_messages_are_refused_with_the_reason(data, needle):
    with pytest.raises(WireError, match=needle.replace("(", r"\(")):
        unpack(data)


def test_limits():
    assert 4097 * 4097 > MAX_IMAGE_PIXELS >= 256 * 256
    with pytest.raises(WireError, match="over the"):
        unpack(b"\x00" * (MAX_MESSAGE_BYTES + 1))
    with pytest.raises(WireError, match="cannot be sent"):
        pack("observation", {"a": np.array([object()])}, 1)
    with pytest.raises(WireError, match="cannot be sent"):
        pack("observation", {"a": {1, 2}}, 1)


def _robosuite_axis_angle(quat: np.ndarray) -> np.ndarray:
    """robosuite's quat2axisangle, as this harness's LIBERO state computes it."""
    w = min(max(quat[3], -1.0), 1.0)
    den = np.sqrt(1.0 - w * w)
    return np.zeros(3) if np.isclose(den, 0.0) else quat[:3] * 2.0 * np.arccos(w) / den


@pytest.mark.parametrize(
    "quat",
    [
        [0.9999, 0.0, 0.0, -0.0002],  # LIBERO's start pose: w just below 0
        [0.3, -0.5, 0.2, -0.7],
        [0.3, -0.5, 0.2, 0.7],  # w > 0: nothing to fold
        [1.0, 0.0, 0.0, 0.0],  # w = 0: vla-eval folds only w < 0
        [0.0, 0.0, 0.0, -1.0],  # the identity, both signs: zero
    ],
)
def test_folding_matches_vla_evals_quat_to_axisangle(quat):
    from vla_eval.rotation import quat_to_axisangle

    quat = np.asarray(quat, np.float64) / np.linalg.norm(quat)
    ours = fold_axis_angle(_robosuite_axis_angle(quat))
    np.testing.assert_allclose(ours, quat_to_axisangle(quat), atol=2e-6)  # vla-eval's is float32
