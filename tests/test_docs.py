"""The documentation cites only what the repository has, and the README stays short.

Every path that README.md, docs/*.md or benchmarks/README.md cite (in backticks or as a
link) and that looks like a repository file must exist; every module, class or function
cited as ``geoidspline.a.b[.name]`` must be defined where it says.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), REPO / "benchmarks" / "README.md"]
README_MAX_LINES = 250

#: First components of repository paths, and files at the repository root.
TOP_DIRS = ("geoidspline", "cli", "grids", "tests", "benchmarks", "docs", ".ci")
#: Written by the benchmarks into the checkout (ignored by git), cited as their outputs.
GENERATED = ("benchmarks/out/",)
#: Installed names that live elsewhere in the checkout (pyproject's package-dir).
PACKAGE_DIRS = {"geoidspline.cli": REPO / "cli", "geoidspline.grids": REPO / "grids", "geoidspline": REPO / "geoidspline"}

_CODE = re.compile(r"(`+)(.+?)\1", re.S)
_LINK = re.compile(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_PATH = re.compile(r"(?<![\w/.~$-])((?:%s)/[\w./*-]*[\w*])" % "|".join(re.escape(d) for d in TOP_DIRS))
_ROOT_FILE = re.compile(r"(?<![\w/.~$-])(Dockerfile|\.dockerignore|pyproject\.toml|requirements\.lock"
                        r"|[A-Za-z][\w-]*\.md)(?![\w/])")
_MODULE = re.compile(r"(?<![\w./])(geoidspline(?:\.\w+)+)")


def cited_paths(doc: Path):
    """(path as written, the file it must be) for every repository path ``doc`` cites."""
    text = doc.read_text(encoding="utf-8")
    # fenced blocks are commands and output, not citations: only their benchmarks/tests scripts count
    for match in _CODE.finditer(text):
        span = match.group(2)
        for path in _PATH.findall(span):
            yield path, [REPO / path]
        for name in _ROOT_FILE.findall(span):
            yield name, [REPO / name, doc.parent / name]
    for target in _LINK.findall(text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        target = target.split("#", 1)[0]
        yield target, [(doc.parent / target).resolve()]


def cited_names(doc: Path):
    text = doc.read_text(encoding="utf-8")
    for match in _CODE.finditer(text):
        yield from _MODULE.findall(match.group(2))


def _exists(candidate: Path) -> bool:
    if "*" in str(candidate):  # a pattern such as tests/test_*.py: something must match it
        return any(REPO.glob(str(candidate.relative_to(REPO))))
    return candidate.exists()


def _module_file(dotted: str):
    """The file defining the longest module prefix of ``dotted``, and the names after it."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        prefix = ".".join(parts[:n])
        base_name = max((k for k in PACKAGE_DIRS if prefix == k or prefix.startswith(k + ".")), key=len,
                        default=None)
        if base_name is None:
            continue
        rest = prefix[len(base_name):].lstrip(".")
        base = PACKAGE_DIRS[base_name].joinpath(*rest.split(".")) if rest else PACKAGE_DIRS[base_name]
        if base.is_dir() and (base / "__init__.py").is_file():
            return base / "__init__.py", parts[n:]
        if base.with_suffix(".py").is_file():
            return base.with_suffix(".py"), parts[n:]
    return None, parts


def _defines(source: str, name: str) -> bool:
    return re.search(rf"^\s*(?:def|class)\s+{re.escape(name)}\b|^\s*{re.escape(name)}\s*[:=]|"
                     rf"^\s*(?:from\s+\S+\s+)?import\s+.*\b{re.escape(name)}\b|\"{re.escape(name)}\"",
                     source, flags=re.M) is not None


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_cited_paths_exist(doc):
    missing = sorted({written for written, candidates in cited_paths(doc)
                      if not (written + "/").startswith(GENERATED) and not any(_exists(c) for c in candidates)})
    assert not missing, f"{doc.relative_to(REPO)} cites paths the repository lacks: {missing}"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_cited_modules_and_names_exist(doc):
    missing = []
    for dotted in sorted(set(cited_names(doc))):
        path, names = _module_file(dotted)
        if path is None:
            missing.append(dotted)
            continue
        # the first name after the module must be defined in it (attributes of a class are not checked)
        if names and not _defines(path.read_text(encoding="utf-8"), names[0]):
            missing.append(dotted)
    assert not missing, f"{doc.relative_to(REPO)} cites modules or names that do not exist: {missing}"


def test_readme_is_short():
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines, at most {README_MAX_LINES}"


def test_the_checker_catches_what_the_issue_found(tmp_path):
    """The dead references of issue 20 are caught, a real one is not."""
    doc = tmp_path / "x.md"
    doc.write_text("see `geoidspline/interpolation.py`, `METHOD.md`, [arch](docs/NOPE.md), "
                   "`benchmarks/spline.py`, `geoidspline.spline.evaluate`, `geoidspline.store.codec.nothing_here`; "
                   "real: `geoidspline/store/codec.py`, `geoidspline.store.codec.encode_tile`, `tests/test_*.py`\n")
    paths = {written for written, candidates in cited_paths(doc) if not any(_exists(c) for c in candidates)}
    assert paths == {"geoidspline/interpolation.py", "METHOD.md", "docs/NOPE.md", "benchmarks/spline.py"}
    bad = set()
    for dotted in cited_names(doc):
        path, names = _module_file(dotted)
        if path is None or (names and not _defines(path.read_text(encoding="utf-8"), names[0])):
            bad.add(dotted)
    assert bad == {"geoidspline.spline.evaluate", "geoidspline.store.codec.nothing_here"}


def test_readme_quick_start_writes_outside_the_checkout():
    text = (REPO / "README.md").read_text(encoding="utf-8").split("\n## ", 1)[0]
    stores = re.findall(r"--store\s+(\S+)", text)
    assert stores, "the quick start names no store"
    for store in stores:
        assert store.startswith(("/", "~", "$HOME")), f"the quick start writes its store into the checkout: {store}"
