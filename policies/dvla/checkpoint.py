"""Checkpoints: weights in safetensors, everything else as JSON in its header.

One file carries what a policy needs to act (model shape and attention pattern, action
tokenizer, instruction vocabulary, state normalisation, training recipe, data hash), so
the sha256 recorded in every result row covers all of it. `NAME.json` beside it is a
readable copy. Nothing is ever unpickled.
"""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from policies.dvla.model import ActionTokenModel, ModelConfig
from policies.dvla.tokenizer import ActionTokenizer
from policies.observations import relative_positions

FORMAT = "dvla-harness-checkpoint/1"
PAD, UNK = 0, 1


class CheckpointError(ValueError):
    """A checkpoint is missing, corrupt, or does not fit what was asked of it."""


def words_of(text: str) -> list[str]:
    return re.findall(r"[a-z0-9]+", text.lower())


@dataclass
class Checkpoint:
    model: ActionTokenModel
    tokenizer: ActionTokenizer
    vocab: dict[str, int]  # instruction word -> id (0 pads, 1 unknown)
    state_mean: np.ndarray
    state_std: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)  # recipe, data hash, steps, losses
    # Start indices of 3-D world positions in the raw state, the end effector's first: the
    # model reads each one's offset from the end effector too (observations.relative_positions).
    # Empty: the raw state only (every checkpoint before this field).
    state_positions: tuple[int, ...] = ()
    # > 0: the model reads only the first `state_prefix` entries of the raw state, the
    # robot's own (`train --state-features proprio`), and finds objects in its camera
    # images. 0: the whole state (every checkpoint before this field).
    state_prefix: int = 0

    @property
    def raw_state_dim(self) -> int:
        """The length of the state the env gives, before the offsets are appended (with
        a state prefix: the longest state trained on, of which the model reads the head)."""
        if self.state_prefix:
            return max([self.state_prefix, *(int(d) for d in self.meta.get("state_dims") or ())])
        extra = 3 * (len(self.state_positions) - 1) if self.state_positions else 0
        return self.model.cfg.state_dim - extra

    @property
    def state_features(self) -> str:
        """What it reads of the state, in `train --state-features` words."""
        return "proprio" if self.state_prefix else "relative" if self.state_positions else "raw"

    def features(self, states: np.ndarray) -> np.ndarray:
        """What the model reads of raw states, before normalisation; training and the
        policies both go through here, so the two cannot drift apart."""
        if self.state_prefix:
            return np.asarray(states, dtype=np.float32)[..., : self.state_prefix]
        return relative_positions(states, self.state_positions)

    def encode_instruction(self, text: str) -> list[int]:
        ids = [self.vocab.get(w, UNK) for w in words_of(text)][: self.model.cfg.max_words]
        return ids + [PAD] * (self.model.cfg.max_words - len(ids))

    def header(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "model": self.model.cfg.to_dict(),
            "tokenizer": self.tokenizer.to_dict(),
            "vocab": self.vocab,
            "state_mean": self.state_mean.tolist(),
            "state_std": self.state_std.tolist(),
            "state_positions": list(self.state_positions),
            "state_prefix": self.state_prefix,
            "meta": self.meta,
        }


def save(ckpt: Checkpoint, path: str | Path) -> Path:
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ckpt.header()
    tensors = {k: v.detach().contiguous().cpu() for k, v in ckpt.model.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata={"dvla_harness": json.dumps(header)})
    tmp.replace(path)
    path.with_suffix(".json").write_text(json.dumps(header, indent=2) + "\n")
    return path


