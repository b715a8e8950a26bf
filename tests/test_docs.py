"""The documents that make promises stay in step with the code."""

from __future__ import annotations

import re
from pathlib import Path

from results.schema import COLUMN_NAMES, markdown_table

REPO = Path(__file__).resolve().parent.parent


def test_results_schema_doc_is_the_schema():
    doc = (REPO / "docs" / "results-schema.md").read_text()
    block = doc.split("<!-- columns:begin -->")[1].split("<!-- columns:end -->")[0].strip()
    assert block == markdown_table(), "regenerate the table from results.schema.markdown_table()"
    for name in COLUMN_NAMES:
        assert f"`{name}`" in block


def _readme_command(kind: str) -> str:
    readme = (REPO / "README.md").read_text()
    match = re.search(rf"<!-- {kind}-command -->\s*```(?:bash|sh)?\n(.+?)\n```", readme, re.S)
    assert match, f"README has no {kind} command block"
    return match.group(1).strip()


def test_ci_runs_exactly_the_readme_test_command():
    command = _readme_command("test")
    lines = [ln for ln in (REPO / ".ci" / "run").read_text().splitlines() if ln and not ln.startswith("#")]
    assert command in lines


def test_readme_main_job_runs_the_embedded_default():
    command = _readme_command("main")
    assert command.endswith("dvla-harness run")
