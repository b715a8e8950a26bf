"""The stored chain files against their recorded sha256 (adapters/chain_data/chains.sha256):
the shipped files match, a changed file is refused when the suite loads, and the
generator records the hash of what it writes."""

from __future__ import annotations

import hashlib
import json

import pytest

from adapters import chain_scenes as cs
from adapters import libero as lb

needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
SCENE = "living_room_scene3"


def _swap_first_two_chains(folder) -> str:
    """A plausible edit: every chain still valid, the protocol's order changed."""
    path = folder / f"{SCENE}.chains.json"
    stored = json.loads(path.read_text())
    stored["chains"][:2] = stored["chains"][1::-1]
    path.write_text(json.dumps(stored, indent=1) + "\n")
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_every_shipped_chain_file_matches_its_recorded_hash():
    recorded = cs.recorded_hashes()
    assert sorted(recorded) == sorted(f"{s}.chains.json" for s in cs.scene_names())
    for scene in cs.scene_names():
        digest = hashlib.sha256(cs.chains_path(scene).read_bytes()).hexdigest()
        assert recorded[f"{scene}.chains.json"] == digest == cs.load_chains(scene).sha256, scene


def test_a_changed_chain_file_is_refused_naming_the_file_both_hashes_and_the_way_out(chain_data):
    expected = cs.recorded_hashes()[f"{SCENE}.chains.json"]
    actual = _swap_first_two_chains(chain_data)
    with pytest.raises(cs.ChainDataError) as caught:
        cs.load_chains(SCENE)
    message = str(caught.value)
    assert str(chain_data / f"{SCENE}.chains.json") in message
    assert expected in message and actual in message and expected != actual
    assert f"git checkout -- adapters/chain_data/{SCENE}.chains.json" in message
    assert f"python -m adapters.chain_scenes generate {SCENE}" in message and "SUITE_VERSION" in message
    cs.load_chains("libero_goal")  # the other scenes' files still load


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (lambda lines: [x for x in lines if SCENE not in x], "no sha256 recorded for it"),
        (lambda lines: [*lines, lines[0]], f"line {len(cs.scene_names()) + 1}: expected one"),  # repeated
        (lambda lines: [lines[0].replace("  ", " ", 1), *lines[1:]], "line 1: expected one"),
    ],
)
def test_a_missing_or_malformed_hash_list_is_refused(chain_data, edit, needle):
    path = chain_data / cs.HASHES
    path.write_text("".join(f"{x}\n" for x in edit(path.read_text().splitlines())))
    with pytest.raises(cs.ChainDataError, match=needle):
        cs.load_chains(SCENE)


@needs_libero
def test_the_suite_refuses_a_changed_chain_file_with_exit_2_and_writes_nothing(cli, tmp_path, chain_data):
    actual = _swap_first_two_chains(chain_data)
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", f"chains/{SCENE}", "--policy", "libero_scripted", "--episodes-per-task", "1",
        "--out", str(out),
    )  # fmt: skip
    assert code == 2 and f"{SCENE}.chains.json: sha256 {actual}" in err, err
    assert not out.exists()


@needs_libero
def test_the_generator_records_the_hash_of_what_it_writes(chain_data, capsys):
    shipped = {p.name: p.read_bytes() for p in chain_data.iterdir()}
    assert cs._main(["generate", SCENE, "--chains", "60", "--seed", "3"]) == 0
    assert f"sha256 {cs.recorded_hashes()[f'{SCENE}.chains.json']}" in capsys.readouterr().out
    cs.load_chains.cache_clear()
    regenerated = cs.load_chains(SCENE)  # its new hash recorded: it loads
    assert len(regenerated.chains) == 60 and regenerated.seed == 3
    lines = (chain_data / cs.HASHES).read_text().splitlines()
    assert [x for x in lines if SCENE not in x] == [
        x for x in shipped[cs.HASHES].decode().splitlines() if SCENE not in x
    ]  # the other scenes' hashes are kept
    # The documented command rewrites the shipped file byte for byte, and its shipped hash.
    assert cs._main(["generate", SCENE]) == 0
    assert (chain_data / f"{SCENE}.chains.json").read_bytes() == shipped[f"{SCENE}.chains.json"]
    assert (chain_data / cs.HASHES).read_bytes() == shipped[cs.HASHES]


@needs_libero
def test_the_manifest_records_the_hashes_of_the_chains_that_ran():
    from adapters import chains

    recorded = cs.recorded_hashes()
    suite = chains.load_suite("chains/all")
    assert suite.provenance["chains_sha256"] == ", ".join(
        f"{s} {recorded[f'{s}.chains.json']}" for s in cs.CALVIN_SCENES
    )
    assert "chains_sha256" not in chains.load_suite(f"chains/{SCENE}", split="train").provenance
