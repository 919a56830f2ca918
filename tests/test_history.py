"""The project's pages, docstrings and comments describe what the library is and does, not how
it got there. History (who worked when, times of day, before/after stories, commit hashes)
belongs in `git log`.

Checked: README.md, paper_figs/README.md, benchmarks/README.md (whose generated header may
carry the date of the run it shows, on its `| run |` row only), and the comments and
docstrings of every Python file in jaxreg/, benchmarks/, examples/, paper_figs/ and tests/.
Code and string data are not checked (a `"%H:%M"` format is not history).
"""

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", "paper_figs/README.md", "benchmarks/README.md"]
CODE = ["jaxreg", "benchmarks", "examples", "paper_figs", "tests"]
# The one line of history a page may hold: the date of the benchmark run it shows.
ALLOWED = {
    "benchmarks/README.md": re.compile(r"\| run \| make bench, \d{4}-\d\d-\d\d \d\d:\d\d UTC \|")
}

HISTORY = {
    "a work session": re.compile(r"\bsessions?\b", re.I),
    "a time zone": re.compile(r"\bUTC\b"),
    "a previous run": re.compile(r"\b(previous|last|earlier) runs?\b", re.I),
    "a rejected attempt": re.compile(r"\btried and not kept\b", re.I),
    "a before/after story": re.compile(r"\bwas\b[^.;:\n]{0,60}?\bnow\b", re.I),
    "a time of day": re.compile(r"(?<![\w:\[(,.+\-])(?:[01]\d|2[0-3]):[0-5]\d(?![\w:\]])"),
    # 7-40 hex digits with at least one digit and one letter: a commit hash.
    "a commit hash": re.compile(r"\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b"),
}


def _findings(text: str) -> list[str]:
    return [what for what, pattern in HISTORY.items() if pattern.search(text)]


def _prose(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every comment and docstring line of a Python file."""
    source = path.read_text()
    tree = ast.parse(source, str(path))
    doc_starts = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                if isinstance(body[0].value.value, str):
                    doc_starts.add(body[0].lineno)
    lines = []
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            lines.append((token.start[0], token.string))
        elif token.type == tokenize.STRING and token.start[0] in doc_starts:
            for offset, line in enumerate(token.string.splitlines()):
                lines.append((token.start[0] + offset, line))
    return lines


def test_pages_hold_no_history():
    hits = []
    for name in PAGES:
        path = ROOT / name
        if not path.exists():
            continue
        allowed = ALLOWED.get(name)
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if allowed is not None and allowed.fullmatch(line.strip()):
                continue
            hits += [f"{name}:{number}: {what}: {line.strip()}" for what in _findings(line)]
    assert not hits, "history in the project's pages:\n" + "\n".join(hits)


def test_docstrings_and_comments_hold_no_history():
    hits = []
    for folder in CODE:
        for path in sorted((ROOT / folder).rglob("*.py")):
            name = path.relative_to(ROOT)
            for number, line in _prose(path):
                hits += [f"{name}:{number}: {what}: {line.strip()}" for what in _findings(line)]
    assert not hits, "history in docstrings and comments:\n" + "\n".join(hits)


def test_the_patterns_catch_history_and_spare_code():
    """Each pattern fires on the history it names and not on ordinary prose or slices."""
    for story in ["this session", "at 21:59", "22:05 UTC", "the previous run", "tried and not "
                  "kept", "was 232 ms, now 101", "at commit 7bab9b7", "see bf34e0d"]:  # fmt: skip
        assert _findings(story), story
    for prose in ["x[:, 0:3]", "x[10:20]", "a (6, 6) matrix", "deadline", "1e-6", "float32",
                  "ratio 1:10", "1234567 points", "was computed", "is not kept"]:  # fmt: skip
        assert not _findings(prose), prose
