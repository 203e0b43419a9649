"""References in the docs that cannot drift, each checked against the thing it names:

- the command-line pages (docs/cli.md, and docs/cli-evaluation.md for the evaluation
  commands) against the binary: every subcommand of `worldpack --help` (and of its groups,
  `bench`, `sim`) has a section, a heading that starts with `worldpack SUBCOMMAND`; every
  long flag its `--help` lists is mentioned in that section; and every flag the pages give
  a command (in its section, or in `worldpack CMD --flag` anywhere) is one the binary has;
- docs/openapi.json against the document a real `worldpack serve` serves at /openapi.json;
- every relative link of README.md and docs/**/*.md: the file exists, and a `#anchor` into
  a markdown page names one of its headings (GitHub's slugs) or HTML ids.

`python tests/test_docs_references.py --write` (or ./scripts/openapi.sh) rewrites
docs/openapi.json from a real server.
"""

import functools
import json
import os
import re
import subprocess
import sys
import tempfile
import time
import unicodedata
import urllib.parse
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))
CLI_PAGES = (ROOT / "docs" / "cli.md", ROOT / "docs" / "cli-evaluation.md")
OPENAPI = ROOT / "docs" / "openapi.json"
REGENERATE = "regenerate it with `.venv/bin/python tests/test_docs_references.py --write` (or ./scripts/openapi.sh)"

# ---------------------------------------------------------------------------------------
# The binary's commands and flags, from its --help.

OPTION_LINE = re.compile(r"^ {2,6}(?:-[A-Za-z0-9], )?--([a-z0-9][a-z0-9-]*)")
FLAG = re.compile(r"(?<![\w-])--([a-z0-9][a-z0-9-]*)")
ALWAYS = {"help", "version"}


