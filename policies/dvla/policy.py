"""The decoders as registered policies over one checkpoint format.

Each policy loads a checkpoint (policies/dvla/checkpoint.py), turns observations into model
inputs, decodes the action tokens of one chunk with its decoder and returns the actions.
The checkpoint's attention pattern must be the one its decoder needs.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from policies.base import ChunkBatch, EpisodeContext, Observation
from policies.dvla.schedules import CACHE_MODES, CONFIDENCES, SCHEDULES
from policies.observations import cameras_of
from policies.spec import PolicySpec, param

SHIPPED = Path(__file__).resolve().parent.parent / "checkpoints"


# Training recipes whose per-block noise profile (`--noise-schedule`) shaped the weights.
NOISE_SCHEDULE_RECIPES = ("block_diffusion", "distill")
BLOCK_SIZE_HELP = (
    "action tokens per block when decoding (0 = the checkpoint's); must divide the chunk's tokens"
)


def shipped(recipe: str, suite: str = "metaworld-mt10") -> str:
    return str(SHIPPED / f"{suite}-{recipe}.safetensors")


def shipped_sets() -> list[str]:
    """The names of the shipped checkpoint sets (`metaworld-mt10`, `libero-spatial`, ...)."""
    return sorted({f.name.rsplit("-", 1)[0] for f in SHIPPED.glob("*-*.safetensors")})


def resolve_checkpoint(params: Any, recipe: str) -> None:
    """Let `checkpoint=libero-spatial` name a shipped set: it becomes that set's file for
    this decoder's recipe at parse time, so manifests and rows record the real path."""
    value = params.checkpoint
    if Path(value).exists() or "/" in value or "\\" in value:
        return  # a path (the default is one): nothing to resolve
    candidate = shipped(recipe, value)
    if Path(candidate).is_file():
        object.__setattr__(params, "checkpoint", candidate)


CHECKPOINT_HELP = "path, or a shipped set's name (e.g. libero-spatial), of a"
TEMPERATURE_HELP = "sample each token from softmax(logits / temperature) (0 = greedy arg-max)"
SEED_HELP = "seed of the sampler (temperature, confidence=random); re-seeded every chunk"


def checkpoint_fields(path: str) -> dict[str, Any]:
    """The header fields ablations group by, read without torch; {} if unreadable.

    Recorded per policy configuration in a run's manifest, so plots can use what
    training fixed (recipe, noise schedule, block size) as an axis or a hue.
    noise_schedule is None for recipes that do not use one.
    """
    try:
        with open(path, "rb") as fh:
            size = int.from_bytes(fh.read(8), "little")
            if not 0 < size < 1 << 26:
                return {}
            header = json.loads(fh.read(size))
        ours = json.loads(header["__metadata__"]["dvla_harness"])
        model, meta = ours["model"], ours.get("meta") or {}
        train = meta.get("train_config") or {}
        recipe = meta.get("recipe")
        block_causal = model.get("pattern") == "block_causal"
        return {
            "recipe": recipe,
            "noise_schedule": train.get("noise_schedule") if recipe in NOISE_SCHEDULE_RECIPES else None,
            "block_size": (model.get("block_size") or model["action_dim"]) if block_causal else None,
            "pattern": model.get("pattern"),
            "action_tokens": model["chunk_len"] * model["action_dim"],
            "train_steps": train.get("steps"),
        }
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def block_size_error(block_size: int, action_tokens: int, checkpoint_block: int | None) -> str | None:
    """Why a decode block size cannot be used, naming the valid ones; None if it can."""
    if block_size == 0 or action_tokens % block_size == 0:
        return None
    valid = [d for d in range(1, action_tokens + 1) if action_tokens % d == 0]
    own = f" (the checkpoint's, {checkpoint_block})" if checkpoint_block else " (the checkpoint's)"
    return (
        f"block_size={block_size} does not divide the chunk's {action_tokens} action tokens; "
        f"valid: 0{own}, {', '.join(map(str, valid))}"
    )


