"""The user guide: generated reference pages up to date, every relative link resolves, no tracker numbers."""
import argparse
import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", ROOT / "CHANGELOG.md", *(ROOT / "docs").glob("*.md")])
HISTORY = sorted((ROOT / "benchmarks" / "results").rglob("history.md"))


def _gen_docs():
    spec = importlib.util.spec_from_file_location("gen_docs", ROOT / "tools" / "gen_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("name", ["cli.md", "config.md"])
def test_generated_reference_pages_are_up_to_date(name):
    gen = _gen_docs()
    text = gen.generated()[ROOT / "docs" / name]
    committed = (ROOT / "docs" / name).read_text()
    assert committed == text, f"docs/{name} is stale: run python tools/gen_docs.py"


def test_cli_reference_lists_every_subcommand_and_option():
    gen = _gen_docs()
    parser = gen.find_parser()
    text = (ROOT / "docs" / "cli.md").read_text()
    subs = list(gen._subcommands(parser))
    assert len(subs) >= 5
    for name, _, sub in subs:
        assert f"## `guidedmatch {name}`" in text
        for action in sub._actions:
            for flag in action.option_strings:
                if flag not in ("-h", "--help"):
                    assert f"`{flag}" in text or f", {flag}" in text, (name, flag)


def test_cli_reference_renders_a_made_up_parser():
    """The renderer itself, on a parser whose every part is known (nested commands, choices, defaults, epilog)."""
    gen = _gen_docs()
    p = argparse.ArgumentParser(prog="guidedmatch")
    sub = p.add_subparsers(dest="command")
    a = sub.add_parser("alpha", help="do alpha", description="Alpha in detail.", epilog="example:\n  guidedmatch alpha x    # (issue 3) aligned")
    a.add_argument("thing", help="what to alpha")
    a.add_argument("--level", type=int, default=3, help="how much (default %(default)s)")
    a.add_argument("--kind", choices=("x", "y"), default="x")
    a.add_argument("--flag", action="store_true", help="a | pipe")
    nested = a.add_subparsers(dest="inner").add_parser("beta", help="inner beta")
    nested.add_argument("--n", metavar="N", help="count")
    md = gen.cli_markdown(p)
    assert "[`alpha`](#guidedmatch-alpha) | do alpha |" in md
    assert "guidedmatch alpha thing [options]" in md
    assert "| `--level LEVEL` | `3` | how much (default 3) |" in md
    assert "| `--kind {x,y}` | `x` |" in md
    assert "| `--flag` |  | a \\| pipe |" in md  # a flag has no default shown; pipes escaped for the table
    assert "  guidedmatch alpha x    # aligned" in md and "Alpha in detail." in md  # layout kept, no tracker refs
    assert "### `guidedmatch alpha beta`" in md and "| `--n N` |  | count |" in md


def test_config_reference_reads_fields_comments_and_continuations(tmp_path, monkeypatch):
    gen = _gen_docs()
    pkg = tmp_path / "guidedmatch"
    (pkg / "evaluation").mkdir(parents=True)
    (pkg / "thing.py").write_text(
        "from dataclasses import dataclass, field\n\n\n"
        "@dataclass(frozen=True)\nclass ThingConfig:\n"
        '    """How things go.\n\n    More detail.\n    """\n\n'
        "    size: int = 4        # how big, px\n"
        "    mode: str = \"a#b\"    # the mode (beyond the paper, issue 7);\n"
        "                         # continued on a second line\n"
        "    extra: list = field(default_factory=list)  # a list\n\n"
        "    def __post_init__(self):\n        pass\n\n\n"
        "class NotAConfig:\n    x: int = 1  # ignored\n")
    (pkg / "evaluation" / "bench.py").write_text(
        "from dataclasses import dataclass\n\n\n@dataclass\nclass BenchConfig:\n    x: int = 1  # skipped\n")
    monkeypatch.setattr(gen, "PKG", pkg)
    classes = gen.config_classes()
    assert [c["name"] for c in classes] == ["ThingConfig"]
    c = classes[0]
    assert c["doc"] == "How things go." and c["module"] == "guidedmatch.thing"
    assert c["fields"] == [
        dict(name="size", type="int", default="4", comment="how big, px"),
        dict(name="mode", type="str", default='"a#b"',
             comment="the mode (beyond the paper, issue 7); continued on a second line"),
        dict(name="extra", type="list", default="list()", comment="a list")]
    md = gen.config_markdown(classes)
    assert "| `mode` | `str` | `\"a#b\"` | the mode (beyond the paper); continued on a second line |" in md


def test_config_reference_covers_every_field_of_the_public_configs():
    import dataclasses

    import guidedmatch as gm

    text = (ROOT / "docs" / "config.md").read_text()
    for cls in (gm.MatcherConfig, gm.VerdictConfig, gm.CollectionConfig, gm.PreparedConfig, gm.SpatialOrderConfig):
        assert f"## {cls.__name__}" in text
        section = text.split(f"## {cls.__name__}", 1)[1].split("\n## ", 1)[0]
        for f in dataclasses.fields(cls):
            row = next((ln for ln in section.splitlines() if ln.startswith(f"| `{f.name}` |")), None)
            assert row is not None, (cls.__name__, f.name)
            assert row.rstrip(" |").split("|")[-1].strip(), f"{cls.__name__}.{f.name} has no one-line comment"


# ---------------------------------------------------------------------------------------------------- links
_FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.S | re.M)
_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def _strip_code(text: str) -> str:
    text = _FENCE.sub("", text)
    return re.sub(r"`[^`\n]*`", "", text)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    h = re.sub(r"<[^>]+>", "", heading.strip().lower())
    h = re.sub(r"[^\w\- ]", "", h)
    return h.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    out, seen = set(), {}
    for line in _FENCE.sub("", path.read_text()).splitlines():
        m = re.match(r"^(#{1,6})\s+(.*?)\s*#*\s*$", line)
        if m:
            s = slug(m.group(2))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}-{n}")
    out |= set(re.findall(r'<a (?:name|id)="([^"]+)"', path.read_text()))
    return out


