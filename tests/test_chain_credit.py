"""CALVIN's credit rule (adapters/chain_credit.py) on hand-made predicate states, the
per-subtask records through Parquet, and (with the libero extra) the rule on LIBERO's
live state."""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest

from adapters import chain_credit as cc
from adapters import chain_scenes as cs
from adapters import libero as lb
from results import schema
from results.store import read_table, rows_to_table

needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
SCENE = "living_room_scene3"
GROCERIES = ("butter", "ketchup", "alphabet_soup", "cream_cheese", "tomato_sauce")


def in_tray(grocery: str) -> cs.Predicate:
    return ("in", f"{grocery}_1", "wooden_tray_1_contain_region")


class HandMadeState:
    """The set of predicates that hold; a test moves groceries in and out of it."""

    def __init__(self) -> None:
        self.true: set[cs.Predicate] = set()

    def __call__(self, predicate: cs.Predicate) -> bool:
        return tuple(predicate) in self.true


def tray_chain() -> tuple[cs.Subtask, ...]:
    scene = cs.load_scene(SCENE)
    return tuple(scene.subtask(f"{g}_in_tray") for g in GROCERIES)


def test_a_subtask_whose_goal_held_at_its_start_is_not_credited():
    state, chain = HandMadeState(), tray_chain()
    credit = cc.ChainCredit.begin(chain, state)
    for _ in range(4):
        assert not credit.after_step(state)
    # The butter's placement knocks the ketchup (the next subtask) into the tray too.
    state.true |= {in_tray("butter"), in_tray("ketchup")}
    assert credit.after_step(state)  # the chain is over: the ketchup was never placed by it
    butter, ketchup, *rest = credit.records
    assert butter | {"success": True, "steps": 5, "start_step": 0, "end_step": 5} == butter
    assert butter["outcome"] == cc.COMPLETED and butter["goal_held_at_start"] is False
    assert ketchup["success"] is False and ketchup["outcome"] == cc.GOAL_HELD_AT_START
    assert (ketchup["goal_held_at_start"], ketchup["start_step"], ketchup["end_step"]) == (True, 5, 5)
    assert ketchup["steps"] == 0 and credit.completed == 1 and credit.in_force == 1
    assert all(r["outcome"] == cc.NOT_REACHED and r["start_step"] is None for r in rest)
    with pytest.raises(RuntimeError, match="the chain is over"):
        credit.after_step(state)


def test_a_goal_that_becomes_true_is_credited_and_the_records_add_up():
    state, chain = HandMadeState(), tray_chain()
    credit = cc.ChainCredit.begin(chain, state)
    for k, grocery in enumerate(GROCERIES):
        for _ in range(2 + k):
            assert not credit.after_step(state)
        state.true.add(in_tray(grocery))
        assert credit.after_step(state) == (k == 4)
    assert credit.completed == 5 and all(r["outcome"] == cc.COMPLETED for r in credit.records)
    assert [r["steps"] for r in credit.records] == [3, 4, 5, 6, 7]
    starts = [r["start_step"] for r in credit.records]
    ends = [r["end_step"] for r in credit.records]
    assert starts == [0, *ends[:-1]] and ends[-1] == credit.step == 25


def test_a_subtask_out_of_steps_stops_the_chain():
    state, chain = HandMadeState(), tray_chain()
    credit = cc.ChainCredit.begin(chain, state)
    over = [credit.after_step(state) for _ in range(cs.STEPS_PER_SUBTASK)]
    assert over == [False] * (cs.STEPS_PER_SUBTASK - 1) + [True]
    first = credit.records[0]
    assert first["outcome"] == cc.OUT_OF_STEPS and first["steps"] == first["end_step"] == 360
    assert credit.completed == 0


def test_the_per_subtask_record_round_trips_through_parquet_and_old_tables_read_nulls(tmp_path):
    from tests.test_leaderboard import row as a_row  # one valid row of the episode table

    state, chain = HandMadeState(), tray_chain()
    credit = cc.ChainCredit.begin(chain, state)
    state.true |= {in_tray("butter"), in_tray("ketchup")}
    credit.after_step(state)
    records = [dict(r) for r in credit.records]
    row = {**a_row(), "chain_id": f"{SCENE}/0", "subtasks_completed": 1, "subtasks": records}
    pq.write_table(rows_to_table([row]), tmp_path / "new.parquet")
    back = read_table(tmp_path / "new.parquet").to_pylist()[0]
    assert back["subtasks"] == records and back["subtasks"][1]["goal_held_at_start"] is True
    # A table written before the credit rule: its records have the first four fields only.
    old_records = [{k: r[k] for k in ("id", "instruction", "success", "steps")} for r in records]
    old_type = schema.pa.list_(schema.pa.struct(list(schema.SUBTASK)[:4]))
    old = rows_to_table([row]).drop_columns(["subtasks"])
    old = old.append_column(schema.pa.field("subtasks", old_type), schema.pa.array([old_records], old_type))
    pq.write_table(old, tmp_path / "old.parquet")
    table = read_table(tmp_path / "old.parquet")
    assert table.schema.field("subtasks").type == schema.arrow_schema().field("subtasks").type
    (first, *_) = table.to_pylist()[0]["subtasks"]
    assert first["steps"] == 1 and first["start_step"] is None and first["outcome"] is None
    # and the two read together, as a resumed run's old and new rows do
    assert len(schema.pa.concat_tables([table, read_table(tmp_path / "new.parquet")])) == 2