def blocks_error(params: Any, action_tokens: int) -> str | None:
    """Why `blocks` (fast_dllm's blocks per chunk) cannot cut this chunk; None if it can or
    an explicit block_size overrides it."""
    blocks = getattr(params, "blocks", None)
    if blocks is None or getattr(params, "block_size", 0) or action_tokens % blocks == 0:
        return None
    valid = [d for d in range(1, action_tokens + 1) if action_tokens % d == 0]
    return (
        f"blocks={blocks} does not divide the chunk's {action_tokens} action tokens; "
        f"valid: {', '.join(map(str, valid))} (or set block_size)"
    )


@dataclass(frozen=True)
class BidirectionalParams:
    checkpoint: str = param(shipped("bidirectional"), f"{CHECKPOINT_HELP} bidirectional model")
    steps: int = param(12, "refinement steps T (= NFE per chunk)", low=1, high=1024)
    schedule: str = param("cosine", "how many tokens stay masked after each step", choices=SCHEDULES)
    confidence: str = param("max_prob", "how positions are ranked", choices=CONFIDENCES)
    remask: float = param(0.0, "secondary remasking: max confidence threshold (0 = off)", low=0.0, high=1.0)
    cache_prefix: bool = param(
        False,
        "reuse the prefix keys/values, never refreshed (exact only if the prefix does not see "
        "the actions; stale otherwise: the pre-Fast-dLLM ablation)",
    )
    temperature: float = param(0.0, TEMPERATURE_HELP, low=0.0, high=10.0)
    seed: int = param(0, SEED_HELP, low=0, high=2**63 - 1)

    def __post_init__(self) -> None:
        resolve_checkpoint(self, "bidirectional")


# fast_dllm's defaults, chosen on held-out demonstration states by
# benchmarks/fast_dllm_sweep.py (docs/decoders-and-training.md, "Fast-dLLM's defaults");
# tests/test_fast_dllm_sweep.py checks them against benchmarks/results/fast-dllm-sweep.json.
FAST_DLLM_BLOCKS = 1
FAST_DLLM_THRESHOLD = 0.3


@dataclass(frozen=True)
class FastDLLMParams:
    checkpoint: str = param(shipped("bidirectional"), f"{CHECKPOINT_HELP} bidirectional model")
    cache: str = param(
        "dual",
        "dual: steps run the block against cached keys of all else; prefix: the block and what "
        "follows against keys before it; none: full passes (refreshed at every block start)",
        choices=CACHE_MODES,
    )
    threshold: float = param(
        FAST_DLLM_THRESHOLD,
        "commit every token at this confidence, at least one per step (0 = fixed steps); the paper's is 0.9",
        low=0.0,
        high=1.0,
    )
    block_size: int = param(
        0,
        "action tokens per block (0 = the chunk cut into `blocks`); must divide the chunk",
        low=0,
        high=4096,
    )
    blocks: int = param(
        FAST_DLLM_BLOCKS,
        "with block_size=0: blocks per chunk, which must divide the chunk's tokens (8 on a "
        "chunk of 8 actions = one action step a block, the paper's 1/8 of the answer)",
        low=1,
        high=4096,
    )
    steps_per_block: int = param(4, "steps per block when threshold=0", low=1, high=1024)
    schedule: str = param("linear", "with threshold=0: tokens left masked after each step", choices=SCHEDULES)
    confidence: str = param("max_prob", "how positions are ranked", choices=CONFIDENCES)
    temperature: float = param(0.0, TEMPERATURE_HELP, low=0.0, high=10.0)
    seed: int = param(0, SEED_HELP, low=0, high=2**63 - 1)

    # Rows recorded before `blocks` existed decoded one action step a block, which its
    # default does not reproduce: `--resume` must count them as another configuration,
    # not adopt them as made at the default (harness/run/resume.py).
    CHANGED_BY_ADDING: ClassVar[frozenset[str]] = frozenset({"blocks"})

    def __post_init__(self) -> None:
        resolve_checkpoint(self, "bidirectional")

    @staticmethod
    def unused(values: Mapping[str, Any]) -> set[str]:
        """Settings with no effect, which labels and plot axes leave out: decoding by
        threshold, the fixed-step ones; block_size 0 is no size of its own (the chunk is
        cut into `blocks`), and a block_size set overrides `blocks`."""
        unused = {"steps_per_block", "schedule"} if float(values.get("threshold", 0.9)) > 0 else set()
        return unused | ({"blocks"} if int(values.get("block_size", 0) or 0) else {"block_size"})


