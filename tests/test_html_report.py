"""The HTML report in a real headless browser (Debian's chromium driven by Playwright).

CI installs chromium before the tests (tox runs tests/ensure_chromium.sh), so a
missing browser fails there; only a non-root developer without it gets a skip.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pandas as pd
import pytest

from harness.run.runner import run
from results import html_report
from results.runs import load_run
from results.store import RunDir
from tests.fakes import ChunkPolicy, fake_resolved
from tests.test_leaderboard import BIDI, FAST, episodes, write_run

CHROMIUM = Path("/usr/bin/chromium")
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.exists():
        if os.geteuid() != 0:
            pytest.skip(f"{CHROMIUM} is missing and installing it needs root: sudo tests/ensure_chromium.sh")
        pytest.fail(f"{CHROMIUM} is missing; `tox -e test` installs it with tests/ensure_chromium.sh")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail("playwright is missing: pip install -e '.[dev]'")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A real run of the fake env through the runner, plus a run of constructed rows on
    the same machine (copied manifest environment) with two token-decoding policies."""
    root = tmp_path_factory.mktemp("runs")
    run(fake_resolved(ChunkPolicy(chunk=2), episodes=3), root / "real")
    manifest = RunDir(root / "real").read_manifest()
    rows = []
    for policy, params, config, wins, tokens in (
        ("bidirectional", BIDI, "bidi000001", [1, 0, 1, 1], [90.0, 100.0, 95.0, 95.0]),
        ("fast_dvla", FAST, "fast000001", [1, 1, 0, 1], [300.0, 320.0, 250.0, 330.0]),
    ):
        for r, t in zip(episodes(policy, params, config, wins), tokens, strict=True):
            rows.append(r | {"suite": "fake/countdown", "task": "count", "tokens_per_s": t, "seed": None})
    write_run(root / "constructed", rows, manifest | {"run_id": "constructed"})
    return [root / "real", root / "constructed"]


@pytest.fixture(scope="module")
def report(runs, tmp_path_factory):
    out = tmp_path_factory.mktemp("out") / "report"
    path, _warnings = html_report.write_report([load_run(r) for r in runs], out)
    return path


@pytest.fixture
def page(browser, report):
    page = browser.new_page()
    problems: list[str] = []
    page.on(
        "console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None
    )
    page.on("pageerror", lambda exc: problems.append(f"page error: {exc}"))
    page.on(
        "request",
        lambda req: None if req.url.startswith(("file:", "data:")) else problems.append(f"fetch {req.url}"),
    )
    page.goto((report / "index.html").as_uri())
    page.wait_for_load_state("load")
    yield page
    page.close()
    assert problems == []  # no console errors, no script errors, nothing fetched from a network


def _table(page, index: int = 0) -> tuple[list[str], list[list[tuple[str, str | None]]]]:
    return page.evaluate(
        """i => { const t = document.querySelectorAll('table.sortable')[i];
        return [Array.from(t.tHead.rows[0].cells).map(c => c.textContent),
                Array.from(t.tBodies[0].rows).map(r => Array.from(r.cells).map(
                    c => [c.textContent, c.getAttribute('data-value')]))]; }""",
        index,
    )


def _parquet(runs) -> pd.DataFrame:
    return pd.concat([pd.read_parquet(r / "episodes.parquet") for r in runs], ignore_index=True)


def test_the_page_loads_offline_with_no_errors_and_shows_provenance(page, runs):
    assert page.title() == "dvla-harness report"
    text = page.inner_text("body")
    manifest = json.loads((runs[0] / "manifest.json").read_text())
    env = manifest["environment"]
    for fact in (env["cpu"], env["python"], manifest["suite"]["render_backend"], "Provenance"):
        assert str(fact) in text
    if env["git_commit"]:
        assert env["git_commit"] in text
    images = page.eval_on_selector_all("img", "imgs => imgs.map(i => i.naturalWidth)")
    assert images and all(w > 0 for w in images)  # the inline Pareto plot decodes


def test_one_row_per_configuration_with_the_parquet_numbers(page, runs):
    df = _parquet(runs)
    headers, rows = _table(page)
    assert len(rows) == df["policy_config_id"].nunique() == 3
    labels = {"fake": "fakeconfig01", "bidirectional": "bidi000001", "fast_dvla": "fast000001"}
    success, tokens = headers.index("success (Wilson 95%)"), headers.index("tokens/s")
    for cells in rows:
        mine = df[df["policy_config_id"] == labels[cells[0][0]]]
        k, n = int(mine["success"].sum()), len(mine)
        assert cells[success][0].endswith(f"({k}/{n})")
        assert float(cells[success][1]) == pytest.approx(k / n)
        assert float(cells[tokens][1]) == pytest.approx(mine["tokens_per_s"].mean())
    speed = {cells[0][0]: cells[-1][0] for cells in rows}
    assert speed["bidirectional"] == "1.00x"
    assert speed["fast_dvla"] == f"{(300 + 320 + 250 + 330) / (90 + 100 + 95 + 95):.2f}x"


def test_clicking_a_header_sorts_numerically(page):
    headers, _ = _table(page)
    column = headers.index("tokens/s")
    th = page.locator("table.sortable").first.locator("thead th").nth(column)
    th.click()
    _, rows = _table(page)
    values = [float(r[column][1]) for r in rows]
    assert th.get_attribute("aria-sort") == "ascending"
    assert values == sorted(values) and len(values) == 3
    assert values[0] == 95.0  # numerically first; as text "95" would sort after "300"
    th.click()
    _, rows = _table(page)
    assert [float(r[column][1]) for r in rows] == sorted(values, reverse=True)
    policy = page.locator("table.sortable").first.locator("thead th").first
    policy.click()
    _, rows = _table(page)
    assert [r[0][0] for r in rows] == ["bidirectional", "fake", "fast_dvla"]


def test_a_suite_without_a_published_table_gets_none(page):
    """fake/countdown is no LIBERO suite: no published rows, no LIBERO layout beside it
    (tests/test_html_fit.py has a LIBERO report's published rows)."""
    headings = page.eval_on_selector_all("h2, h3", "hs => hs.map(h => h.textContent)")
    assert page.locator("tbody.published").count() == 0 and not any("LIBERO" in h for h in headings)
    assert page.locator("table.sortable").count() == 1  # the one suite's leaderboard


def test_a_failed_report_leaves_nothing_and_overwrite_replaces(runs, tmp_path, monkeypatch):
    loaded = [load_run(r) for r in runs]

    def broken(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(html_report, "to_csv", broken)
    with pytest.raises(RuntimeError):
        html_report.write_report(loaded, tmp_path / "report")
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    real_rename = Path.rename

    def rename_fails(self, target):
        if self.name.startswith(".report.tmp"):
            raise OSError("no space left on device")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", rename_fails)
    with pytest.raises(OSError):
        html_report.write_report(loaded, tmp_path / "report")
    assert list(tmp_path.iterdir()) == []  # the half-built folder is gone too
    monkeypatch.undo()
    first, _ = html_report.write_report(loaded, tmp_path / "report")
    (first / "stale.txt").write_text("from an earlier report")
    with pytest.raises(html_report.ReportError, match="pass --overwrite"):
        html_report.write_report(loaded, tmp_path / "report")
    html_report.write_report(loaded, tmp_path / "report", overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]
    assert sorted(p.name for p in (tmp_path / "report").iterdir()) == [
        "index.html",
        "leaderboard.csv",
        "leaderboard.md",
        "paper-table.md",
    ]
