"""The docs state what is: no development history outside CHANGELOG.md.

README.md, CONTRIBUTING.md, the guide pages, the results files and the comments and docstrings of
``jaxloc/`` describe the project as it is, each number with its command, machine and date. Which
session, issue or round of development produced something, what a value "was" before a fix, and
what changed "since" belong in CHANGELOG.md (and in git). Each pattern below names one way such
history was written; each is checked against text it must find and text it must leave alone
(SG2Loc's coarse-to-fine rounds, upstream issue references such as jax-ml/jax#39103, "was" in
ordinary prose). A failure lists every hit as ``file:line: text``.

The pages must also not point into folders outside the repository (a fresh clone has none).
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: Name -> pattern of development history (matched case-insensitively, line by line).
HISTORY = {
    # "session 28", "Session 18 (...)", "sessions 3-4", "session-1 code"
    "session N": r"\bsessions?[ -]\d+",
    # "this session's changes", "the session's start", "the next GPU session", "session start"
    "this session": (
        r"\b(?:this|that|the|same|next|previous|earlier|later|last|gpu) session\b"
        r"|\bsession(?:'s)?[ -]start\b"
    ),
    # "issue 38", "issues 35 and 38", "the benchmark", "(issue: 2500)"; not "an issue"
    "issue N": r"\bissues? #?\d+|\bthe issue's\b|\(issue\b",
    # "#38" as a project issue or pull request; not "jax-ml/jax#39103" (owner/repo#N)
    "#N": r"(?:^|[\s(\[,;])#\d+\b",
    # "(was: a traceback)", "(was 30 s)", "were: ..."
    "was:": r"\bwas:|\bwere:|\((?:was|were)\b",
    # development rounds: "round-12", "in round 7", "round 12's robust" (SG2Loc's filter rounds
    # are numbered 0-4 and stay legitimate)
    "round N": r"\bround[- ](?:[5-9]|[1-9]\d+)\b|\b(?:development|review) rounds?\b",
    # "(fixed, session 28)", "; fixed", "found and fixed"
    "fixed": (
        r"\(fixed(?:[,;:)]|\s+(?:in|by|since|on|after)\b)|;\s*fixed(?:[,;.)]|\s+by\b|$)"
        r"|\bfound and fixed\b|\bnow fixed\b"
    ),
    "previously": r"\bpreviously\b|\bformerly\b|\buntil now\b",
    "no longer": r"\bno longer\b",
    # "it used to hang"; not "the key used to draw the particles"
    "used to": r"\b(?:it|they|this|that|which|we|there|\w+ \d+) used to\b",
    "this change": r"\b(?:before|after|since|until|with|without) (?:this|that) (?:change|fix)\b",
    # "now ... instead of ..." (what changed), within one clause
    "now instead of": r"\bnow\b[^.;:,]{0,60}\binstead of\b",
    # a commit hash as narrative: "(4b3231f)", "at 2de6190's code", "commit 37db8d8"; an upstream
    # pin is written repo@hash
    "commit hash": r"(?<![\w/#.:@-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,12}(?![\w-])",
}
PATTERNS = {name: re.compile(pattern, re.IGNORECASE) for name, pattern in HISTORY.items()}
#: A folder outside the repository: the sibling data folder, absolute work paths.
OUTSIDE = re.compile(r"\.\./shared\b|(?<![\w.])/work/")

#: Markdown checked (CHANGELOG.md is the one place for history).
MARKDOWN = (
    "README.md",
    "CONTRIBUTING.md",
    "docs/pages/**/*.md",
    "benchmarks/results/*.md",
    "experiments/results/**/*.md",
)
#: Pages a reader of the docs follows (no folder outside the repository).
PAGES = ("README.md", "CONTRIBUTING.md", "docs/pages/**/*.md")


def files(globs) -> list[Path]:
    found = set()
    for glob in globs:
        found.update(path for path in REPO.glob(glob) if path.is_file())
    return sorted(found)


def history(text: str) -> list[str]:
    """The names of the history patterns that ``text`` matches."""
    return [name for name, pattern in PATTERNS.items() if pattern.search(text)]


def code_text(path: Path) -> list[tuple[int, str]]:
    """``(line, text)`` of every comment and docstring line of a Python file."""
    source = path.read_text(encoding="utf-8")
    lines = []
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            lines.append((token.start[0], token.string))
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                if isinstance(body[0].value.value, str):
                    first = body[0].value.lineno
                    for offset, line in enumerate(body[0].value.value.splitlines()):
                        lines.append((first + offset, line))
    return lines


def hits_in(path: Path, lines) -> list[str]:
    where = path.relative_to(REPO)
    return [
        f"{where}:{number}: [{', '.join(names)}] {text.strip()[:160]}"
        for number, text in lines
        if (names := history(text))
    ]


def markdown_lines(path: Path) -> list[tuple[int, str]]:
    return list(enumerate(path.read_text(encoding="utf-8").splitlines(), 1))


def test_the_docs_and_results_hold_no_development_history():
    hits = [hit for path in files(MARKDOWN) for hit in hits_in(path, markdown_lines(path))]
    assert not hits, "development history (move it to CHANGELOG.md):\n" + "\n".join(hits)


def test_jaxloc_comments_and_docstrings_hold_no_development_history():
    sources = sorted((REPO / "jaxloc").rglob("*.py"))
    hits = [hit for path in sources for hit in hits_in(path, code_text(path))]
    assert not hits, "development history in comments / docstrings:\n" + "\n".join(hits)


def test_no_page_points_outside_the_repository():
    hits = [
        f"{path.relative_to(REPO)}:{number}: {line.strip()[:160]}"
        for path in files(PAGES)
        for number, line in markdown_lines(path)
        if OUTSIDE.search(line)
    ]
    assert not hits, "pages that name a folder outside the repository:\n" + "\n".join(hits)


def test_the_checks_see_what_they_look_for():
    assert len(files(MARKDOWN)) > 20 and (REPO / "jaxloc" / "sg2loc" / "_filter.py").is_file()
    assert OUTSIDE.search("io.load_instance_map('../shared/data/maps')")
    assert OUTSIDE.search("before = /work/main with the binary traversal")
    assert not OUTSIDE.search("see ../pages/results.md or docs/work/notes")


@pytest.mark.parametrize(
    "text",
    [
        "2026-12-06, session 26, quiet, three runs",
        "## Session 18 (2026-12-05, later): a smaller robust solve",
        "as sessions 3-4 measured",
        "the section below is the session-1 code",
        "before this session's packet and direction changes",
        "four runs alternating with the session's start",
        "Every target of issue 38 is met",
        "The issue's benchmark: 2500 particles",
        "help='poses per ray set (issue: 2500)'",
        "first used in #38, reverted in #41",
        "exit 2 (was: tracebacks with exit 1; fixed)",
        "DCC04 4.4 s warm (was 30 s)",
        "the robust setting of round-12",
        "a tighter bound in round 7",
        "(fixed, session 28)",
        "(was: a bare UnicodeDecodeError; fixed by the shared text parser)",
        "(fixed: a NaN pose)",
        "a NaN pose (fixed in 0.3)",
        "found and fixed: an empty .npy raised EOFError",
        "the map previously stored a zero embedding",
        "so that XLA no longer computes the norm",
        "leaf_size 0 used to make the BVH build split forever",
        "it used to hang",
        "the ratio moved from 0.11x to 0.13x before this change",
        "the check now runs on the host instead of in the program",
        "the session's start (4b3231f, a worktree)",
        "at 2de6190's code",
        "every contracting product asks for HIGHEST precision (commit 37db8d8)",
    ],
)
def test_history_is_found(text):
    assert history(text), text


@pytest.mark.parametrize(
    "text",
    [
        "round 0 spreads the particles over the floor; rounds 1, 2, ... start in a box",
        "the re-initialisation box of rounds 1, 2 and 3 (round 2's is 0.8 m)",
        "round 4/4 (stride 4)",
        "jax/jaxlib 0.10.2 miscompiles vmapped reductions (jax-ml/jax#39103)",
        "pytest-xdist 3.8 hangs (pytest-dev/pytest-xdist#784)",
        "it was measured on 2026-12-06 on a 2-core CPU",
        "the map it was described with",
        "fixed shapes: each capacity compiles once",
        "a fixed count of 2500 particles on every frame",
        "the key used to draw the particles",
        "barycentric coordinates (used to interpolate colours)",
        "a shell session on two shared cores, other sessions running",
        "an issue with the data",
        "trace it now and compile it in a background thread, instead of on the first call",
        "sha256 e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
        "colour #1f77b4, 1280x720, 0x7f3a2b1c",
        "# 1. the demo: builds a synthetic room",
        "checked against HeLiPR-File-Player@e8d95e3 (its .bin readers)",
        "a fixed count (2500 particles) beats KLD-sampling; fixed count 0.044 m",
    ],
)
def test_legitimate_text_is_left_alone(text):
    assert not history(text), (text, history(text))
