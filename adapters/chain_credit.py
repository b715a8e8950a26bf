"""CALVIN's credit rule for a chain's subtasks, apart from the simulator.

CALVIN's evaluation (calvin_models/calvin_agent/evaluation/evaluate_policy.py `rollout`)
takes the env's info when a subtask starts and, after every step, asks its task oracle
(calvin_env/envs/tasks.py `get_task_info_for_set`) whether the change the subtask names
happened between that start and now: a drawer opened from below the threshold to above
it, a light switched from off to on. A subtask whose end state already held when it
started can never be credited there.

The harness's subtasks are goals in LIBERO's predicates, not changes, so the same rule
reads: a subtask counts when its goal becomes true during the subtask (false at its
start, true at some step within its 360). A subtask whose goal already holds at its
start (an earlier subtask knocked the next grocery into the tray) fails the chain at
once, with `goal_held_at_start` in its record: running its 360 steps could not change
that (the goal is false at the start or the subtask is not credited).

Each subtask's record says where it started and ended in the chain's steps, so where
chains fail is read from the rows alone. The rule takes `holds`, a function from a
predicate to whether it holds, so the same code runs on LIBERO's live state
(adapters/chains.py) and on a hand-made state in tests.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from adapters.chain_scenes import STEPS_PER_SUBTASK, Predicate, Subtask

# What became of a subtask (its record's `outcome`).
NOT_REACHED = "not_reached"  # an earlier subtask failed
IN_PROGRESS = "in_progress"  # in force when the episode ended otherwise (an error, the budget)
COMPLETED = "completed"  # its goal became true within its steps
OUT_OF_STEPS = "out_of_steps"  # its 360 steps ran out with its goal false
GOAL_HELD_AT_START = "goal_held_at_start"  # its goal held when it started: never credited
OUTCOMES = (NOT_REACHED, IN_PROGRESS, COMPLETED, OUT_OF_STEPS, GOAL_HELD_AT_START)

Holds = Callable[[Predicate], bool]


def goal_holds(subtask: Subtask, holds: Holds) -> bool:
    """Its goal predicates all hold and none of its `goal_not` does (a take-out is done
    when its object is on its starting region and out of the tray)."""
    return all(holds(p) for p in subtask.goal) and not any(holds(p) for p in subtask.goal_not)


def subtask_record(subtask: Subtask) -> dict[str, Any]:
    """A subtask's record before it starts: what a row keeps of one never reached."""
    return {
        "id": subtask.id,
        "instruction": subtask.instruction,
        "success": False,
        "steps": 0,
        "start_step": None,
        "end_step": None,
        "goal_held_at_start": None,
        "outcome": NOT_REACHED,
    }


@dataclass
class ChainCredit:
    """One chain's progress under CALVIN's rule. `step` counts the chain's env steps
    (LIBERO's settle steps excluded, as the row's `steps`); a subtask's `start_step` is
    the count when it took over and its `end_step` the count when it ended, so its
    `steps` is their difference."""

    chain: tuple[Subtask, ...]
    records: list[dict[str, Any]] = field(default_factory=list)
    k: int = 0  # the subtask in force (len(chain) once all are completed)
    step: int = 0
    over: bool = False

    @classmethod
    def begin(cls, chain: tuple[Subtask, ...], holds: Holds) -> ChainCredit:
        credit = cls(chain, [subtask_record(s) for s in chain])
        credit._start(holds)
        return credit

    def _start(self, holds: Holds) -> None:
        """Subtask k takes over at the current step; the chain ends here if its goal holds."""
        held = goal_holds(self.chain[self.k], holds)
        record = self.records[self.k]
        record.update(start_step=self.step, end_step=self.step, goal_held_at_start=held)
        record["outcome"] = GOAL_HELD_AT_START if held else IN_PROGRESS
        self.over = held

    def after_step(self, holds: Holds) -> bool:
        """Credit the subtask in force after one env step; True when the chain is over
        (all completed, or the subtask in force failed)."""
        if self.over:
            raise RuntimeError("the chain is over; reset the env before stepping it again")
        self.step += 1
        record = self.records[self.k]
        record["end_step"] = self.step
        record["steps"] = self.step - record["start_step"]
        if goal_holds(self.chain[self.k], holds):  # false at its start, so it became true
            record.update(success=True, outcome=COMPLETED)
            self.k += 1
            if self.k == len(self.chain):
                self.over = True
            else:
                self._start(holds)
        elif record["steps"] >= STEPS_PER_SUBTASK:
            record["outcome"] = OUT_OF_STEPS
            self.over = True  # the chain stops at its first failed subtask
        return self.over

    @property
    def completed(self) -> int:
        return sum(r["success"] for r in self.records)

    @property
    def in_force(self) -> int:
        """The subtask whose instruction is in force (the last one once all are done)."""
        return min(self.k, len(self.chain) - 1)
