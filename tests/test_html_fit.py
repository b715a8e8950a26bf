"""The HTML report fits what it shows: the published rows only beside their own suite,
no columns without a value, a laptop-wide window without horizontal scrolling. Checked
in the real headless browser of tests/test_html_report.py."""

from __future__ import annotations

import pytest

from results import html_report
from results.runs import load_run
from tests.test_html_report import browser  # noqa: F401  (the module's browser fixture)
from tests.test_leaderboard import BIDI, FAST, MANIFEST, episodes, write_run

MT10 = (
    "reach-v3 push-v3 pick-place-v3 door-open-v3 drawer-open-v3 drawer-close-v3 "
    "button-press-topdown-v3 peg-insert-side-v3 window-open-v3 window-close-v3"
).split()
LAPTOP = {"width": 1280, "height": 800}


def _mt10_rows() -> list[dict]:
    """Three decoders over MT10's ten tasks, 50 episodes each: the widest common table."""
    rows = []
    configs = (
        ("bidirectional", BIDI, "bidi000001", 100.0),
        ("fast_dvla", FAST, "fast000001", 300.0),
        ("fast_dvla", FAST.replace("0.5", "0.3"), "fast000003", 330.0),
    )
    for policy, params, config, tokens in configs:
        for t, task in enumerate(MT10):
            wins = [1] * 50 if t % 3 else [1] * 43 + [0] * 7
            for r in episodes(policy, params, config, wins, tokens_per_s=tokens):
                rows.append(r | {"task": task, "task_index": t})
    return rows


def _reach_rows() -> list[dict]:
    """A plugin's 2-D reach suite: policies that read state and decode no tokens."""
    rows = []
    for policy, params, config, wins in (
        ("acme_pd", '{"gain":0.5}', "acme000005", [1, 1, 0, 1]),
        ("acme_pd", '{"gain":1.0}', "acme000010", [1, 0, 0, 1]),
    ):
        for r in episodes(policy, params, config, wins):
            no_tokens = {"action_tokens_total": 0, "tokens_per_s": None, "nfe_total": None}
            rows.append(r | {"suite": "acme/reach", "task": "reach", "nfe_per_chunk": None} | no_tokens)
    for i in (2, 3):  # two episodes of gain=1 raised, for the same reason
        rows[4 + i] |= {
            "success": False,
            "failure_reason": "ValueError: action [3.0, 0.0] is outside Box(-1, 1)",
        }
    return rows


REACH_MANIFEST = MANIFEST | {
    "suite": MANIFEST["suite"] | {"name": "acme/reach", "provided_by": "acme-reach 1.2.0"},
    "policies": [
        {"name": "acme_pd", "config_id": c, "params": "{}", "provided_by": "acme-reach 1.2.0"}
        for c in ("acme000005", "acme000010")
    ],
}


def _libero_rows() -> list[dict]:
    suite = "libero/spatial:obs=upstream,seeding=openvla"
    lib_bidi = '{"checkpoint":"/x/libero-spatial-bidirectional.safetensors","steps":12}'
    lib_fast = '{"checkpoint":"/x/libero-spatial-fast_dvla.safetensors","tau_conf":0.5}'
    rows = episodes("bidirectional", lib_bidi, "bidilib001", [1, 0, 1], tokens_per_s=100.0)
    rows += episodes("fast_dvla", lib_fast, "fastlib001", [1, 1, 0], tokens_per_s=300.0)
    return [r | {"suite": suite} for r in rows]


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit")
    out = {}
    for name, rows in (("mt10", _mt10_rows()), ("reach", _reach_rows()), ("libero", _libero_rows())):
        run = load_run(write_run(root / name, rows, REACH_MANIFEST if name == "reach" else None))
        out[name], _ = html_report.write_report([run], root / f"{name}-report")
    return out


def _open(browser, report, viewport=LAPTOP):  # noqa: F811
    page = browser.new_page(viewport=viewport)
    page.goto((report / "index.html").as_uri())
    page.wait_for_load_state("load")
    return page


def _headers(page, index: int = 0) -> list[str]:
    return page.evaluate(
        "i => Array.from(document.querySelectorAll('table.sortable')[i].tHead.rows[0].cells)"
        ".map(c => c.textContent)",
        index,
    )


def test_a_meta_world_report_has_no_libero_section(browser, reports):  # noqa: F811
    page = _open(browser, reports["mt10"])
    text = page.inner_text("body")
    assert "LIBERO" not in text and page.locator("tbody.published").count() == 0
    assert page.locator("table.sortable").count() == 1  # the leaderboard, nothing beside it
    assert (reports["mt10"] / "paper-table.md").read_text().startswith("No LIBERO, CALVIN-like or SimplerEnv")
    page.close()


