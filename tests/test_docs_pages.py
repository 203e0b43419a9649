"""The user pages under docs/ say what is true today; the history lives in docs/research/.

A user page is every docs/*.md except docs/changelog.md (docs/research/ is not a user page).
Each must stay under MAX_LINES lines, carry no date in its prose (a date may sit in a code
span or block, a link target, an HTML attribute or a file name written as code), and never
say "not kept": what was tried and dropped belongs in a dated research note. Every note in
docs/research/ must be listed in its index, docs/research/README.md, and the index must be
reachable from docs/README.md.

Stdlib only: `.venv/bin/python -m pytest tests/test_docs_pages.py -q`.
"""

import re
from pathlib import Path

from test_docs_references import prose_of  # fenced blocks and code spans blanked

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
RESEARCH = DOCS / "research"
NOT_USER_PAGES = {"changelog.md"}
MAX_LINES = 300

MONTHS = r"(?:Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Sept|Oct|Nov|Dec)(?:[a-z]*)\.?"
DATE = re.compile(
    r"\b\d{4}-\d{2}-\d{2}\b"                       # 2026-11-28
    r"|\b\d{4}/\d{2}/\d{2}\b"                      # 2026/11/28
    rf"|\b{MONTHS} \d{{1,2}}(?:st|nd|rd|th)?\b"    # Nov 28, November 28th
    rf"|\b\d{{1,2}}(?:st|nd|rd|th)? {MONTHS}(?![a-z])"  # 28 Nov, 28th November
)
NOT_KEPT = re.compile(r"not\s+kept", re.I)

LINK_TARGET = re.compile(r"(\]\()[^)]*(\))")
REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*\S+.*$", re.M)
ATTRIBUTE = re.compile(r"""\b(?:href|src|id|name)\s*=\s*(["'])[^"']*\1""", re.I)
COMMENT = re.compile(r"<!--.*?-->", re.S)


def user_pages():
    return sorted(p for p in DOCS.glob("*.md") if p.name not in NOT_USER_PAGES)


def prose(text):
    """The page's prose, line numbers kept: fenced blocks, code spans, link targets,
    reference definitions, HTML attributes that name files or anchors, and comments blanked."""
    text = COMMENT.sub(lambda m: "\n" * m.group(0).count("\n"), prose_of(text))
    text = LINK_TARGET.sub(lambda m: m.group(1) + "\n" * m.group(0).count("\n") + m.group(2), text)
    text = REFERENCE.sub("", text)
    return ATTRIBUTE.sub("", text)


def dates_in(text):
    """(line, date) for every date in the prose of a page's text."""
    found = []
    for n, line in enumerate(prose(text).splitlines(), 1):
        found += [(n, m.group(0)) for m in DATE.finditer(line)]
    return found


def not_kept_in(text):
    """Line numbers that say "not kept", anywhere in the page (code included)."""
    flat = re.sub(r"\s+", " ", text)
    if not NOT_KEPT.search(flat):
        return []
    lines = [n for n, line in enumerate(text.splitlines(), 1) if NOT_KEPT.search(line)]
    return lines or ["(across a line break)"]


def problems_of(page):
    text = page.read_text()
    name = page.relative_to(ROOT)
    problems = []
    count = len(text.splitlines())
    if count > MAX_LINES:
        problems.append(f"{name}: {count} lines (at most {MAX_LINES}: split it into task pages, "
                        f"or move history into docs/research/)")
    for line, date in dates_in(text):
        problems.append(f"{name}:{line}: a date in the prose ({date!r}): say what is true today, "
                        f"and keep when it happened in docs/research/")
    for line in not_kept_in(text):
        problems.append(f"{name}:{line}: \"not kept\": what was tried and dropped belongs in docs/research/")
    return problems


def test_there_are_user_pages_and_research_notes():
    names = {p.name for p in user_pages()}
    assert {"README.md", "model.md", "doom.md", "benchmarks.md"} <= names, names
    assert "changelog.md" not in names
    assert (RESEARCH / "README.md").exists(), "docs/research/README.md, the index of the research notes, is missing"


def test_every_user_page_is_short_undated_and_says_what_is_true_today():
    problems = [p for page in user_pages() for p in problems_of(page)]
    assert not problems, "user pages that read as a lab notebook:\n" + "\n".join(problems)


def test_every_research_note_is_in_the_index():
    index = (RESEARCH / "README.md").read_text()
    linked = {m.group(1).split("#")[0] for m in re.finditer(r"\]\(\s*<?([^)\s>]+)", index)}
    linked = {Path(t).name for t in linked if not re.match(r"^[a-z]+:", t) and "/" not in t.strip("./")}
    notes = sorted(p.name for p in RESEARCH.glob("*.md") if p.name != "README.md")
    assert notes, "docs/research/ holds no notes"
    missing = [n for n in notes if n not in linked]
    assert not missing, f"docs/research/README.md does not list {', '.join(missing)}"


def test_the_docs_index_links_the_research_notes():
    index = (DOCS / "README.md").read_text()
    assert re.search(r"\]\(\s*research/(README\.md)?(#[^)]*)?\)", index), \
        "docs/README.md does not link docs/research/ (research/README.md)"


def test_the_checks_catch_dates_not_kept_and_length_and_spare_code_and_links():
    page = (
        "# A page\n\n"
        "Measured 2026-11-28 on the CPU.\n"
        "On Nov 28 it was served; on 28 November too.\n"
        "It was tried and not\nkept.\n\n"
        "`runs/speed-2026-11-28/walk.json` and [a note](research/x.md#2026-11-28-evening) "
        "and <img src=\"bench/walk-2026-11-27.png\" alt=\"x\">.\n\n"
        "```sh\n# a comment of 2026-11-27\n```\n\n"
        "November and a 2026 budget, 11-28 and 28 frames, May the 4th.\n"
    )
    dates = dates_in(page)
    assert [d for _, d in dates] == ["2026-11-28", "Nov 28", "28 November"], dates
    assert [n for n, _ in dates] == [3, 4, 4], dates
    assert not_kept_in(page) == ["(across a line break)"]
    assert not_kept_in("a candidate, not kept\n") == [1]
    assert not_kept_in("kept, and not keeping it\n") == []

    class Fake:
        def __init__(self, text):
            self.text = text

        def read_text(self):
            return self.text

        def relative_to(self, _):
            return "docs/fake.md"

    long = Fake("line\n" * (MAX_LINES + 1))
    assert any("301 lines" in p for p in problems_of(long)), problems_of(long)
    assert problems_of(Fake("line\n" * MAX_LINES)) == []
    assert len(problems_of(Fake(page))) == 4, problems_of(Fake(page))