@dataclass(frozen=True)
class BlockDiffusionParams:
    checkpoint: str = param(shipped("block_diffusion"), f"{CHECKPOINT_HELP} block-causal model")
    steps_per_block: int = param(4, "denoising steps per block", low=1, high=1024)
    schedule: str = param(
        "linear", "how many tokens of a block stay masked after each step", choices=SCHEDULES
    )
    confidence: str = param("max_prob", "how positions are ranked", choices=CONFIDENCES)
    block_size: int = param(0, BLOCK_SIZE_HELP, low=0, high=4096)
    temperature: float = param(0.0, TEMPERATURE_HELP, low=0.0, high=10.0)
    seed: int = param(0, SEED_HELP, low=0, high=2**63 - 1)

    def __post_init__(self) -> None:
        resolve_checkpoint(self, "block_diffusion")


@dataclass(frozen=True)
class FastDVLAParams:
    checkpoint: str = param(shipped("fast_dvla"), f"{CHECKPOINT_HELP} block-causal model")
    tau_conf: float = param(0.5, "confidence a token needs to be committed", low=0.0, high=1.0)
    tau_add: float = param(2 / 7, "decoded fraction of a block before the next is added", low=0.0, high=1.0)
    tau_act: float = param(
        4 / 7, "decoded fraction of a block before the next is fully activated", low=0.0, high=1.0
    )
    n: int = param(2, "a fully activated block commits at least 1/n of its masked tokens", low=1, high=64)
    confidence: str = param("max_prob", "how positions are ranked", choices=CONFIDENCES)
    block_size: int = param(0, BLOCK_SIZE_HELP, low=0, high=4096)
    random_block_sizes: bool = param(
        False,
        "the paper's ablation: blocks of random sizes (1 to 2k-1 tokens for block size k), one "
        "partition of the chunk drawn from seed",
    )
    temperature: float = param(0.0, TEMPERATURE_HELP, low=0.0, high=10.0)
    seed: int = param(0, SEED_HELP, low=0, high=2**63 - 1)

    def __post_init__(self) -> None:
        resolve_checkpoint(self, "fast_dvla")

    def validate(self) -> None:
        if self.tau_add > self.tau_act:
            raise ValueError(f"tau_add ({self.tau_add}) must be <= tau_act ({self.tau_act})")


@dataclass(frozen=True)
class AutoregressiveParams:
    checkpoint: str = param(shipped("autoregressive"), f"{CHECKPOINT_HELP} causal model")
    temperature: float = param(0.0, TEMPERATURE_HELP, low=0.0, high=10.0)
    seed: int = param(0, SEED_HELP, low=0, high=2**63 - 1)

    def __post_init__(self) -> None:
        resolve_checkpoint(self, "autoregressive")


def check_observation_space(cfg: Any, space: Any, state_dims: Sequence[int] = ()) -> None:
    """Refuse a suite whose observations the checkpoint cannot read, before any episode:
    a wrong state size, or camera images it was trained on and the suite does not give
    (ask for them with the suite's options, e.g. `libero/spatial:obs=images`). `state_dims`
    are the raw state sizes it was trained on (`cfg.state_dim` when not recorded)."""
    import gymnasium as gym

    state = space["state"] if isinstance(space, gym.spaces.Dict) else space
    sizes = state_dims or (cfg.state_dim,)
    if len(state.shape) != 1 or state.shape[0] not in sizes:
        raise ValueError(
            f"checkpoint reads states of size {' or '.join(map(str, sizes))}, the suite gives {state.shape}"
        )
    if not cfg.cameras:
        return
    given = cameras_of(space)
    missing = [c for c in cfg.cameras if c not in given]
    if missing:
        raise ValueError(
            f"checkpoint reads camera images {list(cfg.cameras)}, the suite gives "
            f"{given or 'none'}; ask the suite for images (e.g. libero/spatial:obs=images,"
            f"image_size={cfg.image_size})"
        )
    want = (cfg.image_size, cfg.image_size, 3)
    for cam in cfg.cameras:
        if space[cam].shape != want:
            raise ValueError(
                f"checkpoint reads {cfg.image_size}x{cfg.image_size} images, the suite's {cam!r} is "
                f"{space[cam].shape[:2]}; set the suite's image_size={cfg.image_size}"
            )