@needs_libero
def test_on_liberos_live_state_a_later_subtask_already_in_place_fails_the_chain():
    """The real env: after the butter's subtask, the ketchup is moved into the tray by hand
    (MuJoCo's joint state), as a placement that knocks it in would; the next step credits the
    butter and ends the chain on the ketchup with the reason, where the old rule credited it."""
    import numpy as np

    from adapters import chains
    from adapters.base import EpisodeSpec
    from tests.chain_live import put_in_tray

    suite = chains.load_suite(f"chains/{SCENE}")
    assert suite.version == chains.SUITE_VERSION == "3"
    env = suite.make_env(suite.tasks[0])
    chain = tuple(f"{g}_in_tray" for g in GROCERIES)
    try:
        env.reset(options={"episode": EpisodeSpec(index=0, seed=0, init_state_id=0, chain=chain)})
        put_in_tray(env, ("butter", "ketchup"))
        _, _, terminated, _, info = env.step(np.zeros(7))  # they settle into the tray
        assert env.holds(in_tray("butter")) and env.holds(in_tray("ketchup"))
        assert terminated and not info["success"] and info["subtasks_completed"] == 1
        butter, ketchup = info["subtasks"][:2]
        assert butter["outcome"] == cc.COMPLETED and butter["end_step"] == 1
        assert ketchup["outcome"] == cc.GOAL_HELD_AT_START and ketchup["goal_held_at_start"]
    finally:
        env.close()


def test_where_chains_fail_is_read_from_the_rows():
    import pandas as pd

    from results.chain_table import subtask_failures

    state, chain = HandMadeState(), tray_chain()
    knocked = cc.ChainCredit.begin(chain, state)  # butter completed, ketchup already in place
    state.true |= {in_tray("butter"), in_tray("ketchup")}
    knocked.after_step(state)
    timed_out = cc.ChainCredit.begin(chain, HandMadeState())
    while not timed_out.after_step(HandMadeState()):
        pass
    old = [  # a row from before outcomes were recorded: butter done in 40 steps, ketchup out of steps
        {"id": "butter_in_tray", "instruction": "", "success": True, "steps": 40, "outcome": None},
        {"id": "ketchup_in_tray", "instruction": "", "success": False, "steps": 360, "outcome": None},
        {"id": "alphabet_soup_in_tray", "instruction": "", "success": False, "steps": 0, "outcome": None},
    ]
    episodes = pd.DataFrame(
        {
            "policy_config_id": ["a", "a", "b"],
            "subtasks": [knocked.records, timed_out.records, old],
        }
    )
    table = subtask_failures(episodes).set_index(["policy_config_id", "subtask"])
    butter, ketchup = table.loc[("a", "butter_in_tray")], table.loc[("a", "ketchup_in_tray")]
    assert (butter["attempts"], butter["completed"], butter["out_of_steps"]) == (2, 1, 1)
    assert butter["median_steps_completed"] == 1
    assert (ketchup["attempts"], ketchup["goal_held_at_start"], ketchup["completed"]) == (1, 1, 0)
    assert ("a", "alphabet_soup_in_tray") not in table.index  # never reached
    assert table.loc[("b", "butter_in_tray"), "completed"] == 1
    assert table.loc[("b", "ketchup_in_tray"), "unrecorded"] == 1
    assert ("b", "alphabet_soup_in_tray") not in table.index


def test_the_start_check_names_later_subtasks_whose_goal_already_holds():
    from adapters.chain_starts import later_goals_holding

    scene, state = cs.load_scene(SCENE), HandMadeState()
    chain = tuple(f"{g}_in_tray" for g in GROCERIES)
    assert later_goals_holding(scene, chain, state) == []
    state.true |= {in_tray("butter"), in_tray("cream_cheese")}  # the first's goal is not "later"
    assert later_goals_holding(scene, chain, state) == [(3, "cream_cheese_in_tray")]


@needs_libero
def test_the_start_check_runs_on_the_stored_chains(capsys):
    from adapters.chain_starts import _main

    assert _main(["kitchen_scene1", "--chains", "2"]) == 0
    assert (
        capsys.readouterr()
        .out.strip()
        .endswith(
            "kitchen_scene1: 2 chains; a goal holds at the start of 0; a later subtask's goal holds at the start of 0"
        )
    )
    with pytest.raises(SystemExit) as exc:
        _main(["no_such_scene"])
    assert exc.value.code == 2
