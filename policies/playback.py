"""The `playback` policy: recorded episodes' actions, played back open loop.

`--policy playback:demos=DIR` plays the actions of a demonstrations folder (`dvla-harness
collect`, docs/demonstrations.md) back, episode by episode: episode j of a task gets the
actions recorded for episode j of that task, in order, whatever it observes. It reads no
observation, so any harness that starts the same episode can feed it, and two harnesses
that execute the same actions from the same start must reach the same states: the
cross-harness check with vla-eval (benchmarks/vlaeval_agreement.py) rests on that. Run
in this harness on the episodes it was recorded on, it reproduces them step for step.

An episode is matched by task and episode index, and its seed and initial state must be
the recorded ones (a playback from another start would say nothing), so a playback on
another seeding or split is that episode's failure, naming both. When the recording
runs out before the episode ends (a recording of a success played back where it did not
succeed in time), the arm holds still with the gripper as last commanded.

`gripper=sign` plays the gripper back as vla-eval's LIBERO benchmark executes it (its sign,
0 counting as +1, close): the recorded 0 ("hold the command", which LIBERO's scripted
expert sends while it grips a drawer's handle) becomes a close, so this harness executes
what vla-eval will, and the two can be compared action for action.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from policies.base import ChunkBatch, EpisodeContext, Observation
from policies.spec import PolicySpec, param

GRIPPERS = ("as_recorded", "sign")


@dataclass(frozen=True)
class PlaybackParams:
    demos: str = param("", "a demonstrations folder (dvla-harness collect) whose actions are played back")
    chunk_length: int = param(1, "actions returned per call", low=1, high=1024)
    gripper: str = param(
        "as_recorded",
        "as_recorded, or sign: +-1 by sign (0 -> +1), as vla-eval's LIBERO executes it",
        choices=GRIPPERS,
    )

    def validate(self) -> None:
        if not self.demos:
            raise ValueError("demos= is required: a folder written by `dvla-harness collect`")


@dataclass(frozen=True)
class Recorded:
    actions: np.ndarray  # (steps, action_dim) float32
    seed: int | None
    init_state_id: int | None


def load_demos(folder: Path) -> tuple[str, dict[tuple[str, int], Recorded]]:
    """(the suite the folder was collected on, its episodes by (task, episode index))."""
    import pandas as pd
    import pyarrow.parquet as pq

    manifest, steps = folder / "manifest.json", folder / "steps.parquet"
    if not manifest.is_file() or not steps.is_file():
        raise ValueError(
            f"{str(folder)!r} is not a demonstrations folder (no manifest.json and steps.parquet)"
        )
    suite = str(json.loads(manifest.read_text()).get("suite", ""))
    columns = ["task", "episode_index", "seed", "init_state_id", "step", "action"]
    table = pq.read_table(steps, columns=columns).to_pandas()
    episodes: dict[tuple[str, int], Recorded] = {}
    for (task, index), rows in table.groupby(["task", "episode_index"], sort=False):
        rows = rows.sort_values("step")
        seed, state = rows.iloc[0][["seed", "init_state_id"]]
        episodes[(str(task), int(index))] = Recorded(
            np.stack(rows["action"].to_numpy()).astype(np.float32),
            None if pd.isna(seed) else int(seed),
            None if pd.isna(state) else int(state),
        )
    return suite, episodes


class PlaybackPolicy:
    def __init__(self, params: PlaybackParams):
        self.params = params
        self.suite, self.episodes = load_demos(Path(params.demos))
        self._actions = np.zeros((0, 0), np.float32)
        self._next = 0

    def check_spaces(self, observation_space: gym.Space, action_space: gym.Space) -> None:
        any_episode = next(iter(self.episodes.values()), None)
        if any_episode is not None and any_episode.actions.shape[1:] != action_space.shape:
            raise ValueError(
                f"{self.params.demos} holds {any_episode.actions.shape[1]}-D actions; this suite takes "
                f"{list(action_space.shape)}"
            )

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        (context,) = episodes
        if context.subtask_index > 0:
            return  # a chain's next instruction: the recording goes on
        recorded = self.episodes.get((context.task, context.episode_index))
        if recorded is None:
            raise ValueError(
                f"{self.params.demos} holds no episode {context.episode_index} of task {context.task} "
                f"(collected on {self.suite}; only successful episodes are kept)"
            )
        if (recorded.seed, recorded.init_state_id) != (context.seed, context.init_state_id):
            raise ValueError(
                f"episode {context.episode_index} of {context.task} was recorded with seed {recorded.seed}, "
                f"initial state {recorded.init_state_id}; this one has seed {context.seed}, initial state "
                f"{context.init_state_id} (another seeding or split than {self.suite})"
            )
        self._actions, self._next = recorded.actions, 0
        if self.params.gripper == "sign":
            self._actions = self._actions.copy()
            self._actions[:, -1] = np.where(self._actions[:, -1] < 0, -1.0, 1.0)

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        chunk = self._actions[self._next : self._next + self.params.chunk_length]
        self._next += len(chunk)
        missing = self.params.chunk_length - len(chunk)
        if missing:
            hold = np.zeros((missing, self._actions.shape[1]), np.float32)
            hold[:, -1] = self._actions[-1, -1] if len(self._actions) else -1.0
            chunk = np.concatenate([chunk, hold])
        return ChunkBatch(actions=chunk[None])


PLAYBACK = PolicySpec(
    name="playback",
    summary="recorded episodes' actions played back open loop (demonstrations folders; no model, NFE 0)",
    params=PlaybackParams,
    build=PlaybackPolicy,
)
