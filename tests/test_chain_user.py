"""A researcher's own chain file (`chains/<scene>:chains=PATH`): checked as the stored
chains are (every subtask eligible where its chain reaches it, no episode twice, the
scene's names), its own sha256 in the suite name and the manifest, and its chains credited
by CALVIN's rule on LIBERO's live state like any other."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from adapters import chain_credit as cc
from adapters import chain_scenes as cs
from adapters import libero as lb

needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
SCENE = "living_room_scene3"
GROCERIES = ("butter", "ketchup", "alphabet_soup", "cream_cheese", "tomato_sauce")
IN_ORDER = [f"{g}_in_tray" for g in GROCERIES]


def write(path, chains, scene=SCENE, **extra):
    path.write_text(json.dumps({"scene": scene, "chains": chains, **extra}))
    return path


def test_a_user_file_reads_in_the_stored_format_and_hashes_its_own_bytes(tmp_path):
    path = write(tmp_path / "mine.json", [IN_ORDER, IN_ORDER[::-1]])
    chains = cs.load_user_chains(path, SCENE)
    assert chains.chains == (tuple(IN_ORDER), tuple(IN_ORDER[::-1]))
    assert chains.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert chains.seed is None and chains.command is None  # optional in a user's file
    assert cs.load_user_chains(cs.chains_path(SCENE), SCENE).chains == cs.load_chains(SCENE).chains


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ({"scene": SCENE, "chains": []}, "non-empty list of chains"),
        ({"scene": SCENE, "chains": ["butter_in_tray"]}, "chain 0 is not a list of subtask ids"),
        ({"scene": SCENE, "chain": [IN_ORDER]}, "unknown keys ['chain']"),
        ({"chains": [IN_ORDER]}, "missing 'scene'"),
        ([IN_ORDER], "the top level is a JSON list, not an object"),
        ({"scene": SCENE, "chains": [IN_ORDER], "seed": "x"}, "\"seed\" must be an integer or null, not 'x'"),
        ({"scene": SCENE, "chains": [IN_ORDER], "seed": True}, '"seed" must be an integer'),
        ({"scene": SCENE, "chains": [IN_ORDER], "command": 3}, '"command" must be a string'),
        ({"scene": ["x"], "chains": [IN_ORDER]}, '"scene" must be a scene name'),
        ({"scene": "libero_goal", "chains": [IN_ORDER]}, "for scene 'libero_goal', not 'living_room_scene3'"),
    ],
)
def test_a_malformed_user_file_is_refused_naming_it(tmp_path, body, needle):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(body))
    with pytest.raises(cs.ChainDataError, match=None) as err:
        cs.load_user_chains(path, SCENE)
    assert str(path) in str(err.value) and needle in str(err.value)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ('{"scene": "x", "chains": [', "not valid JSON"),
        ('{"scene": "living_room_scene3", "chains": [], "chains": []}', "key 'chains' appears twice"),
    ],
)
def test_a_user_file_that_is_not_json_is_refused_with_the_layout(tmp_path, text, needle):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(cs.ChainDataError) as err:
        cs.load_user_chains(path, SCENE)
    assert needle in str(err.value) and '"chains": [["<subtask id>"' in str(err.value)


@needs_libero
@pytest.mark.parametrize(
    ("chains", "needle"),
    [
        ([IN_ORDER[:4]], "chain 0: 4 subtasks; a chain has 5"),
        ([[*IN_ORDER[:4], "butter_in_tray"]], "chain 0: subtask 4 (butter_in_tray) is not eligible there"),
        ([[*IN_ORDER[:4], "bowl_on_plate"]], "has no subtask 'bowl_on_plate'"),
        ([IN_ORDER, *[IN_ORDER[::-1]] * 49, IN_ORDER], "chain 50 repeats chain 0"),
    ],
)
def test_user_chains_are_checked_as_the_stored_ones(cli, tmp_path, chains, needle):
    path = write(tmp_path / "mine.json", chains)
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", f"chains/{SCENE}:chains={path}", "--policy", "random", "--out", str(out)
    )  # fmt: skip
    assert code == 2 and needle in err, err
    assert not out.exists()


@needs_libero
def test_chains_takes_one_scene_and_an_evaluation_file(tmp_path):
    from adapters import chains
    from adapters.libero_options import SuiteOptionError

    path = write(tmp_path / "mine.json", [IN_ORDER])
    with pytest.raises(SuiteOptionError, match="chains=PATH runs a chain file of one scene"):
        chains.load_suite(f"chains/all:chains={path}")
    with pytest.raises(SuiteOptionError, match="the train split samples chains of its own"):
        chains.load_suite(f"chains/{SCENE}:chains={path}", split="train")
    with pytest.raises(cs.ChainDataError, match="no such file"):
        chains.load_suite(f"chains/{SCENE}:chains={tmp_path / 'none.json'}")


@needs_libero
def test_the_suite_name_and_manifest_carry_the_files_own_hash(tmp_path):
    from adapters import chains

    path = write(tmp_path / "mine.json", [IN_ORDER, IN_ORDER[::-1]])
    sha = hashlib.sha256(path.read_bytes()).hexdigest()
    suite = chains.load_suite(f"chains/{SCENE}:chains={path}")
    assert suite.name == f"chains/{SCENE}:seeding=openvla,chains=sha256-{sha[:16]}"
    assert suite.provenance["chains_sha256"] == f"{SCENE} {sha}"
    assert suite.version == chains.SUITE_VERSION
    (task,) = suite.tasks
    assert [(e.index, e.init_state_id, e.chain) for e in task.episodes] == [
        (0, 0, tuple(IN_ORDER)),
        (1, 1, tuple(IN_ORDER[::-1])),
    ]
    stored = chains.load_suite(f"chains/{SCENE}")
    assert (
        stored.name == f"chains/{SCENE}:seeding=openvla"
        and stored.provenance["chains_sha256"] != (suite.provenance["chains_sha256"])
    )


@needs_libero
def test_a_user_chain_whose_earlier_subtask_puts_a_later_goal_in_place_ends_there(tmp_path):
    """CALVIN's rule on a user's chain, live: the butter's placement also puts the ketchup
    (the next subtask's object) into the tray, so the ketchup's subtask finds its goal
    holding when it takes over and the chain ends there, one subtask completed: the
    symbolic check passes the chain, the live state decides."""
    from adapters import chains
    from tests.chain_live import put_in_tray

    path = write(tmp_path / "mine.json", [IN_ORDER])
    suite = chains.load_suite(f"chains/{SCENE}:chains={path}")
    (task,) = suite.tasks
    env = suite.make_env(task)
    try:
        env.reset(options={"episode": task.episodes[0]})
        put_in_tray(env, ("butter", "ketchup"))
        _, _, terminated, _, info = env.step(np.zeros(7))
        assert terminated and not info["success"] and info["subtasks_completed"] == 1
        butter, ketchup, *rest = info["subtasks"]
        assert butter["outcome"] == cc.COMPLETED
        assert ketchup["outcome"] == cc.GOAL_HELD_AT_START and ketchup["goal_held_at_start"]
        assert all(r["outcome"] == cc.NOT_REACHED for r in rest)
    finally:
        env.close()
