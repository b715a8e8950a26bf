"""The README and the docs promise commands and pages: every promise must hold.

A user copies the README's commands as written, so each `dvla-harness` line of a bash
block is parsed by the real argument parser (a subcommand that exists, flags it takes,
values its choices allow), and every `docs/...` page a README or doc names must exist,
down to the heading an anchor points at. The front page stays a front page: short, with
no issue numbers and no run folders a clone does not have.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from harness.cli import build_parser

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
DOCS = sorted((REPO / "docs").glob("*.md"))
MAX_README_LINES = 260

FENCE = re.compile(r"^```([\w-]*)\n(.*?)^```", re.S | re.M)
DOC_LINK = re.compile(r"(?<![\w/.-])(docs/[\w.-]+\.md)(#[\w-]+)?")
SHELL_OPERATORS = {"&&", "||", "|", ";", "&"}
REDIRECTIONS = {">", ">>", "<", "2>", "&>"}


def _blocks(text: str, languages: set[str]) -> list[str]:
    return [body for lang, body in FENCE.findall(text) if lang in languages]


def _without_fences(text: str) -> str:
    return FENCE.sub("", text)


def _command_lines(block: str) -> list[str]:
    """Shell lines with their backslash continuations joined, as bash reads them."""
    return [line.strip() for line in block.replace("\\\n", " ").splitlines() if line.strip()]


def _words(line: str) -> list[str]:
    """Shell words of one line, a comment dropped only where bash drops it: at the start of a
    word. A `#` glued to an argument (`--out x# note`) stays, so the note's words reach the
    parser and fail it, as they would fail the shell's command."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.commenters = ""
    lexer.whitespace_split = True
    words: list[str] = []
    redirect = False
    for word in lexer:
        if word.startswith("#"):
            break
        if redirect:  # the file a `>` or `<` names is the shell's, not the command's
            redirect = False
        elif word in REDIRECTIONS:
            redirect = True
        else:
            words.append(word)
    return words


def dvla_commands(block: str) -> list[list[str]]:
    """The argument lists of every `dvla-harness` invocation in a bash block."""
    found = []
    for line in _command_lines(block):
        segment: list[str] = []
        for word in [*_words(line), ";"]:
            if word in SHELL_OPERATORS:
                if segment and Path(segment[0]).name == "dvla-harness":
                    found.append(segment[1:])
                segment = []
            else:
                segment.append(word)
    return found


def parse_error(args: list[str]) -> str | None:
    """What argparse says about these arguments, or None when they parse."""
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(args)
    except SystemExit as exc:
        if exc.code not in (0, None):
            return stderr.getvalue().strip().splitlines()[-1] if stderr.getvalue() else str(exc.code)
    return None


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = _without_fences(page.read_text())
    return {_slug(m.group(1)) for m in re.finditer(r"^#+\s+(.+)$", text, re.M)}


def readme_commands() -> list[list[str]]:
    return [cmd for block in _blocks(README.read_text(), {"bash", "sh"}) for cmd in dvla_commands(block)]


def test_the_extractor_sees_what_the_shell_sees():
    block = (
        "# a comment line\n"
        "dvla-harness run --suite metaworld/mt10 \\\n    --policy scripted --out runs/a  # trailing note\n"
        "dvla-harness serve --policy fast_dvla &\n"
        "python3 -m venv .venv && .venv/bin/dvla-harness run\n"
        "dvla-harness run --out runs/b# glued note\n"
        "dvla-harness leaderboard runs/b --format csv > board.csv\n"
    )
    assert dvla_commands(block) == [
        ["run", "--suite", "metaworld/mt10", "--policy", "scripted", "--out", "runs/a"],
        ["serve", "--policy", "fast_dvla"],
        ["run"],
        ["run", "--out", "runs/b#", "glued", "note"],
        ["leaderboard", "runs/b", "--format", "csv"],
    ]


def test_the_parser_check_rejects_what_a_user_would_trip_on():
    assert parse_error(["run", "--suite", "metaworld/mt10", "--out", "runs/a"]) is None
    assert "invalid choice" in (parse_error(["runn"]) or "")
    assert "unrecognized arguments" in (parse_error(["run", "--no-such-flag"]) or "")
    assert "unrecognized arguments" in (parse_error(["run", "--out", "runs/b#", "glued", "note"]) or "")
    assert parse_error(["run", "--workers", "$(nproc)"]) is not None
    assert parse_error(["run", "--device", "tpu"]) is not None


def test_the_readme_has_commands_to_check():
    commands = readme_commands()
    assert len(commands) >= 20, "the tour's commands were not found: is the block still ```bash?"
    assert {cmd[0] for cmd in commands} >= {
        "run",
        "list",
        "show",
        "leaderboard",
        "report",
        "gate",
        "sweep",
        "plot",
    }


@pytest.mark.parametrize("args", readme_commands(), ids=lambda args: " ".join(args)[:60])
def test_readme_command_parses(args):
    error = parse_error(args)
    assert error is None, f"`dvla-harness {' '.join(args)}`: {error}"


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.name)
def test_docs_commands_parse(page):
    bad = []
    for block in _blocks(page.read_text(), {"bash", "sh"}):
        for args in dvla_commands(block):
            if (error := parse_error(args)) is not None:
                bad.append(f"`dvla-harness {' '.join(args)}`: {error}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("page", [README, *DOCS], ids=lambda p: p.name)
def test_docs_links_resolve(page):
    missing = []
    for match in DOC_LINK.finditer(page.read_text()):
        target = REPO / match.group(1)
        if not target.is_file():
            missing.append(match.group(0))
        elif match.group(2) and match.group(2)[1:] not in _anchors(target):
            missing.append(f"{match.group(0)} (no such heading)")
    assert not missing, f"{page.name} names pages or headings that do not exist: {missing}"


def test_readme_lists_every_doc():
    readme = README.read_text()
    unlisted = [p.name for p in DOCS if f"docs/{p.name}" not in readme]
    assert not unlisted, f"the README's documentation map misses {unlisted}"


def test_readme_is_a_front_page():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_README_LINES
    assert not re.search(r"\bissues? #?\d", text, re.I), "issue numbers mean nothing to a user"
    assert not re.search(r"the mission|the issue's", text, re.I)
    prose = _without_fences(text)
    assert "runs/" not in prose, "prose names a run folder a clone does not have"


def test_readme_reads_only_run_folders_its_commands_make():
    made: set[str] = set()
    text = README.read_text()
    for lang, body in FENCE.findall(text):
        if lang in ("bash", "sh"):
            for args in dvla_commands(body):
                if "--out" in args:
                    made.add(args[args.index("--out") + 1].rstrip("/"))
                for word in args:
                    if word.startswith("runs/") and word.rstrip("/") not in made:
                        pytest.fail(
                            f"`dvla-harness {' '.join(args)}` reads {word}, which no earlier --out made"
                        )
        for folder in re.findall(r"runs/[\w.-]+", body if lang not in ("bash", "sh") else ""):
            assert folder in made, f"a {lang or 'text'} block reads {folder}, which no command made"