def links(path: Path):
    for m in _LINK.finditer(_strip_code(path.read_text())):
        target = m.group(1)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:
            continue
        yield target


def test_slug_follows_github():
    assert slug("How many inliers the mapper needs") == "how-many-inliers-the-mapper-needs"
    assert slug("`guidedmatch sfm`") == "guidedmatch-sfm"
    assert slug("Resume, failures, crash safety") == "resume-failures-crash-safety"
    assert slug("First run: Numba compilation") == "first-run-numba-compilation"


@pytest.mark.parametrize("page", PAGES + HISTORY, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    assert page.exists(), page
    bad = []
    for target in links(page):
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert not bad, "\n".join(bad)


def test_the_link_checker_sees_broken_links(tmp_path):
    (tmp_path / "a.md").write_text("# Top\n\n## Sub part\n\n[ok](#sub-part) [ok2](b.md#x) [bad](#nope) [gone](c.md)\n"
                                   "`[not a link](zzz.md)`\n```\n[nor this](yyy.md)\n```\n[web](https://x.org)\n")
    (tmp_path / "b.md").write_text("# X\n")
    assert list(links(tmp_path / "a.md")) == ["#sub-part", "b.md#x", "#nope", "c.md"]
    assert anchors(tmp_path / "a.md") == {"top", "sub-part"}


# ------------------------------------------------------------------------------------------ describe, not recount
_TRACKER = re.compile(r"session [0-9]|issue [0-9]|\(issue|sessions? [0-9]", re.I)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_user_docs_cite_no_issue_or_session_numbers(page):
    hits = [ln for ln in page.read_text().splitlines() if _TRACKER.search(ln)]
    assert not hits, "\n".join(hits)


def test_the_package_source_cites_no_issue_or_session_numbers():
    """Code, docstrings and CLI help describe what the code does now, not the tracker's history."""
    src = ROOT / "src" / "guidedmatch"
    hits = [f"{p.relative_to(ROOT)}:{i}: {ln.strip()}" for p in sorted(src.rglob("*.py"))
            for i, ln in enumerate(p.read_text().splitlines(), 1) if _TRACKER.search(ln) or "issue #" in ln.lower()]
    assert not hits, "\n".join(hits)


@pytest.mark.parametrize("page", HISTORY, ids=lambda p: str(p.relative_to(ROOT)))
def test_measurement_histories_are_organised_by_date_or_topic(page):
    headings = [ln for ln in page.read_text().splitlines() if ln.startswith("#")]
    assert headings
    assert not [h for h in headings if _TRACKER.search(h)]


def test_readme_is_short_and_answers_the_collection_question_on_the_first_screen():
    text = (ROOT / "README.md").read_text()
    assert len(text.encode()) <= 13_000
    first_screen = "\n".join(text.splitlines()[:60])
    assert "guidedmatch colmap" in first_screen and "guidedmatch sfm" in first_screen


def test_parser_is_found_in_a_cli_package_that_does_not_reexport_it(tmp_path, monkeypatch):
    """After cli.py becomes a cli/ package, the generator still finds the parser factory (in the package or in one
    of its modules)."""
    import types

    gen = _gen_docs()
    (tmp_path / "main.py").write_text("")
    pkg = types.ModuleType("guidedmatch.cli")
    pkg.__path__ = [str(tmp_path)]
    main = types.ModuleType("guidedmatch.cli.main")
    main.build_parser = lambda: argparse.ArgumentParser(prog="found")
    modules = {"guidedmatch.cli": pkg, "guidedmatch.cli.main": main}
    monkeypatch.setattr(gen.importlib, "import_module", lambda name: modules[name])
    assert gen.find_parser().prog == "found"
    del main.build_parser
    with pytest.raises(SystemExit):
        gen.find_parser()