def help_of(path):
    out = subprocess.run([BIN, *path, "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, f"`worldpack {' '.join(path)} --help` failed: {out.stderr}"
    return out.stdout


def parse_help(text):
    """(subcommands, long flags) of one --help page (clap's layout)."""
    subs, flags, section = [], set(), None
    for line in text.splitlines():
        if line in ("Commands:", "Options:", "Arguments:"):
            section = line[:-1]
            continue
        if line and not line[0].isspace():
            section = None
        elif section == "Commands":
            m = re.match(r"^  (\S+)", line)
            if m and m.group(1) != "help":
                subs.append(m.group(1))
        elif section == "Options":
            m = OPTION_LINE.match(line)
            if m:
                flags.add(m.group(1))
    return subs, flags - ALWAYS


@functools.lru_cache(maxsize=None)
def command_tree():
    """{("bench", "walk"): {"model", "steps", ...}, ("bench",): set(), ...}, groups included."""
    tree = {}

    def walk(path):
        subs, flags = parse_help(help_of(path))
        tree[path] = flags
        for sub in subs:
            walk(path + (sub,))

    walk(())
    return tree


# ---------------------------------------------------------------------------------------
# docs/cli.md: sections, and the flags each mentions.

FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
SPAN = re.compile(r"(`+)(.+?)\1", re.S)
SEPARATOR = re.compile(r"\s(?:\|\|?|;|&&?|#)(?:\s|$)")


def is_worldpack(token):
    return token == "worldpack" or token.endswith("target/release/worldpack")


def resolve(tokens, tree):
    path = ()
    for t in tokens:
        if path + (t,) in tree:
            path += (t,)
        else:
            break
    return path


def flags_in(tokens):
    return [m.group(1) for t in tokens if t.lstrip("[(").startswith("--") for m in [FLAG.search(t)] if m]


def read_code(content, tree):
    """What one code span or code line says about flags: a list of (path, flag) for
    `worldpack CMD ... --flag` (or `CMD --flag` for a top-level CMD), and `None` paths for
    flags of a span that starts with a flag (the section's own)."""
    found = []
    for piece in SEPARATOR.split(content):
        tokens = piece.split()
        if not tokens:
            continue
        at = next((i for i, t in enumerate(tokens) if is_worldpack(t)), None)
        if at is not None and len(tokens) > at + 1:
            rest = tokens[at + 1:]
            path = resolve(rest, tree)
            if not path and not rest[0].startswith("-") and not rest[0].isupper():  # CMD: a placeholder
                found.append((("?", rest[0]), None))
                continue
            found += [(path, f) for f in flags_in(rest[len(path):])]
        elif at is None and tokens[0].lstrip("[(").startswith("--"):
            found += [(None, f) for f in flags_in(tokens)]
        elif at is None and (tokens[0],) in tree:
            path = resolve(tokens, tree)
            found += [(path, f) for f in flags_in(tokens[len(path):])]
    return found


def command_of_heading(text, tree):
    m = SPAN.search(text)
    if not m:
        return None
    tokens = m.group(2).split()
    if not tokens or not is_worldpack(tokens[0]):
        return None
    return resolve(tokens[1:], tree) or None


def cli_units(text):
    """(line, kind, content) in order: kind 'heading' (content: (level, text)), 'code'
    (a fenced line, continuations joined), 'span' (inline code) or 'prose'."""
    lines = text.splitlines()
    i, units = 0, []
    paragraph, start = [], 0

    def flush():
        nonlocal paragraph
        if paragraph:
            block = "\n".join(paragraph)
            for m in SPAN.finditer(block):
                units.append((start + block[:m.start()].count("\n") + 1, "span", m.group(2)))
            prose = SPAN.sub(" ", block)
            units.append((start + 1, "prose", prose))
        paragraph = []

    while i < len(lines):
        line = lines[i]
        if FENCE.match(line):
            flush()
            i += 1
            while i < len(lines) and not FENCE.match(lines[i]):
                first, code = i, lines[i]
                while code.endswith("\\") and i + 1 < len(lines):
                    i += 1
                    code = code[:-1] + " " + lines[i]
                units.append((first + 1, "code", code))
                i += 1
            i += 1
            continue
        h = HEADING.match(line)
        if h:
            flush()
            units.append((i + 1, "heading", (len(h.group(1)), h.group(2))))
            for m in SPAN.finditer(h.group(2)):
                units.append((i + 1, "span", m.group(2)))
        elif not line.strip():
            flush()
        else:
            if not paragraph:
                start = i
            paragraph.append(line)
        i += 1
    flush()
    return units


def cli_problems(texts, tree):
    """Every way the pages ({name: markdown}) and the binary disagree, one message each."""
    problems = []
    sections, mentioned = {}, {}
    children = {}
    for path in tree:
        for i in range(1, len(path)):
            children.setdefault(path[:i], set()).update(tree[path])
    units = [(page, line, kind, content) for page, text in texts.items() for line, kind, content in cli_units(text)]
    stack, last_page = [], None  # (level, path or None) of the headings open
    for page, line, kind, content in units:
        if page != last_page:
            stack, last_page = [], page
        if kind == "heading":
            level, title = content
            while stack and stack[-1][0] >= level:
                stack.pop()
            path = command_of_heading(title, tree)
            stack.append((level, path))
            if path:
                if path in sections:
                    problems.append(f"{page}:{line}: a second section for `worldpack {' '.join(path)}` "
                                    f"(the first is {sections[path]})")
                sections.setdefault(path, f"{page}:{line}")
                mentioned.setdefault(path, set())
        owner = next((p for _, p in reversed(stack) if p), None)
        where = f"{page}:{line}"
        if kind == "prose":
            found = [(None, f) for f in FLAG.findall(content)]
        elif kind in ("span", "code"):
            found = read_code(content, tree)
        else:
            continue
        for path, flag in found:
            if path and path[0] == "?":
                problems.append(f"{where}: `worldpack {path[1]}`: the binary has no such subcommand")
                continue
            if path is None:
                if owner is None:
                    continue
                path = owner
            if flag in ALWAYS or (path == owner and flag in children.get(path, ())):
                continue  # a group's section may speak of its subcommands' flags
            name = " ".join(path)
            if flag not in tree[path]:
                problems.append(f"{where}: `worldpack {name}` has no flag --{flag} "
                                f"(`worldpack {name} --help` lists {', '.join('--' + f for f in sorted(tree[path])) or 'none'})")
            elif path == owner:
                mentioned[path].add(flag)
    for path in sorted(tree):
        if not path:
            continue
        name = " ".join(path)
        if path not in sections:
            problems.append(f"{' and '.join(texts)}: no section for `worldpack {name}` "
                            f"(a heading that starts with `worldpack {name}`)")
            continue
        for flag in sorted(tree[path] - mentioned[path]):
            problems.append(f"{sections[path]}: the section of `worldpack {name}` does not mention its flag --{flag}")
    return problems


def cli_texts():
    return {str(page.relative_to(ROOT)): page.read_text() for page in CLI_PAGES}


def test_every_subcommand_has_its_section_and_every_flag_is_the_binarys():
    tree = command_tree()
    assert ("bench", "walk") in tree and ("sim", "loopnav") in tree and "model" in tree[("serve",)], \
        "the --help parser found no nested subcommands or flags: has clap's layout changed?"
    problems = cli_problems(cli_texts(), tree)
    assert not problems, "the command-line pages and the binary disagree:\n" + "\n".join(problems)


def test_the_cli_check_catches_a_dropped_section_a_dropped_flag_and_an_invented_one():
    tree, texts = command_tree(), cli_texts()
    cli = "docs/cli.md"

    def edited(new):
        return {**texts, cli: new}

    text = texts[cli]
    heading = re.search(r"^#+ `worldpack check\b.*$", text, re.M)
    assert heading, "docs/cli.md has no `worldpack check` heading"
    without = text.replace(heading.group(0), "## Checking a dataset")
    assert any("no section for `worldpack check`" in p for p in cli_problems(edited(without), tree))
    walk = re.search(r"^#+ `worldpack bench walk\b.*$", text, re.M)
    assert walk, "docs/cli.md has no `worldpack bench walk` heading"
    section_end = re.compile(r"^#{1,%d} " % walk.group(0).index(" "), re.M).search(text, walk.end())
    section = text[walk.start():section_end.start() if section_end else len(text)]
    dropped = text.replace(section, section.replace("--explore", "--explored"))
    problems = cli_problems(edited(dropped), tree)
    assert any("bench walk` does not mention its flag --explore" in p for p in problems), problems
    assert any("`worldpack bench walk` has no flag --explored" in p for p in problems), problems
    invented = text + "\n```sh\nworldpack serve --no-such-flag\nworldpack frobnicate --out x\n```\n"
    problems = cli_problems(edited(invented), tree)
    assert any("`worldpack serve` has no flag --no-such-flag" in p for p in problems), problems
    assert any("`worldpack frobnicate`: the binary has no such subcommand" in p for p in problems), problems


# ---------------------------------------------------------------------------------------
# docs/openapi.json against the served document.

def served_openapi():
    """The document a memory-only `worldpack serve` serves at /openapi.json (the document
    is the API's, not the model's)."""
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.Popen([BIN, "serve", "--memory-only", "--store", str(Path(tmp) / "store.redb"),
                                 "--addr", "127.0.0.1:0"], cwd=ROOT, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            first = proc.stdout.readline()
            m = re.search(r"listening on (http://\S+)", first)
            if not m:
                raise RuntimeError(f"`worldpack serve` did not start: {first}{proc.stderr.read()}")
            url = m.group(1)
            for _ in range(100):
                try:
                    with urllib.request.urlopen(url + "/openapi.json", timeout=10) as r:
                        return json.load(r)
                except OSError:
                    time.sleep(0.1)
            raise RuntimeError(f"{url}/openapi.json did not answer")
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def first_difference(saved, served, at="$"):
    if type(saved) is not type(served):
        return f"{at}: {type(saved).__name__} saved, {type(served).__name__} served"
    if isinstance(saved, dict):
        for key in sorted(set(saved) | set(served)):
            if key not in served:
                return f"{at}.{key}: saved, no longer served"
            if key not in saved:
                return f"{at}.{key}: served, not saved"
            d = first_difference(saved[key], served[key], f"{at}.{key}")
            if d:
                return d
        return None
    if isinstance(saved, list):
        for i, (a, b) in enumerate(zip(saved, served)):
            d = first_difference(a, b, f"{at}[{i}]")
            if d:
                return d
        if len(saved) != len(served):
            return f"{at}: {len(saved)} items saved, {len(served)} served"
        return None
    if saved != served:
        return f"{at}: {json.dumps(saved)[:120]} saved, {json.dumps(served)[:120]} served"
    return None


def write_openapi():
    OPENAPI.write_text(json.dumps(served_openapi(), indent=2, sort_keys=True, ensure_ascii=False) + "\n")


def test_docs_openapi_json_is_the_document_the_server_serves():
    assert OPENAPI.exists(), f"docs/openapi.json is missing: {REGENERATE}"
    saved, served = json.loads(OPENAPI.read_text()), served_openapi()
    assert saved == served, (f"docs/openapi.json differs from what `worldpack serve` serves at /openapi.json "
                             f"(first difference: {first_difference(saved, served)}); {REGENERATE}")


def test_the_openapi_check_catches_an_edited_document():
    saved = json.loads(OPENAPI.read_text())
    edited = json.loads(json.dumps(saved))
    edited["paths"].pop(sorted(edited["paths"])[0])
    assert edited != saved and first_difference(edited, saved).startswith("$.paths.")


# ---------------------------------------------------------------------------------------
# Relative links of README.md and docs/**/*.md.

LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HTML_LINK = re.compile(r"""<(?:a|img|source|link)\b[^>]*?\b(?:href|src)\s*=\s*["']([^"']+)["']""", re.I)
REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.M)
HTML_ID = re.compile(r"""<[a-z][^>]*?\b(?:id|name)\s*=\s*["']([^"']+)["']""", re.I)


def pages():
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def prose_of(text):
    """The page without fenced code and inline code spans, line numbers kept."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            out.append("")
        else:
            out.append("" if fenced else line)
    return SPAN.sub(lambda m: "\n" * m.group(0).count("\n"), "\n".join(out))


def slug(heading):
    """GitHub's anchor for a heading: its rendered text, lower case, punctuation but `-`
    and `_` dropped, each space a `-`."""
    text = re.sub(r"!?\[((?:[^\[\]]|\[[^\]]*\])*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"<[^>]+>", "", text).lower()
    text = "".join(c for c in text if c in "-_ " or unicodedata.category(c)[0] in "LMN")
    return text.replace(" ", "-")


@functools.lru_cache(maxsize=None)
def anchors_of(page):
    text = page.read_text()
    seen, anchors = {}, set()
    fenced = False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        h = None if fenced else HEADING.match(line)
        if h:
            s = slug(h.group(2))
            n = seen.get(s, 0)
            seen[s] = n + 1
            anchors.add(s if n == 0 else f"{s}-{n}")
    anchors |= set(HTML_ID.findall(prose_of(text)))
    return anchors


def broken_links(page):
    text = prose_of(page.read_text())
    found = []
    for pattern in (LINK, HTML_LINK, REFERENCE):
        for m in pattern.finditer(text):
            found.append((text[:m.start()].count("\n") + 1, m.group(1)))
    problems = []
    for line, target in sorted(found):
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("//"):
            continue
        path, _, anchor = target.partition("#")
        path = urllib.parse.unquote(path.split("?")[0])
        file = page if not path else (ROOT / path.lstrip("/") if path.startswith("/") else page.parent / path)
        where = f"{page.relative_to(ROOT)}:{line}: {target}"
        if not file.exists():
            problems.append(f"{where}: no such file")
        elif anchor and file.suffix == ".md" and urllib.parse.unquote(anchor) not in anchors_of(file.resolve()):
            problems.append(f"{where}: {file.name} has no heading with that anchor")
    return problems


def test_every_relative_link_of_the_docs_lands():
    problems = [p for page in pages() for p in broken_links(page)]
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_the_link_check_catches_a_missing_file_and_a_missing_anchor(tmp_path):
    page = tmp_path / "page.md"
    (tmp_path / "other.md").write_text("# Other\n\n## The `worldpack geometry [--input FILE]` op\n\n## Twice\n\n## Twice\n")
    page.write_text("[a](other.md#the-worldpack-geometry---input-file-op) [b](other.md#twice-1) [c](#here)\n\n"
                    "## Here\n\n[d](missing.md) [e](other.md#nowhere) `[f](ignored.md)`\n\n```\n[g](ignored.md)\n```\n")
    global ROOT
    root, ROOT = ROOT, tmp_path
    try:
        problems = broken_links(page)
    finally:
        ROOT = root
    assert len(problems) == 2, problems
    assert "missing.md: no such file" in problems[0] and "other.md#nowhere" in problems[1]


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: tests/test_docs_references.py --write   (rewrites docs/openapi.json from a real server)")
    write_openapi()
    print(f"wrote {OPENAPI.relative_to(ROOT)}")