def load(path: str | Path) -> Checkpoint:
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        with safe_open(str(path), framework="pt") as fh:
            raw = (fh.metadata() or {}).get("dvla_harness")
            shapes = {k: tuple(fh.get_slice(k).get_shape()) for k in fh.keys()}
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable safetensors file ({exc})") from None
    if raw is None:
        raise CheckpointError(f"{path}: safetensors file without a dvla-harness header")
    try:
        header = json.loads(raw)
        if not isinstance(header, dict):
            raise CheckpointError(f"{path}: invalid header (a JSON {type(header).__name__}, not an object)")
        if header.get("format") != FORMAT:
            raise CheckpointError(f"{path}: format {header.get('format')!r}, expected {FORMAT!r}")
        _check_header(header)
        cfg = ModelConfig(**header["model"])
        cfg.validate()
        _check_shapes(cfg, shapes)
        model = ActionTokenModel(cfg)
        tokenizer = ActionTokenizer.from_dict(header["tokenizer"])
        positions = tuple(int(p) for p in header.get("state_positions") or ())
        prefix = header.get("state_prefix") or 0
        if isinstance(prefix, bool) or not isinstance(prefix, int) or prefix < 0:
            raise CheckpointError(f"{path}: invalid header (state_prefix {prefix!r}: a non-negative integer)")
        if prefix and (positions or prefix != cfg.state_dim):
            raise CheckpointError(
                f"{path}: invalid header (state_prefix {prefix} with a {cfg.state_dim}-D state input"
                f"{' and state_positions' if positions else ''}: a prefix is all the model reads)"
            )
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, RecursionError) as exc:
        if isinstance(exc, CheckpointError):
            raise
        what = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise CheckpointError(f"{path}: invalid header ({what})") from None
    try:
        with safe_open(str(path), framework="pt") as fh:
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable safetensors file ({exc})") from None
    converted = sorted({str(t.dtype) for t in tensors.values() if t.is_floating_point()} - {"torch.float32"})
    if converted:
        warnings.warn(
            f"{path}: weights stored as {', '.join(converted)}, converted to float32 on load",
            stacklevel=2,
        )
    try:
        model.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[1].strip() if "\n" in str(exc) else str(exc)
        raise CheckpointError(f"{path}: weights do not match the model in its header ({first})") from None
    if tokenizer.action_dim != cfg.action_dim or tokenizer.bins != cfg.bins:
        raise CheckpointError(
            f"{path}: tokenizer ({tokenizer.action_dim}-D, {tokenizer.bins} bins) does not fit the model"
        )
    _check_normalisation(path, header, tokenizer)
    ckpt = Checkpoint(
        model=model.eval(),
        tokenizer=tokenizer,
        vocab={str(k): int(v) for k, v in header["vocab"].items()},
        state_mean=np.asarray(header["state_mean"], dtype=np.float32),
        state_std=np.asarray(header["state_std"], dtype=np.float32),
        meta=header.get("meta", {}),
        state_positions=positions,
        state_prefix=prefix,
    )
    if positions and (len(positions) < 2 or min(positions) < 0 or max(positions) + 3 > ckpt.raw_state_dim):
        raise CheckpointError(
            f"{path}: state_positions {list(positions)} do not fit a {ckpt.raw_state_dim}-D state "
            "(need the end effector and at least one more position, each 3 entries inside it)"
        )
    return ckpt


# Bounds on a header's model fields: a hostile or corrupt header must be refused before
# it allocates anything (a width of 10^9 would try to, for minutes).
_FIELD_BOUNDS = {
    "action_dim": (1, 64),
    "chunk_len": (1, 1024),
    "state_dim": (1, 1 << 16),
    "bins": (2, 1 << 16),
    "vocab_words": (2, 1 << 20),
    "max_words": (1, 4096),
    "state_tokens": (1, 256),
    "width": (1, 1 << 14),
    "layers": (1, 256),
    "heads": (1, 256),
    "ffn": (1, 1 << 16),
    "block_size": (0, 1 << 16),
    "image_size": (0, 4096),
    "image_tokens": (1, 1024),
}


def _check_header(header: dict[str, Any]) -> None:
    """The header's structure and the model's sizes, before anything is built from them."""
    for key, kind in (("model", dict), ("tokenizer", dict), ("vocab", dict), ("meta", dict)):
        if key in header and not isinstance(header[key], kind):
            raise CheckpointError(
                f"invalid header: {key!r} must be a JSON object, got {type(header[key]).__name__}"
            )
    model = header["model"]
    for name, (low, high) in _FIELD_BOUNDS.items():
        if name not in model:
            continue
        value = model[name]
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise CheckpointError(f"invalid header: model {name}={value!r}, valid range [{low}, {high}]")
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in header["vocab"].values()):
        raise CheckpointError("invalid header: vocab must map words to integer ids")


def _check_shapes(cfg: ModelConfig, shapes: dict[str, tuple[int, ...]]) -> None:
    """The file's tensors have the shapes the header's model would give them, read
    without loading them (a header that lies about sizes is refused here)."""
    with torch.device("meta"):
        expected = {k: tuple(v.shape) for k, v in ActionTokenModel(cfg).state_dict().items()}
    if expected != shapes:
        diff = sorted(set(expected) ^ set(shapes)) or [k for k in expected if expected[k] != shapes[k]]
        raise CheckpointError(
            f"invalid header: the weights do not fit the model it describes (first: {diff[0]})"
        )


def _check_normalisation(path: Path, header: dict[str, Any], tokenizer: ActionTokenizer) -> None:
    """State normalisation and tokenizer ranges must be finite, and std > 0, or every
    action would come out NaN (an ordinary-looking unsuccessful run)."""
    try:
        mean = np.asarray(header["state_mean"], dtype=np.float64)
        std = np.asarray(header["state_std"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: invalid header (state normalisation: {exc})") from None
    if mean.ndim != 1 or mean.shape != std.shape:
        raise CheckpointError(f"{path}: state_mean and state_std must be lists of one length")
    if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()):
        raise CheckpointError(f"{path}: state normalisation is not finite or has std <= 0")
    if not (np.isfinite(tokenizer.low).all() and np.isfinite(tokenizer.high).all()):
        raise CheckpointError(f"{path}: the action tokenizer's range is not finite")


def to_tensors(
    ckpt: Checkpoint, instructions: list[str], states: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """Model inputs for a batch: instruction word ids and normalised states (raw states
    in, of the checkpoint's `raw_state_dim`)."""
    words = torch.tensor([ckpt.encode_instruction(t) for t in instructions], dtype=torch.long)
    norm = (ckpt.features(states) - ckpt.state_mean) / ckpt.state_std
    return words, torch.from_numpy(norm.astype(np.float32))
