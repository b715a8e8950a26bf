"""The config_label column: rows a user groups by without parsing policy_params."""

from __future__ import annotations

import dataclasses
import json

import pandas as pd
import pyarrow.parquet as pq

from harness.run.runner import run
from results import schema
from results.labels import config_labels, with_config_labels
from results.leaderboard import leaderboards
from results.runs import load_run
from results.store import RunDir, read_table, rows_to_table
from tests.fakes import ChunkPolicy, fake_resolved
from tests.test_leaderboard import row


def _two_gains(tmp_path):
    """A run of one policy at two parameter settings (and the same policy's config id scheme)."""
    resolved = fake_resolved(ChunkPolicy(chunk=2), episodes=2, succeed_at=5)
    first = resolved.policies[0]
    resolved.policies = [
        dataclasses.replace(first, params_json=json.dumps({"gain": 0.5}), config_id="gain0000005"),
        dataclasses.replace(
            first, params_json=json.dumps({"gain": 1.0}), config_id="gain0000010", policy=ChunkPolicy(chunk=2)
        ),
    ]
    out = tmp_path / "run"
    run(resolved, out)
    return out


def test_two_settings_of_one_policy_are_two_labels_in_the_written_rows(tmp_path):
    out = _two_gains(tmp_path)
    df = pd.read_parquet(out / "episodes.parquet")  # as a user reads it: no harness code
    assert set(df["config_label"]) == {"fake (gain=0.5)", "fake (gain=1)"}
    per_config = df.groupby("policy_config_id")["config_label"].nunique()
    assert (per_config == 1).all()
    per_label = df.groupby("config_label")["policy_config_id"].nunique()
    assert (per_label == 1).all()
    # Grouping by (label, task) keeps the settings apart where (policy, task) merges them.
    assert len(df.groupby(["config_label", "task"])) == 2 and len(df.groupby(["policy", "task"])) == 1
    assert pq.read_schema(out / "episodes.parquet").metadata[schema.SCHEMA_VERSION_KEY] == b"5"


def test_the_tables_print_the_label_the_rows_hold(tmp_path):
    out = _two_gains(tmp_path)
    r = load_run(out)
    (board,) = leaderboards([r])
    assert {e.label for e in board.entries} == set(r.episodes["config_label"])


def test_labels_are_unique_even_when_the_parameters_read_alike():
    frame = pd.DataFrame(
        {
            "policy_config_id": ["a", "b", "c"],
            "policy": ["acme_pd", "acme_pd", "acme_pd"],
            # 4 significant digits make the first two read alike: the id tells them apart
            "policy_params": [json.dumps({"gain": 0.50001}), json.dumps({"gain": 0.50002}), "{}"],
        }
    )
    labels = config_labels(frame)
    assert len(set(labels.values())) == 3
    assert labels["a"] == "acme_pd (gain=0.5) [a]" and labels["b"] == "acme_pd (gain=0.5) [b]"


def test_a_version_3_table_reads_with_labels_filled_in(tmp_path):
    rows = [
        row(params=json.dumps({"steps": 12}), config="bidi12"),
        row(params=json.dumps({"steps": 8}), config="bidi08", episode_index=1),
    ]
    old = rows_to_table(rows).drop_columns(["config_label"])
    old = old.replace_schema_metadata({schema.SCHEMA_VERSION_KEY: b"3"})
    (tmp_path / "old").mkdir()
    pq.write_table(old, tmp_path / "old" / "e.parquet")
    assert read_table(tmp_path / "old" / "e.parquet").column("config_label").null_count == 2
    df = load_run(tmp_path / "old" / "e.parquet").episodes
    assert list(df["config_label"]) == ["bidirectional (steps=12)", "bidirectional (steps=8)"]


def test_inconsistent_stored_labels_are_redone_for_the_whole_frame(tmp_path):
    """Rows resumed under other defaults must not give one configuration two names."""
    df = pd.DataFrame(
        [
            row(config="x1", config_label="bidirectional"),
            row(config="x1", config_label="bidirectional (steps=12)", episode_index=1),
        ]
    )
    assert set(with_config_labels(df)["config_label"]) == {"bidirectional"}
    run_dir = RunDir(tmp_path / "r")
    run_dir.create()
    for r in df.to_dict("records"):
        run_dir.append_episode(r)
    assert run_dir.read_episodes()["config_label"].nunique() == 1


def test_a_shipped_checkpoint_is_named_as_the_user_typed_it():
    """`--policy bidirectional:checkpoint=libero-object` reads `checkpoint=libero-object`, on any
    machine; a checkpoint of one's own keeps its file name."""
    from policies.dvla.policy import shipped

    frame = pd.DataFrame(
        {
            "policy_config_id": ["here", "there", "own"],
            "policy": ["bidirectional"] * 3,
            "policy_params": [
                json.dumps({"checkpoint": shipped("bidirectional", "libero-object")}),
                json.dumps(
                    {
                        "checkpoint": "/home/x/clone/policies/checkpoints/libero-spatial-bidirectional.safetensors"
                    }
                ),
                json.dumps({"checkpoint": "ckpt/my-bidirectional.safetensors"}),
            ],
        }
    )
    assert config_labels(frame) == {
        "here": "bidirectional (checkpoint=libero-object)",
        "there": "bidirectional (checkpoint=libero-spatial)",
        "own": "bidirectional (checkpoint=my-bidirectional.safetensors)",
    }
    default = frame.iloc[:1].assign(
        policy_params=json.dumps({"checkpoint": "/y/metaworld-mt10-bidirectional.safetensors"})
    )
    assert config_labels(default) == {"here": "bidirectional"}  # the default set, from another machine
