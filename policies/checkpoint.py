"""Checkpoints: weights in safetensors, everything else as JSON in its header.

One file carries what a policy needs to act (model shape and attention pattern, action
tokenizer, instruction vocabulary, state normalisation, training recipe, data hash), so
the sha256 recorded in every result row covers all of it. `NAME.json` beside it is a
readable copy. Nothing is ever unpickled.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from policies.model import ActionTokenModel, ModelConfig
from policies.observations import relative_positions
from policies.tokenizer import ActionTokenizer

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

    @property
    def raw_state_dim(self) -> int:
        """The length of the state the env gives, before the offsets are appended."""
        extra = 3 * (len(self.state_positions) - 1) if self.state_positions else 0
        return self.model.cfg.state_dim - extra

    def features(self, states: np.ndarray) -> np.ndarray:
        """What the model reads of raw states, before normalisation; training and the
        policies both go through here, so the two cannot drift apart."""
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
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable safetensors file ({exc})") from None
    if raw is None:
        raise CheckpointError(f"{path}: safetensors file without a dvla-harness header")
    try:
        header = json.loads(raw)
        if header.get("format") != FORMAT:
            raise CheckpointError(f"{path}: format {header.get('format')!r}, expected {FORMAT!r}")
        cfg = ModelConfig(**header["model"])
        model = ActionTokenModel(cfg)
        tokenizer = ActionTokenizer.from_dict(header["tokenizer"])
        positions = tuple(int(p) for p in header.get("state_positions") or ())
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, CheckpointError):
            raise
        raise CheckpointError(f"{path}: invalid header ({exc})") from None
    try:
        model.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[1].strip() if "\n" in str(exc) else str(exc)
        raise CheckpointError(f"{path}: weights do not match the model in its header ({first})") from None
    if tokenizer.action_dim != cfg.action_dim or tokenizer.bins != cfg.bins:
        raise CheckpointError(
            f"{path}: tokenizer ({tokenizer.action_dim}-D, {tokenizer.bins} bins) does not fit the model"
        )
    ckpt = Checkpoint(
        model=model.eval(),
        tokenizer=tokenizer,
        vocab={str(k): int(v) for k, v in header["vocab"].items()},
        state_mean=np.asarray(header["state_mean"], dtype=np.float32),
        state_std=np.asarray(header["state_std"], dtype=np.float32),
        meta=header.get("meta", {}),
        state_positions=positions,
    )
    if positions and (len(positions) < 2 or min(positions) < 0 or max(positions) + 3 > ckpt.raw_state_dim):
        raise CheckpointError(
            f"{path}: state_positions {list(positions)} do not fit a {ckpt.raw_state_dim}-D state "
            "(need the end effector and at least one more position, each 3 entries inside it)"
        )
    return ckpt


def to_tensors(
    ckpt: Checkpoint, instructions: list[str], states: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """Model inputs for a batch: instruction word ids and normalised states (raw states
    in, of the checkpoint's `raw_state_dim`)."""
    words = torch.tensor([ckpt.encode_instruction(t) for t in instructions], dtype=torch.long)
    norm = (ckpt.features(states) - ckpt.state_mean) / ckpt.state_std
    return words, torch.from_numpy(norm.astype(np.float32))