class DVLAPolicy:
    """A checkpointed action-token model decoded by one of the decoders."""

    def __init__(self, params: Any, pattern: str, decode: Callable[..., Any]):
        if not Path(params.checkpoint).is_file():
            raise ValueError(
                f"checkpoint {params.checkpoint!r} does not exist; pass checkpoint=PATH or a "
                f"shipped set ({', '.join(shipped_sets())}); train one with `dvla-harness train`"
            )
        self.params = params
        self._pattern = pattern
        self._decode = decode
        self._instructions: list[str] = []
        self._load("cpu")

    def _load(self, device: str) -> None:
        from policies.dvla.checkpoint import CheckpointError, load

        try:
            self.ckpt = load(self.params.checkpoint)
        except CheckpointError as exc:
            raise ValueError(str(exc)) from None
        got = self.ckpt.model.cfg.pattern
        if got != self._pattern:
            raise ValueError(
                f"{self.params.checkpoint}: a {got} model; this decoder needs a {self._pattern} model"
            )
        self._set_block_size(getattr(self.params, "block_size", 0))
        error = blocks_error(self.params, self.ckpt.model.cfg.action_tokens)
        if error:
            raise ValueError(error)
        if device == "cpu":
            from policies.dvla.kernels import pack_linears

            pack_linears(self.ckpt.model)  # decoding's small passes, ~2x faster on a CPU
        else:
            self.ckpt.model = self.ckpt.model.to(device)
        self.model = self.ckpt.model
        self.device = device

    def to_device(self, device: str) -> None:
        """Decode on `device` ('cpu', 'cuda') from now on (`run --device`). The model is
        loaded again from its checkpoint: CPU-packed linears (policies/dvla/kernels.py) do not
        move to a GPU."""
        if device != self.device:
            self._load(device)

    def _set_block_size(self, block_size: int) -> None:
        """Decode with another block size than training used: the attention mask and the
        decoders' block bookkeeping both follow the model config, so a copy of the model
        with that config (same weights; the mask is not a weight) is all it takes."""
        cfg = self.ckpt.model.cfg
        error = block_size_error(block_size, cfg.action_tokens, cfg.block)
        if error:
            raise ValueError(error)
        if block_size in (0, cfg.block):
            return
        from policies.dvla.model import ActionTokenModel

        model = ActionTokenModel(dataclasses.replace(cfg, block_size=block_size))
        model.load_state_dict(self.ckpt.model.state_dict())
        device = next(self.ckpt.model.parameters()).device
        self.ckpt.model = model.to(device).eval()

    def check_spaces(self, observation_space: Any, action_space: Any) -> None:
        cfg = self.model.cfg
        if action_space.shape != (cfg.action_dim,):
            raise ValueError(
                f"{self.params.checkpoint}: acts in {cfg.action_dim}-D, the suite's actions are "
                f"{action_space.shape}"
            )
        try:
            check_observation_space(
                cfg, observation_space, self.ckpt.meta.get("state_dims") or (self.ckpt.raw_state_dim,)
            )
        except ValueError as exc:
            trained_on = sorted(
                {s["suite"] for s in self.ckpt.meta.get("data_sources") or [] if "suite" in s}
            )
            if not trained_on:
                raise
            # A suite option that changes the state (goal_positions=on) is in the suite's name.
            raise ValueError(f"{exc} (it was trained on {'; '.join(trained_on)})") from None

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        for ep in episodes:
            self.check_spaces(ep.observation_space, ep.action_space)
        self._instructions = [ep.instruction for ep in episodes]

    def act_batch(
        self, episodes: Sequence[EpisodeContext], observations: Sequence[Observation]
    ) -> ChunkBatch:
        """Batched inference across environments (--batch-envs): the decoders keep nothing
        between chunks (a KV cache lives inside one decode), so an episode's instruction is
        all the per-episode state there is."""
        self._instructions = [ep.instruction for ep in episodes]
        return self.act(observations)

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        import torch

        from policies.dvla.checkpoint import to_tensors

        states = np.zeros((len(observations), self.ckpt.raw_state_dim), dtype=np.float32)
        for row, o in zip(states, observations, strict=True):
            state = np.asarray(o["state"] if isinstance(o, Mapping) else o)
            row[: len(state)] = state  # zero-padded like training (mixed state layouts)
        words, state = to_tensors(self.ckpt, self._instructions, states)
        images = None
        if self.model.cfg.cameras:
            images = torch.from_numpy(
                np.stack([[o[cam] for cam in self.model.cfg.cameras] for o in observations])
            ).to(self.device)
        words, state = words.to(self.device), state.to(self.device)  # no copy on the CPU
        with torch.inference_mode():
            decoded = self._decode(self.model, words, state, self.params, images)
        actions = self.ckpt.tokenizer.decode(decoded.tokens.cpu().numpy())  # waits for the GPU
        return ChunkBatch(
            actions=actions,
            action_tokens=int(decoded.tokens.numel()),
            trace=[decoded.row_trace(row) for row in range(len(observations))],
        )


