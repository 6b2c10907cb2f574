"""The documentation: README.md as the front door, docs/*.md as the reference.

Pure file reading, no import of quadshank: the README stays short and names the two
commands, every relative link and image resolves, no page reads as a development diary,
and the Python examples use only the public API.
"""

from __future__ import annotations

import ast
import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
README_MAX_CHARS = 10_000


def doc_files() -> list[Path]:
    return [README, *sorted(DOCS.glob("*.md"))]


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


FENCE = re.compile(r"^(```|~~~)[^\n]*\n.*?^\1[ \t]*$", re.M | re.S)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def prose(text: str) -> str:
    """The text without fenced code blocks and inline code (links are not read there)."""
    return INLINE_CODE.sub("", FENCE.sub("", text))


def code_blocks(text: str, languages=("python", "py")) -> list[str]:
    return [
        m.group(2)
        for m in re.finditer(r"^```[ \t]*(\w*)[^\n]*\n(.*?)^```[ \t]*$", text, re.M | re.S)
        if m.group(1).lower() in languages
    ]


# [text](target) and ![alt](target), with an optional "title"
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def links(text: str) -> list[str]:
    return LINK.findall(prose(text))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text
    text = unicodedata.normalize("NFC", text.strip().lower())
    text = "".join(c for c in text if c.isalnum() or c in " -_")
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for m in re.finditer(r"^#{1,6}[ \t]+(.+?)[ \t#]*$", FENCE.sub("", path.read_text(encoding="utf-8")), re.M):
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


# ---------------------------------------------------------------------------- the README


def test_readme_is_short():
    size = len(README.read_bytes())  # bytes >= characters: the stricter count
    assert size < README_MAX_CHARS, f"README.md is {size} bytes; keep it under {README_MAX_CHARS} (move material to docs/)"


def test_readme_names_the_two_commands():
    text = README.read_text(encoding="utf-8")
    for command in ("make demo", "make test"):
        assert command in text, f"README.md does not mention `{command}`"


def test_readme_links_into_docs():
    targets = [t for t in links(README.read_text(encoding="utf-8")) if t.startswith("docs/")]
    assert targets, "README.md has no link into docs/"


def test_docs_exist():
    assert (DOCS / "index.md").is_file()
    assert len(list(DOCS.glob("*.md"))) >= 5


# ---------------------------------------------------------------------------- links


def test_link_regex_and_slug():
    text = "See [a](docs/x.md#y), ![img](results/a.png \"t\") and `[not](a link)`.\n```\n[nor](this)\n```\n"
    assert links(text) == ["docs/x.md#y", "results/a.png"]
    assert slug("The hierarchical fit (`quadshank fit`)") == "the-hierarchical-fit-quadshank-fit"
    assert slug("J_φ,p rollouts") == "j_φp-rollouts"


