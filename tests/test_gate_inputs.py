"""Every input the gate reads is checked first: a run whose rows hold what the harness never
writes (a NaN or null success, a negative NFE, an infinite time) is refused with exit 2,
naming the column and the row, instead of being judged."""

from __future__ import annotations

import json
import math

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from results.gate_inputs import check_gate_inputs
from results.schema import arrow_schema
from results.store import ResultsFileError
from tests.test_gate import episodes, write_run

MIXED = {"a": [True, False, True, False, True, False], "b": [True] * 6}


def _null(value) -> bool:
    return value is None or value is pd.NA or (isinstance(value, float) and math.isnan(value))


def _write(path, df: pd.DataFrame, schema: pa.Schema | None = None, nan_in: str = ""):
    """A run folder of `df` in `schema` (every column nullable: a hand-edited or foreign
    file); a NaN in column `nan_in` is written as NaN, every other as null."""
    schema = schema or arrow_schema()
    schema = pa.schema([f.with_nullable(True) for f in schema], metadata=schema.metadata)
    path.mkdir(parents=True)
    records = [
        {k: None if k != nan_in and _null(v) else v for k, v in row.items()} for row in df.to_dict("records")
    ]
    pq.write_table(pa.Table.from_pylist(records, schema=schema), path / "episodes.parquet")
    (path / "manifest.json").write_text(json.dumps({"run_id": path.name}))
    return path


def test_a_nan_success_is_refused_not_counted_as_a_success(cli, tmp_path):
    base = write_run(tmp_path / "base", episodes(MIXED))
    nan = episodes(MIXED)
    nan["success"] = nan["success"].astype(float)
    nan.loc[[1, 3], "success"] = math.nan  # two failures of the baseline, NaN here: read as True
    schema = arrow_schema()
    schema = schema.set(schema.get_field_index("success"), pa.field("success", pa.float64()))
    cand = _write(tmp_path / "cand", nan, schema, nan_in="success")
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand))
    assert code == 2 and "gate passed" not in out and len(err.strip().splitlines()) == 1, err
    assert err.startswith("dvla-harness gate: error: --candidate:")
    assert "column 'success' holds nan in row 1, which is not a bool value" in err
    # the same file on the baseline's side
    code, _, err = cli("gate", "--baseline", str(cand), "--candidate", str(base))
    assert code == 2 and "--baseline:" in err and "column 'success' holds nan in row 1" in err


def _edited(column: str, value) -> pd.DataFrame:
    df = episodes(MIXED)
    df[column] = df[column].astype(object)
    df.at[4, column] = value
    return df


@pytest.mark.parametrize(
    ("column", "value", "shown"),
    [
        (
            "success",
            None,
            "holds null in row 4 (task 'a', episode_index 4, policy 'fast_dvla'); the gate needs true or false, never null",
        ),
        ("nfe_total", -5, "holds -5 in row 4"),
        ("chunks", None, "holds null in row 4"),
        ("action_tokens_total", -1, "holds -1 in row 4"),
        ("policy_time_s", math.inf, "holds inf in row 4"),
        ("policy_time_s", -0.5, "holds -0.5 in row 4"),
        ("subtasks_completed", -2, "holds -2 in row 4"),
        ("policy_params", "{not json", "holds '{not json' in row 4"),
        ("batch_envs", 0, "holds 0 in row 4"),
    ],
)
def test_a_value_the_harness_never_writes_is_refused_naming_column_and_row(
    cli, tmp_path, column, value, shown
):
    base = write_run(tmp_path / "base", episodes(MIXED))
    cand = _write(tmp_path / "cand", _edited(column, value))
    code, _, err = cli("gate", "--baseline", str(base), "--candidate", str(cand))
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"--candidate: {cand}: column {column!r} {shown}" in err


def test_rows_the_harness_writes_pass_the_check():
    df = episodes(MIXED)
    df.loc[0, ["nfe_total", "flops_total", "subtasks_completed", "seed"]] = None  # nullable: not measured
    check_gate_inputs(df, "run")
    with pytest.raises(ResultsFileError, match="column 'nfe_total' holds -5"):
        check_gate_inputs(_edited("nfe_total", -5), "run")