def _spec(name: str, summary: str, params: type, pattern: str, decode: Callable[..., Any]) -> PolicySpec:
    return PolicySpec(
        name=name, summary=summary, params=params, build=lambda p: DVLAPolicy(p, pattern, decode)
    )


def _generator(p: Any) -> Any:
    import torch

    return torch.Generator().manual_seed(p.seed)


def _bidirectional(m, w, s, p, i=None):
    from policies.dvla.decoders import decode_bidirectional

    return decode_bidirectional(
        m, w, s, p.steps, p.schedule, p.confidence, p.remask, p.cache_prefix, i, p.temperature, _generator(p)
    )


def _fast_dllm(m, w, s, p, i=None):
    from policies.dvla.fast_dllm import decode_fast_dllm

    return decode_fast_dllm(
        m,
        w,
        s,
        p.block_size or m.cfg.action_tokens // p.blocks,
        p.threshold,
        p.cache,
        p.steps_per_block,
        p.schedule,
        p.confidence,
        i,
        p.temperature,
        _generator(p),
    )


def _block_diffusion(m, w, s, p, i=None):
    from policies.dvla.decoders import decode_block_diffusion

    return decode_block_diffusion(
        m, w, s, p.steps_per_block, p.schedule, p.confidence, i, p.temperature, _generator(p)
    )


def _fast_dvla(m, w, s, p, i=None):
    from policies.dvla.fast_dvla import decode_fast_dvla, random_block_sizes

    sizes = (
        random_block_sizes(m.cfg.action_tokens, m.cfg.block, _generator(p)) if p.random_block_sizes else None
    )
    return decode_fast_dvla(
        m, w, s, p.tau_conf, p.tau_add, p.tau_act, p.n, p.confidence, i, p.temperature, _generator(p), sizes
    )


def _autoregressive(m, w, s, p, i=None):
    from policies.dvla.decoders import decode_autoregressive

    return decode_autoregressive(m, w, s, p.temperature, _generator(p), images=i)


SPECS = [
    _spec(
        "bidirectional",
        "dVLA baseline: all tokens masked, T parallel refinement steps, no KV cache",
        BidirectionalParams,
        "bidirectional",
        _bidirectional,
    ),
    _spec(
        "fast_dllm",
        "Fast-dLLM baseline: bidirectional model, block-wise approximate KV cache refreshed per block, confidence-threshold parallel decoding (defaults chosen by benchmarks/fast_dllm_sweep.py; the paper's literal: blocks=8,threshold=0.9)",
        FastDLLMParams,
        "bidirectional",
        _fast_dllm,
    ),
    _spec(
        "block_diffusion",
        "block-causal model, blocks one after another, finished blocks cached",
        BlockDiffusionParams,
        "block_causal",
        _block_diffusion,
    ),
    _spec(
        "fast_dvla",
        "block-causal model, pipelined parallel decoding of several blocks (Fast-dVLA)",
        FastDVLAParams,
        "block_causal",
        _fast_dvla,
    ),
    _spec(
        "autoregressive",
        "causal model, one token per forward pass, KV cache",
        AutoregressiveParams,
        "causal",
        _autoregressive,
    ),
]