@pytest.mark.parametrize("path", doc_files(), ids=rel)
def test_relative_links_resolve(path: Path):
    problems = []
    for target in links(path.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("//"):
            continue  # http(s):, mailto: and the like
        file_part, _, fragment = target.partition("#")
        if not file_part:
            continue  # a pure #anchor within the page
        dest = (path.parent / file_part).resolve()
        if not dest.exists():
            problems.append(f"{target}: no such file ({dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest})")
        elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
            problems.append(f"{target}: no heading with anchor #{fragment} in {rel(dest)}")
    assert not problems, f"{rel(path)} has broken links:\n  " + "\n  ".join(problems)


# ---------------------------------------------------------------------------- no development diary

HEX_WITH_LETTER_AND_DIGIT = r"(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]"
DIARY = [
    (re.compile(rf"\b(at|of|commit|before|since|on|in|from) {HEX_WITH_LETTER_AND_DIGIT}{{7,12}}\b"), "a commit as history"),
    (re.compile(rf"\b{HEX_WITH_LETTER_AND_DIGIT}{{7,40}}\b"), "a commit-hash-like token"),
    (re.compile(r"20\d\d-[01]\d-[0-3]\d"), "an ISO date"),
    (re.compile(r"\bsessions?\b", re.I), "the word 'session'"),
    (re.compile(r"\bissues?\s*#\s*\d*", re.I), "an issue reference"),
    (re.compile(r"\bissues?\s+\d+\b", re.I), "an issue reference"),
    (re.compile(r"\bissue's\b", re.I), "an issue reference"),
    (re.compile(r"\b(another|this|that|the other|a slower|a faster) machine\b", re.I), "a remark about machines"),
    (re.compile(r"\b(on|in) (slower|faster|other) days\b|\bthe same day\b|\bearlier that day\b", re.I), "a remark about days"),
    (re.compile(r"\bearlier (attempts?|runs?)\b|\bthe run before\b", re.I), "a comparison with earlier runs"),
]


def test_diary_patterns():
    def hits(line):
        return [why for rx, why in DIARY if rx.search(line)]

    assert hits("the code of 6d4532d gives") and hits("at b1ba6c1 (125 s)")
    assert hits("on 2026-11-25") and hits("in this session's machine") and hits("see issue #12")
    assert hits("at the issue's size") and hits("on another machine of this kind")
    # legitimate content does not trip them
    for ok in ("a log density of 1758313.149206", "4 chains × 1000 draws after 1000 warm-up",
               "IEEE Trans. Rehab. Eng. 1995", "ν_n = ν + (n − 1)(ν − 4)", "9·10⁹ RK4 steps",
               "the value at 974 462", "`bench_fit_screen` section"):
        assert not hits(ok), ok


@pytest.mark.parametrize("path", doc_files(), ids=rel)
def test_no_development_diary(path: Path):
    problems = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        for rx, why in DIARY:
            m = rx.search(line)
            if m:
                problems.append(f"line {n}: {why}: {m.group(0)!r}")
    assert not problems, (
        f"{rel(path)} reads as a development diary (state results as facts with the command that "
        "regenerates them):\n  " + "\n  ".join(problems)
    )


# ---------------------------------------------------------------------------- examples use the public API

PRIVATE_IMPORT = [
    re.compile(r"\bquadshank(\.\w+)*\._"),  # quadshank._fit, quadshank.inference._nuts, quadshank._x.y
    re.compile(r"^\s*from\s+quadshank[\w.]*\s+import\s+(\([^)]*\)|[^\n]*)", re.M),  # checked for _names below
]


def private_uses(code: str) -> list[str]:
    found = [m.group(0) for m in PRIVATE_IMPORT[0].finditer(code)]
    for m in PRIVATE_IMPORT[1].finditer(code):
        names = re.findall(r"\b(\w+)(?:\s+as\s+\w+)?", m.group(1).strip("()"))
        found += [f"from … import {n}" for n in names if n.startswith("_") and n != "as"]
    for alias in re.findall(r"^\s*import\s+quadshank\s+as\s+(\w+)", code, re.M):
        found += [m.group(0) for m in re.finditer(rf"\b{alias}\._\w*", code)]
    return found


def public_names() -> set[str] | None:
    """``quadshank.__all__`` read from the source, or None where it is not a literal list."""
    init = ROOT / "src" / "quadshank" / "__init__.py"
    for node in ast.parse(init.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            try:
                return set(ast.literal_eval(node.value))
            except ValueError:
                return None
    return None


def test_private_use_detection():
    assert private_uses("from quadshank._fit import fit")
    assert private_uses("import quadshank.inference._nuts")
    assert private_uses("from quadshank import fit, _helper")
    assert private_uses("import quadshank as qs\nqs._pipeline.run()")
    assert not private_uses("import quadshank as qs\nqs.fit(cohort, model)\nfrom quadshank import Effect, Param")


@pytest.mark.parametrize("path", doc_files(), ids=rel)
def test_python_examples_use_public_names(path: Path):
    blocks = code_blocks(path.read_text(encoding="utf-8"))
    problems = [u for code in blocks for u in private_uses(code)]
    assert not problems, f"{rel(path)}: Python examples reach past the public API: {problems}"


def test_readme_quickstart_names_are_exported():
    blocks = code_blocks(README.read_text(encoding="utf-8"))
    assert blocks, "README.md has no Python example"
    exported = public_names()
    if exported is None:
        pytest.skip("quadshank.__all__ is not a literal list")
    used = set()
    for code in blocks:
        for alias in re.findall(r"^\s*import\s+quadshank\s+as\s+(\w+)", code, re.M):
            used |= set(re.findall(rf"\b{alias}\.(\w+)", code))
        for m in PRIVATE_IMPORT[1].finditer(code):
            used |= {n for n in re.findall(r"\b(\w+)(?:\s+as\s+\w+)?", m.group(1).strip("()")) if n != "as"}
    missing = sorted(used - exported)
    assert not missing, f"README.md uses names that quadshank does not export: {missing}"


def test_every_benchmark_section_is_listed_with_its_command():
    """Each section of results/benchmarks.md is named in docs/benchmarks.md's table, and each
    benchmark script there is one that exists."""
    results = (ROOT / "results" / "benchmarks.md").read_text()
    listed = (DOCS / "benchmarks.md").read_text()
    sections = re.findall(r"<!-- (\S+):begin -->", results)
    assert sections, "results/benchmarks.md holds no section"
    assert [s for s in sections if f"| `{s}` |" not in listed] == []
    scripts = set(re.findall(r"python (benchmarks/\S+\.py)", listed))
    assert scripts and [s for s in sorted(scripts) if not (ROOT / s).is_file()] == []
