"""A static, self-contained HTML report: leaderboards, the paper table, figures, provenance.

One file with inline CSS, inline JavaScript and figures as base64 PNG, so it opens
offline, from an e-mail or a CI artifact, with no server and no CDN. Tables sort when a
header is clicked; each cell carries the number it sorts by (`data-value`), so numbers
sort numerically and tests can read the exact values back. The report folder is built
in a temporary sibling and renamed into place: an error never leaves half a report.
"""

from __future__ import annotations

import base64
import html
import io
import os
import re
import shlex
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from results.labels import config_labels
from results.leaderboard import Block, Cell, Leaderboard, leaderboards, to_csv, to_markdown
from results.paper_table import blocks_markdown, paper_blocks, paper_table
from results.runs import Run, combined_episodes

GENERATOR = "dvla-harness report"
INDEX = "index.html"


class ReportError(ValueError):
    """The report cannot be written where asked; nothing was written."""


_CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:2em auto;max-width:1400px;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:2em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.6em 0;font-variant-numeric:tabular-nums;font-size:13px}
.scroll{overflow-x:auto;max-width:100%}
th,td{border:1px solid #ccc;padding:2px 4px;text-align:right;white-space:nowrap}
th{white-space:normal;min-width:3.5em;vertical-align:bottom;font-size:12px}
th:first-child,td:first-child{text-align:left;white-space:normal;min-width:8em}
td .ci{display:block;color:#666;font-size:.85em}
table.failures td{text-align:left;white-space:normal}
thead th{background:#f3f3f3;cursor:pointer;user-select:none}
th[aria-sort=ascending]::after{content:" \\25B2"}th[aria-sort=descending]::after{content:" \\25BC"}
tbody.published td{color:#555;background:#fafafa;font-style:italic}
.warn{background:#fff4d6;border:1px solid #e0b84c;padding:.5em 1em}
.note{color:#555;font-size:.92em}dl{display:grid;grid-template-columns:max-content 1fr;gap:2px 12px}
dt{font-weight:600}dd{margin:0;word-break:break-all}img{max-width:100%}
"""

# Click a header: sort each tbody of that table by the column, numbers numerically,
# empty cells last; a second click reverses.
_JS = """
function cellKey(td){if(!td||!td.hasAttribute('data-value'))return null;
 var v=td.getAttribute('data-value');var n=Number(v);return(v!==''&&!isNaN(n))?n:v;}
function sortTable(table,col,th){
 var dir=th.getAttribute('aria-sort')==='ascending'?'descending':'ascending';
 table.querySelectorAll('thead th').forEach(function(h){h.removeAttribute('aria-sort');});
 th.setAttribute('aria-sort',dir);
 Array.prototype.forEach.call(table.tBodies,function(body){
  var rows=Array.prototype.slice.call(body.rows);
  rows.sort(function(a,b){var x=cellKey(a.cells[col]),y=cellKey(b.cells[col]);
   if(x===null&&y===null)return 0;if(x===null)return 1;if(y===null)return -1;
   var c=(typeof x==='number'&&typeof y==='number')?x-y:String(x).localeCompare(String(y));
   return dir==='ascending'?c:-c;});
  rows.forEach(function(r){body.appendChild(r);});});}
document.querySelectorAll('table.sortable').forEach(function(table){
 table.querySelectorAll('thead th').forEach(function(th,i){
  th.addEventListener('click',function(){sortTable(table,i,th);});});});
"""


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


# "86.0% [74, 93] (43/50)": the rate, then its interval and its count on lines of their
# own, so a ten-task table fits a laptop screen and every cell breaks alike.
_SUCCESS = re.compile(r"^(-?[\d.]+%) (\[[^\]]*\]) (\(\d+/\d+\))$")


def _td(cell: Cell) -> str:
    value = "" if cell.value is None else f' data-value="{_e(cell.value)}"'
    m = _SUCCESS.match(cell.text)
    text = (
        "".join([_e(m[1]), *(f"<span class='ci'> {_e(part)}</span>" for part in m.groups()[1:])])
        if m
        else _e(cell.text)
    )
    return f"<td{value}>{text}</td>"


def _header(text: str) -> str:
    """A header that may break after its slashes and underscores as well as at spaces
    and hyphens ("NFE/" "chunk", "tau_" "conf"): a column is as wide as its widest cell,
    not its header, so an MT10 leaderboard fits a 1,280-px laptop window."""
    return re.sub(r"([/_])", r"\1<wbr>", _e(text))


def empty_columns(headers: Sequence[str], rows: Sequence[Sequence[Cell]]) -> list[int]:
    """Columns (never the first) with no value in any row: tokens/s and speedup on a suite
    whose policies decode no tokens, NFE for policies without a model."""
    return [
        i for i in range(1, len(headers)) if rows and all(i >= len(r) or r[i].value is None for r in rows)
    ]


def table_html(
    headers: Sequence[str], rows: Sequence[Sequence[Cell]], published_from: int | None = None
) -> str:
    """A sortable table; rows from `published_from` on go in their own tbody, so sorting
    never interleaves published reference rows with measured ones. Columns with no value
    in any row are left out, and a note under the table names them with why."""
    drop = set(empty_columns(headers, rows))
    why = {
        h: sorted({r[i].text for r in rows if i < len(r) and r[i].text not in ("", "-")})
        for i, h in enumerate(headers)
        if i in drop
    }
    headers = [h for i, h in enumerate(headers) if i not in drop]
    rows = [[c for i, c in enumerate(r) if i not in drop] for r in rows]
    split = len(rows) if published_from is None else published_from
    head = "".join(f'<th scope="col">{_header(h)}</th>' for h in headers)
    bodies = []
    for cls, part in (("measured", rows[:split]), ("published", rows[split:])):
        if part:
            trs = "".join("<tr>" + "".join(_td(c) for c in r) + "</tr>" for r in part)
            bodies.append(f'<tbody class="{cls}">{trs}</tbody>')
    # A table wider than the window scrolls on its own; the page does not.
    table = f'<table class="sortable"><thead><tr>{head}</tr></thead>{"".join(bodies)}</table>'
    note = ""
    if why:
        parts = [f"{h}" + (f" ({'; '.join(texts)})" if texts else "") for h, texts in why.items()]
        note = f'<p class="note dropped">Not shown, no value in any row: {_e(", ".join(parts))}.</p>'
    return f'<div class="scroll">{table}</div>{note}'


def _board_html(board: Leaderboard) -> str:
    headers, rows = board.cells()
    out = [f"<h2>{_e(board.suite)}</h2>", table_html(headers, rows)]
    if board.ranking is not None:
        out.append(f"<p>{_e(board.ranking.text())}</p>")
    if board.warnings:
        items = "".join(f"<li>{_e(w)}</li>" for w in board.warnings)
        out.append(f'<div class="warn"><b>Warnings</b><ul>{items}</ul></div>')
    return "".join(out)


def _block_html(block: Block) -> str:
    notes = "".join(f"<li>{_e(n)}</li>" for n in block.notes)
    return (
        f"<h3>{_e(block.title)}</h3>"
        + table_html(block.headers, block.rows, block.published_from)
        + (f'<ul class="note">{notes}</ul>' if notes else "")
    )


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode()


def _figure(data: str, alt: str) -> str:
    return (
        f"<figure><img alt='{_e(alt)}' src='data:image/png;base64,{data}'>"
        f"<figcaption>{_e(alt)}</figcaption></figure>"
    )


def _figures_html(episodes: pd.DataFrame) -> str:
    """Per suite: a Pareto plot (tokens/s against success, results.plots) of the
    configurations that decode tokens; for a suite where none does, success per task
    and configuration with its intervals (results.success_plot)."""
    try:
        from results.plots import PlotInputError, pareto_plot
        from results.success_plot import success_plot
    except ImportError:
        return '<p class="note">No figures: results.plots is not available.</p>'
    parts = []
    for suite, rows in episodes.groupby("suite", sort=False):
        # Configurations that decode no tokens (scripted, random) have no place on a tokens/s axis.
        decoding = rows.groupby("policy_config_id")["tokens_per_s"].transform(lambda v: v.notna().any())
        if not decoding.any():
            alt = f"{suite}: success per task and configuration (Wilson 95%); no policy decodes tokens"
            parts.append(_figure(_png(success_plot(rows, title=str(suite))), alt))
            continue
        try:
            fig = pareto_plot(rows[decoding])
        except (PlotInputError, ValueError, OSError) as exc:
            parts.append(f'<p class="note">{_e(suite)}: no Pareto plot ({_e(exc)})</p>')
            continue
        alt = f"{suite}: success against tokens/s, one marker per policy configuration"
        parts.append(_figure(_png(fig), alt))
    return "".join(parts)


MAX_REASON = 300  # characters of an exception message shown; the rest is in events.jsonl


def _failures_html(episodes: pd.DataFrame) -> str:
    """Why episodes raised, per configuration: each distinct reason with its count and
    one episode to look it up by (its traceback is in that run's events.jsonl)."""
    failed = episodes[episodes["failure_reason"].notna()]
    if failed.empty:
        return (
            '<p class="note">No episode raised: every failure to succeed was the task\'s, not an error.</p>'
        )
    labels = config_labels(episodes)
    headers = ["configuration", "suite", "reason", "episodes", "example episode"]
    rows = []
    for (cid, suite, reason), group in failed.groupby(
        ["policy_config_id", "suite", "failure_reason"], sort=False
    ):
        first = group.sort_values(["task_index", "episode_index"]).iloc[0]
        short = reason if len(reason) <= MAX_REASON else reason[:MAX_REASON] + "…"
        where = f"{first['task']} #{first['episode_index']}" + (
            f" ({first['run']})" if "run" in group else ""
        )
        rows.append(
            [
                Cell(labels[cid], labels[cid]),
                Cell(str(suite), str(suite)),
                Cell(short, reason),
                Cell(str(len(group)), len(group)),
                Cell(where, where),
            ]
        )
    rows.sort(key=lambda r: (str(r[0].value), -int(r[3].value or 0)))
    note = '<p class="note">Tracebacks: each run folder\'s events.jsonl (event episode_failed).</p>'
    return table_html(headers, rows).replace('class="sortable"', 'class="sortable failures"', 1) + note


def _providers(manifest: dict[str, Any]) -> str:
    """Which installed distribution (dvla-harness, or a plugin and its version) gave the
    suite and each policy: a plugin's results are only as good as its version."""
    suite = manifest.get("suite") or {}
    parts = [f"suite {suite.get('name')}: {suite['provided_by']}"] if suite.get("provided_by") else []
    for p in manifest.get("policies") or []:
        if p.get("provided_by"):
            parts.append(f"{p.get('name')}: {p['provided_by']}")
    return "; ".join(dict.fromkeys(parts)) or "not recorded"


def _provenance_html(run: Run) -> str:
    m = run.manifest
    if not m:
        return f"<h3>{_e(run.label)}</h3><p class='note'>No manifest.json: provenance unknown.</p>"
    env = m.get("environment") or {}
    suite = m.get("suite") or {}
    packages = {**(env.get("packages") or {}), **(env.get("simulators") or {})}
    items = {
        "run id": m.get("run_id"),
        "status": m.get("status"),
        "started / finished": f"{m.get('started_at')} / {m.get('finished_at')}",
        "suite": f"{suite.get('name')} v{suite.get('version')}: {', '.join(suite.get('tasks') or [])}",
        "render backend": suite.get("render_backend"),
        "MUJOCO_GL": env.get("mujoco_gl"),
        "mujoco": (suite.get("simulator_packages") or {}).get("mujoco") or packages.get("mujoco"),
        "versions": ", ".join(f"{k} {v}" for k, v in packages.items() if v),
        "python": env.get("python"),
        "host": env.get("host"),
        "CPU": f"{env.get('cpu')} ({env.get('cpu_count')} cores)",
        "GPU": env.get("gpu") or "none",
        "platform": env.get("platform"),
        "git commit": env.get("git_commit") or "n/a",
        "command": shlex.join(map(str, m.get("command") or [])),
        "policies": "; ".join(
            f"{p.get('name')} {p.get('config_id')} {p.get('params')}" for p in m.get("policies") or []
        ),
        "provided by": _providers(m),
    }
    rows = "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in items.items())
    return f"<h3>{_e(run.label)}</h3><dl>{rows}</dl>"


def render_page(
    runs: Sequence[Run],
    boards: Sequence[Leaderboard],
    title: str = "dvla-harness report",
    figures: bool = True,
    paper: Sequence[Block] = (),
    extra: Sequence[Block] = (),
    links_from: Path | None = None,
) -> str:
    """`extra`: further titled tables after the leaderboards (generalization gaps);
    `links_from`: the page's folder, from which the runs' rollout videos are linked."""
    # The same de-duplicated rows as the tables: an episode given twice counts once here too.
    episodes = combined_episodes(runs)
    duplicates = episodes.attrs.get("duplicates", 0)
    twice = f" ({duplicates} duplicate row(s) of an episode given twice not counted)" if duplicates else ""
    sections = [f"<h1>{_e(title)}</h1>"]
    sections.append(
        f'<p class="note">{len(runs)} run(s), {len(episodes)} episodes{twice}. '
        "Every number is computed from the runs' Parquet rows; click a column header to sort.</p>"
    )
    sections += [_board_html(b) for b in boards]
    sections += [_block_html(b) for b in extra]
    if paper:
        sections.append("<h2>Beside the published results</h2>")
        sections += [_block_html(b) for b in paper]
    sections.append("<h2>Failures</h2>" + _failures_html(episodes))
    if links_from is not None and "video" in episodes and episodes["video"].notna().any():
        sections.append("<h2>Rollout videos</h2>" + _videos_html(runs, episodes, links_from))
    if figures:
        sections.append("<h2>Figures</h2>" + _figures_html(episodes))
    sections.append("<h2>Provenance</h2>" + "".join(_provenance_html(r) for r in runs))
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<meta name='generator' content='{GENERATOR}'><title>{_e(title)}</title>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<style>{_CSS}</style></head><body>{''.join(sections)}<script>{_JS}</script></body></html>\n"
    )


def _videos_html(runs: Sequence[Run], episodes: pd.DataFrame, page: Path) -> str:
    """A table of the recorded episodes (`run --video`), each linked to its MP4 beside its
    run, by a path relative to the page (a report kept beside its runs keeps its links)."""
    folders = {r.label: Path(r.path).resolve() for r in runs}
    recorded = episodes[episodes["video"].notna()].sort_values(
        ["config_label", "task_index", "episode_index"]
    )
    rows = []
    for r in recorded.itertuples():
        target = folders[r.run] / str(r.video) if r.run in folders else Path(str(r.video))
        href = os.path.relpath(target, page.resolve())
        outcome = (
            "success" if r.success else (f"failed: {r.failure_reason}" if r.failure_reason else "failure")
        )
        rows.append(
            f"<tr><td>{_e(r.config_label)}</td><td>{_e(r.task)}</td><td>{r.episode_index}</td>"
            f"<td>{_e(outcome)}</td><td><a href='{_e(href)}'>{_e(Path(str(r.video)).name)}</a></td></tr>"
        )
    head = "".join(f"<th>{h}</th>" for h in ("configuration", "task", "episode", "outcome", "video"))
    note = (
        '<p class="note">MP4 files in each run folder\'s videos/ (recorded with <code>--video</code>); '
        "a red border marks a step the robot held still under an inference latency.</p>"
    )
    return f"<div class='scroll'><table class='videos'><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table></div>{note}"


def _gap_blocks(runs: Sequence[Run]) -> list[Block]:
    """LIBERO-PRO generalization gaps, where the runs hold perturbed suites."""
    from results.generalization import gap_blocks, gap_tables
    from results.leaderboard import config_labels

    episodes = combined_episodes(runs)
    return gap_blocks(gap_tables(episodes, config_labels(episodes)))


def check_out(out: str | os.PathLike[str], overwrite: bool) -> None:
    """Refuse a destination before any work: a file, a missing parent, or a folder
    that holds something other than an earlier report."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ReportError(f"{out} exists and is not a folder")
    if not out.parent.is_dir():
        raise ReportError(f"{out}: folder {out.parent} does not exist")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise ReportError(f"{out} exists and is not empty; pass --overwrite to replace it")
        index = out / INDEX
        if not index.is_file() or GENERATOR not in index.read_text(errors="replace")[:2000]:
            raise ReportError(f"{out} is not a dvla-harness report folder; refusing to delete it")


def write_report(
    runs: Sequence[Run],
    out: str | os.PathLike[str],
    baseline: str | None = None,
    overwrite: bool = False,
    allow_privileged: bool = False,
) -> tuple[Path, tuple[str, ...]]:
    """OUT/index.html (the page), leaderboard.md/.csv and paper-table.md, all or nothing.

    Returns the folder and the leaderboards' warnings (the caller shows them). LIBERO rows
    measured on privileged state raise results.published.PrivilegedRowsError before
    anything is written, unless `allow_privileged` (results.paper_table.paper_blocks)."""
    out = Path(out)
    check_out(out, overwrite)
    boards = leaderboards(runs, baseline)
    blocks = paper_blocks(paper_table(runs, baseline), allow_privileged)
    files = {
        INDEX: render_page(runs, boards, paper=blocks, extra=_gap_blocks(runs), links_from=out),
        "leaderboard.md": to_markdown(boards),
        "leaderboard.csv": to_csv(boards),
        "paper-table.md": blocks_markdown(blocks),
    }
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    try:
        tmp.mkdir()
        for name, text in files.items():
            (tmp / name).write_text(text)
        if out.is_dir() and any(out.iterdir()):
            out.rename(old)
        elif out.is_dir():
            out.rmdir()
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists() and not out.exists():
            old.rename(out)
        raise
    shutil.rmtree(old, ignore_errors=True)
    return out, tuple(f"{b.suite}: {w}" for b in boards for w in b.warnings)
