"""Training recipes as data: which recipe, which noise schedule, which shapes.

Torch-free, so the CLI can describe and validate a training run before loading torch.
The recipes and noise schedules themselves are explained in policies/dvla/training.py.
"""

from __future__ import annotations

from dataclasses import dataclass

RECIPES = ("bidirectional", "autoregressive", "block_diffusion", "distill")
# Per-block mask ratios of the block-causal recipes (policies/dvla/training.py says what each is).
NOISE_SCHEDULES = ("clean_context", "frontier", "d2f", "linear", "sorted_uniform")
# The schedule a recipe trains with when none is named; the others use none.
DEFAULT_NOISE_SCHEDULE = {"block_diffusion": "clean_context", "distill": "frontier"}
SAMPLING = ("task", "step")
NOISY_TARGETS = ("first_action", "chunk")
STATE_FEATURES = ("raw", "relative", "proprio")
# Which training actions the tokenizer's bins span, as percentiles per dimension.
ACTION_RANGES = {"percentile": (1.0, 99.0), "full": (0.0, 100.0)}
PATTERN = {
    "bidirectional": "bidirectional",
    "autoregressive": "causal",
    "block_diffusion": "block_causal",
    "distill": "block_causal",
}


@dataclass(frozen=True)
class TrainConfig:
    recipe: str
    steps: int = 2000
    batch_size: int = 256
    lr: float = 1e-3
    weight_decay: float = 0.01
    warmup: int = 200
    seed: int = 0
    chunk_len: int = 8
    bins: int = 256
    width: int = 128
    layers: int = 4
    heads: int = 4
    ffn: int = 512
    block_size: int = 0  # 0 = one action step
    image_tokens: int = 4  # camera demonstrations: tokens per camera (a square number)
    image_coords: bool = False  # camera demonstrations: CoordConv's x/y inputs (model.py)
    noise_schedule: str = ""  # "" = the recipe's default (DEFAULT_NOISE_SCHEDULE)
    obs_noise: float = 0.01  # std of Gaussian noise on normalised states
    teacher: str = ""  # distill: the bidirectional checkpoint
    init: str = ""  # start from this checkpoint's weights, tokenizer and normalisation
    sampling: str = "task"  # "task": every instruction equally often; "step": every step equally
    probe_every: int = 0  # every N steps, the probe loss (see training.probe_loss); 0 = off
    warmup_steps: int | None = None  # None = `warmup`; a short one suits continued training
    # Rows of `collect --action-noise` folders: score only the first action of their chunk
    # (the rest answers noise the row's state cannot predict; see training._first_action_only)
    # or the whole chunk, like clean rows.
    noisy_targets: str = "first_action"
    # What the model reads of the state: "raw", or "relative" (the raw state plus each
    # world position's offset from the end effector, where the demonstrations say where
    # positions are; policies/observations.py), or "proprio" (only the robot's own leading
    # entries, where the demonstrations record how many: a camera policy that must find
    # the objects in its images, as upstream VLAs do). "" = the --init or --teacher
    # checkpoint's choice, else raw.
    state_features: str = ""
    # "percentile": bins span the 1st-99th percentile of each action dimension (DD-VLA;
    # outliers clipped); "full": every training action (nothing clipped). A fresh model's
    # only: --init and --teacher bring their tokenizer.
    action_range: str = "percentile"
    # distill only: weight of a cross-entropy term against the demonstrated tokens, added
    # to the KL to the teacher (0 = Fast-dVLA's loss, the default). Not in the paper: a
    # student that only matches the teacher inherits every blur of it; the demonstrations
    # pull it back towards what the expert did (noisy rows: first action only).
    demo_ce: float = 0.0
    # Decay of an exponential moving average of the weights, saved in their place (0 = the
    # last step's weights). Diffusion policies are usually evaluated on such an average:
    # closed-loop success swings between checkpoints a few hundred steps apart while the
    # loss barely moves, and the average smooths the last steps' noise out.
    ema: float = 0.0
    # Where the model trains: "cpu" or "cuda" (harness/device.py resolves `--device auto`).
    # Batches, masks and noise are drawn on the CPU from --seed whatever the device, so every
    # device sees the same data in the same order. Only CPU runs are known to repeat bit for
    # bit: a GPU's arithmetic differs in the last bits, and PyTorch does not promise
    # deterministic CUDA kernels (whether two GPU runs match was not measured).
    device: str = "cpu"

    @property
    def schedule(self) -> str:
        """The noise schedule this run really uses ("" for recipes without one)."""
        return self.noise_schedule or DEFAULT_NOISE_SCHEDULE.get(self.recipe, "")

    def validate(self) -> None:
        if self.recipe not in RECIPES:
            raise ValueError(f"recipe {self.recipe!r} is not one of {', '.join(RECIPES)}")
        if self.noise_schedule and self.noise_schedule not in NOISE_SCHEDULES:
            raise ValueError(
                f"noise_schedule {self.noise_schedule!r} is not one of {', '.join(NOISE_SCHEDULES)}"
            )
        if self.noise_schedule and self.recipe not in DEFAULT_NOISE_SCHEDULE:
            raise ValueError(
                f"noise_schedule {self.noise_schedule!r}: recipe {self.recipe!r} draws no per-block "
                f"mask ratios; only {' and '.join(DEFAULT_NOISE_SCHEDULE)} take a noise schedule"
            )
        if self.recipe == "distill" and self.noise_schedule == "clean_context":
            raise ValueError(
                "noise_schedule 'clean_context' is block_diffusion's loss (cross-entropy against the "
                "demonstrated tokens, each block read with the earlier ones clean); distill matches "
                "the teacher on one noisy chunk the teacher sees whole, so it takes a "
                "diffusion-forcing schedule: frontier (its default), d2f, linear or sorted_uniform"
            )
        if self.sampling not in SAMPLING:
            raise ValueError(f"sampling {self.sampling!r} is not one of {', '.join(SAMPLING)}")
        if self.noisy_targets not in NOISY_TARGETS:
            raise ValueError(f"noisy_targets {self.noisy_targets!r} is not one of {', '.join(NOISY_TARGETS)}")
        if self.state_features and self.state_features not in STATE_FEATURES:
            raise ValueError(
                f"state_features {self.state_features!r} is not one of {', '.join(STATE_FEATURES)}"
            )
        if self.action_range not in ACTION_RANGES:
            raise ValueError(f"action_range {self.action_range!r} is not one of {', '.join(ACTION_RANGES)}")
        if not 0 <= self.ema < 1:
            raise ValueError(f"ema must be in [0, 1) (a decay per step; 0 = off), got {self.ema}")
        if not self.demo_ce >= 0:
            raise ValueError(f"demo_ce must be >= 0, got {self.demo_ce}")
        if self.demo_ce and self.recipe != "distill":
            raise ValueError(
                f"demo_ce {self.demo_ce}: only distill mixes a cross-entropy term into its loss "
                f"(recipe {self.recipe!r} is cross-entropy already)"
            )
        if self.recipe == "distill" and not self.teacher:
            raise ValueError("recipe 'distill' needs --teacher CHECKPOINT (a bidirectional model)")
        for name in ("steps", "batch_size", "chunk_len", "width", "layers", "heads", "ffn", "image_tokens"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.warmup_steps is not None and self.warmup_steps < 1:
            raise ValueError(f"warmup_steps must be >= 1, got {self.warmup_steps}")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"device {self.device!r} is not one of cpu, cuda")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