def test_a_libero_report_keeps_published_figures_in_their_own_table(browser, reports):  # noqa: F811
    page = _open(browser, reports["libero"])
    assert "published" in page.inner_text("body")
    measured, published = _headers(page, 1), _headers(page, 2)  # after the leaderboard: the paper's layout
    assert "tokens/s (measured)" in measured and "speedup vs bidirectional (measured)" in measured
    assert "tokens/s (published)" in published and "speedup vs Dream-VLA (published)" in published
    assert not any("published" in h for h in measured)
    page.locator("table.sortable").nth(1).locator("thead th").nth(
        measured.index("tokens/s (measured)")
    ).click()
    bodies = page.evaluate(
        """() => Array.from(document.querySelectorAll('table.sortable')).slice(1, 3).map(
            t => Array.from(t.tBodies).filter(b => b.rows.length).map(b => b.className + ':' + b.rows.length))"""
    )
    assert bodies == [["measured:2"], ["published:8"]]
    page.close()


def test_a_state_only_plugin_suite_has_no_token_columns(browser, reports):  # noqa: F811
    page = _open(browser, reports["reach"])
    headers = _headers(page)
    assert not [h for h in headers if "tokens" in h or "speedup" in h or "NFE" in h], headers
    assert {"policy", "success (Wilson 95%)", "control Hz"} <= set(headers)
    note = page.locator("p.dropped").first.inner_text()
    assert "tokens/s" in note and "n/a: no bidirectional row" in note  # says what was left out, and why
    labels = page.evaluate(
        "() => Array.from(document.querySelector('table.sortable').tBodies[0].rows).map(r => r.cells[0].textContent)"
    )
    assert sorted(labels) == ["acme_pd (gain=0.5)", "acme_pd (gain=1)"]
    page.close()


def test_the_mt10_table_fits_a_1280_px_laptop_window_without_scrolling(browser, reports):  # noqa: F811
    page = _open(browser, reports["mt10"])
    widths = page.evaluate(
        """() => ({page: document.documentElement.scrollWidth,
                   tables: Array.from(document.querySelectorAll('.scroll')).map(d => [d.scrollWidth, d.clientWidth])})"""
    )
    assert widths["page"] <= LAPTOP["width"], widths
    for scroll, client in widths["tables"]:
        assert scroll <= client, widths  # no table scrolls sideways either
    # every success cell breaks the same way: the rate, then its interval and count on a
    # line each, none of them wrapped
    lines = page.evaluate(
        """() => Array.from(document.querySelector('table.sortable').tBodies[0].rows)
             .flatMap(r => Array.from(r.cells).filter(c => c.querySelector('.ci'))
             .map(c => Array.from(c.querySelectorAll('.ci')).map(s => s.getClientRects().length)
                       .concat([Math.round(c.querySelector('.ci').getBoundingClientRect().height)])))"""
    )
    assert len(lines) == 3 * 11 and len({tuple(x) for x in lines}) == 1 and lines[0][:2] == [1, 1], lines
    page.close()


def test_failures_are_listed_per_configuration_with_a_count_and_an_example(browser, reports):  # noqa: F811
    page = _open(browser, reports["reach"])
    rows = page.evaluate(
        "() => Array.from(document.querySelector('table.failures').tBodies[0].rows)"
        ".map(r => Array.from(r.cells).map(c => c.textContent))"
    )
    ((label, suite, reason, count, example),) = rows
    assert (label, suite, count) == ("acme_pd (gain=1)", "acme/reach", "2")
    assert reason == "ValueError: action [3.0, 0.0] is outside Box(-1, 1)"
    assert example == f"reach #2 ({reports['reach'].parent / 'reach'})"  # task, episode, run
    page.close()


def test_provenance_names_the_distribution_that_provided_the_suite_and_policy(browser, reports):  # noqa: F811
    page = _open(browser, reports["reach"])
    text = page.inner_text("body")
    assert "suite acme/reach: acme-reach 1.2.0; acme_pd: acme-reach 1.2.0" in text
    page.close()


def test_a_suite_without_tokens_gets_a_success_plot_with_intervals(browser, reports):  # noqa: F811
    page = _open(browser, reports["reach"])
    images = page.eval_on_selector_all("img", "imgs => imgs.map(i => [i.alt, i.naturalWidth])")
    assert len(images) == 1 and images[0][1] > 0
    assert images[0][0].startswith("acme/reach: success per task and configuration (Wilson 95%)")
    assert "no Pareto plot" not in page.inner_text("body")
    page.close()


def test_paper_table_of_a_meta_world_run_has_nothing_to_show_and_exits_2(cli, reports):
    code, out, err = cli("report", "paper-table", str(reports["mt10"].parent / "mt10"))
    assert code == 2 and out == ""
    assert err.strip() == (
        "dvla-harness report: error: metaworld/mt10: no LIBERO, CALVIN-like or SimplerEnv-like suite "
        "in these runs: no published table to lay them out beside (`dvla-harness leaderboard` shows them)"
    )
