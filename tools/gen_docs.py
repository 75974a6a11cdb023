"""Generate the reference pages of the user guide from the code: docs/cli.md and docs/config.md.

    python tools/gen_docs.py            write both files
    python tools/gen_docs.py --check    exit 1 (naming the stale files) when a committed file differs

* ``docs/cli.md``: every (sub)command of the ``guidedmatch`` argument parser -- found through
  ``guidedmatch.cli.build_parser()`` (or another public parser factory of ``guidedmatch.cli``, module or package) --
  with its description, positional arguments, options (metavar, choices, default, help) and examples (epilog).
  Rendered from the parser's actions, not from ``format_help()``, so the page does not depend on the terminal width
  or on the Python version's argparse layout.
* ``docs/config.md``: every frozen dataclass named ``*Config`` under ``src/guidedmatch`` (benchmarks and test helpers
  excluded), read with ``ast`` from the source: each field's type, default (as written) and its one-line comment
  (plus the comment lines continuing it), and the class docstring's first paragraph.

``tests/test_docs.py`` regenerates both in memory and compares them with the committed files, so after a change to
the CLI or a config class, rerun this script.
"""
from __future__ import annotations

import argparse
import ast
import importlib
import io
import re
import tokenize
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
PKG = SRC / "guidedmatch"
CLI_MD = ROOT / "docs" / "cli.md"
CONFIG_MD = ROOT / "docs" / "config.md"
#: parser factories tried in this order on ``guidedmatch.cli``
PARSER_FACTORIES = ("build_parser", "make_parser", "get_parser", "create_parser", "parser")
#: config classes shown first, in the order a user meets them; any other ``*Config`` dataclass follows by name
CONFIG_ORDER = ("MatcherConfig", "VerdictConfig", "PreparedConfig", "SpatialOrderConfig", "CollectionConfig",
                "SfmConfig")
#: source folders that hold no user-facing configuration
CONFIG_SKIP_DIRS = ("evaluation", "testing")
#: the docs cite no issue tracker or work-session numbers; a source comment that still does is cited without them
_TRACKER_REFS = (re.compile(r"\s*\(\s*(?:issues?|sessions?)\s*#?\d+\s*\)", re.I),   # " (issue 11)"
                 re.compile(r",\s*(?:issues?|sessions?)\s*#?\d+", re.I),              # ", issue 11"
                 re.compile(r"\b(?:issues?|sessions?)\s*#?\d+[,;:]?\s*", re.I))        # "issue 11; ..."


def _strip_refs(text: str) -> str:
    """``text`` without issue / session citations (the docs describe the code, not its history); layout kept."""
    for pattern in _TRACKER_REFS:
        text = pattern.sub("", text)
    return text


def _clean(text: str) -> str:
    """:func:`_strip_refs`, runs of blanks collapsed (for one-line table cells and paragraphs)."""
    return re.sub(r"[ \t]{2,}", " ", _strip_refs(text)).strip()


def _rst_to_md(text: str) -> str:
    """Docstring markup to Markdown: ``:func:`~a.b``` -> `` `b` ``, double back-quotes -> single."""
    text = re.sub(r":\w+:`~[\w.]*?(\w+)`", r"`\1`", text)
    text = re.sub(r":\w+:`([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def _md_cell(text: str) -> str:
    return _clean(text).replace("|", "\\|").replace("\n", " ")


# ------------------------------------------------------------------------------------------------------------ CLI
def _use_src() -> None:
    if str(SRC) not in sys.path:
        sys.path.insert(0, str(SRC))


def _parser_from(module) -> argparse.ArgumentParser | None:
    for name in PARSER_FACTORIES:
        obj = getattr(module, name, None)
        if isinstance(obj, argparse.ArgumentParser):
            return obj
        if callable(obj) and not isinstance(obj, type):
            parser = obj()
            if isinstance(parser, argparse.ArgumentParser):
                return parser
    return None


def find_parser() -> argparse.ArgumentParser:
    """The ``guidedmatch`` argument parser: the first public factory of ``guidedmatch.cli`` (a module or a package),
    else of one of the package's modules (a ``cli/`` package that does not re-export it)."""
    import pkgutil

    _use_src()
    cli = importlib.import_module("guidedmatch.cli")
    parser = _parser_from(cli)
    for info in ([] if parser is not None else pkgutil.iter_modules(getattr(cli, "__path__", []))):
        parser = _parser_from(importlib.import_module(f"guidedmatch.cli.{info.name}"))
        if parser is not None:
            break
    if parser is None:
        raise SystemExit(f"guidedmatch.cli has none of {', '.join(PARSER_FACTORIES)} returning an ArgumentParser")
    return parser


def _subcommands(parser: argparse.ArgumentParser):
    """(name, help, subparser) of each subcommand, in the order they were added (aliases skipped)."""
    for action in parser._actions:  # noqa: SLF001 - argparse keeps its actions here, stable since Python 2.7
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            helps = {a.dest: a.help for a in action._choices_actions}  # noqa: SLF001
            seen = set()
            for name, sub in action.choices.items():
                if id(sub) in seen:
                    continue
                seen.add(id(sub))
                yield name, helps.get(name), sub


def _help_text(action: argparse.Action, prog: str) -> str:
    if not action.help or action.help == argparse.SUPPRESS:
        return ""
    params = dict(vars(action), prog=prog)
    for k, v in list(params.items()):
        if isinstance(v, (list, tuple)):
            params[k] = ", ".join(map(str, v))
    try:
        return action.help % params
    except (KeyError, TypeError, ValueError):
        return action.help


def _metavar(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.metavar is not None:
        mv = action.metavar if isinstance(action.metavar, str) else " ".join(action.metavar)
    elif action.choices is not None:
        mv = "{" + ",".join(map(str, action.choices)) + "}"
    else:
        mv = action.dest.upper() if action.option_strings else action.dest
    if action.nargs in ("*",):
        return f"[{mv} ...]"
    if action.nargs == "+":
        return f"{mv} [{mv} ...]"
    if action.nargs == "?":
        return f"[{mv}]"
    return mv


def _default(action: argparse.Action) -> str:
    d = action.default
    if action.nargs == 0 or d is None or d is argparse.SUPPRESS or isinstance(action, argparse._VersionAction):  # noqa: SLF001
        return ""
    if isinstance(d, tuple) and len(d) == 2 and all(isinstance(v, int) for v in d):
        return f"{d[0]}x{d[1]}"
    return str(d)


def _usage(name: str, sub: argparse.ArgumentParser) -> str:
    parts = [f"guidedmatch {name}".strip()]
    for a in sub._actions:  # noqa: SLF001
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):  # noqa: SLF001
            continue
        if not a.option_strings:
            parts.append(_metavar(a))
    return " ".join(parts) + " [options]"


def _command_section(name: str, short: str | None, sub: argparse.ArgumentParser, level: int) -> list[str]:
    out = [f"{'#' * level} `guidedmatch {name}`", ""]
    if short:
        out += [_clean(short[0].upper() + short[1:]) + ".", ""]
    out += ["```", _usage(name, sub), "```", ""]
    if sub.description and sub.description != short:
        out += [_clean(sub.description), ""]
    pos = [a for a in sub._actions if not a.option_strings and not isinstance(a, argparse._SubParsersAction)]  # noqa: SLF001
    opts = [a for a in sub._actions if a.option_strings and not isinstance(a, argparse._HelpAction)]  # noqa: SLF001
    if pos:
        out += ["| argument | meaning |", "|---|---|"]
        for a in pos:
            choices = f" (one of: {', '.join(f'`{c}`' for c in a.choices)})" if a.choices else ""
            out.append(f"| `{_metavar(a)}` | {_md_cell(_help_text(a, name))}{choices} |")
        out.append("")
    if opts:
        out += ["| option | default | meaning |", "|---|---|---|"]
        for a in opts:
            flag = ", ".join(a.option_strings)
            mv = _metavar(a)
            d = _default(a)
            out.append(f"| `{flag}{' ' + mv if mv else ''}` | {f'`{d}`' if d else ''} | {_md_cell(_help_text(a, name))} |")
        out.append("")
    if sub.epilog:
        out += ["```", _strip_refs(sub.epilog).strip("\n"), "```", ""]
    for child, child_help, child_sub in _subcommands(sub):
        out += _command_section(f"{name} {child}", child_help, child_sub, level + 1)
    return out


def cli_markdown(parser: argparse.ArgumentParser | None = None) -> str:
    parser = parser or find_parser()
    subs = list(_subcommands(parser))
    out = ["# Command-line reference", "",
           "<!-- generated by tools/gen_docs.py from the argument parser of guidedmatch.cli; do not edit by hand -->",
           "",
           "Every command also prints this with `--help`. Exit status: 0 done, 2 bad input or options (one line "
           "naming the file or option, before any work), 1 an internal error (`--debug` shows the traceback), "
           "130 interrupted.", "",
           "```", "guidedmatch [--debug] COMMAND ...", "```", ""]
    top = [a for a in parser._actions if a.option_strings and not isinstance(a, argparse._HelpAction)]  # noqa: SLF001
    if top:
        out += ["| option | meaning |", "|---|---|"]
        out += [f"| `{', '.join(a.option_strings)}` | {_md_cell(_help_text(a, 'guidedmatch'))} |" for a in top]
        out.append("")
    out += ["| command | what it does |", "|---|---|"]
    out += [f"| [`{n}`](#guidedmatch-{n}) | {_md_cell(h or '')} |" for n, h, _ in subs]
    out.append("")
    for name, short, sub in subs:
        out += _command_section(name, short, sub, 2)
    return "\n".join(out).rstrip() + "\n"


# --------------------------------------------------------------------------------------------------------- config
def _is_dataclass(node: ast.ClassDef) -> bool:
    for d in node.decorator_list:
        target = d.func if isinstance(d, ast.Call) else d
        if (isinstance(target, ast.Name) and target.id == "dataclass") or \
                (isinstance(target, ast.Attribute) and target.attr == "dataclass"):
            return True
    return False


def _comments(src: str) -> dict[int, str]:
    """Line number -> text of the ``#`` comment on that line (tokenize: a ``#`` inside a string is no comment)."""
    out = {}
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            out[tok.start[0]] = tok.string.lstrip("#").strip()
    return out


def _comment(lines: list[str], comments: dict[int, str], stmt: ast.AST, next_lineno: int) -> str:
    """The comment ending the field's line(s) plus comment-only lines that continue it before the next field."""
    parts = [comments[ln] for ln in range(stmt.lineno, stmt.end_lineno + 1) if ln in comments]
    ln = stmt.end_lineno + 1
    while ln < next_lineno and lines[ln - 1].strip().startswith("#"):
        parts.append(comments.get(ln, ""))
        ln += 1
    return " ".join(p for p in parts if p)


def _default_text(src: str, node: ast.AST | None) -> str:
    if node is None:
        return "(required)"
    text = ast.get_source_segment(src, node) or ""
    m = re.fullmatch(r"field\((?:default_factory=)?(?:lambda: )?(.*)\)", text, re.S)
    if m and "default_factory" in text:
        return m.group(1).strip() if "lambda" in text else m.group(1).strip() + "()"
    return re.sub(r"\s+", " ", text)


def config_classes() -> list[dict]:
    """Every ``*Config`` dataclass under ``src/guidedmatch`` (see the module doc), fields read from the source."""
    found = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG)
        if rel.parts[0] in CONFIG_SKIP_DIRS:
            continue
        src = path.read_text()
        tree = ast.parse(src)
        lines = src.splitlines()
        comments = _comments(src)
        for node in tree.body:
            if not (isinstance(node, ast.ClassDef) and node.name.endswith("Config") and _is_dataclass(node)):
                continue
            stmts = [s for s in node.body if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)]
            fields = []
            for i, s in enumerate(stmts):
                nxt = stmts[i + 1].lineno if i + 1 < len(stmts) else node.end_lineno + 1
                later = [b.lineno for b in node.body if b.lineno > s.end_lineno]
                nxt = min([nxt] + later)
                fields.append(dict(name=s.target.id, type=ast.get_source_segment(src, s.annotation),
                                   default=_default_text(src, s.value), comment=_comment(lines, comments, s, nxt)))
            doc = _rst_to_md((ast.get_docstring(node) or "").split("\n\n")[0].replace("\n", " "))
            module = ".".join(("guidedmatch",) + rel.with_suffix("").parts).removesuffix(".__init__")
            found.append(dict(name=node.name, module=module, doc=doc, fields=fields))
    rank = {n: i for i, n in enumerate(CONFIG_ORDER)}
    return sorted(found, key=lambda c: (rank.get(c["name"], len(rank)), c["name"]))


def config_markdown(classes: list[dict] | None = None) -> str:
    classes = config_classes() if classes is None else classes
    _use_src()
    public = set(getattr(importlib.import_module("guidedmatch"), "__all__", ()))
    out = ["# Configuration reference", "",
           "<!-- generated by tools/gen_docs.py from the config dataclasses' source; do not edit by hand -->", "",
           "Every setting is a field of a small frozen dataclass, checked when it is constructed (a bad value raises "
           "`gm.ConfigError` naming the field, the accepted values and the value received). Pass an instance or a "
           "dict of fields:", "",
           "```python",
           "import guidedmatch as gm",
           "",
           "cfg = gm.MatcherConfig(band_px=3.0, mutual=True)         # or gm.match(f1, f2, config={\"band_px\": 3.0})",
           "cfg = gm.MatcherConfig.paper()                            # the paper's settings (no additions)",
           "gm.CollectionConfig(workers=0, matcher={\"max_unguided\": 0.005})",
           "```", "",
           "On the command line, `--config KEY=VALUE` (repeatable) sets a `MatcherConfig` field in `guidedmatch "
           "match`, `colmap`, `hloc` and `sfm`; the other commands' options map onto the fields below "
           "([cli.md](cli.md)).", ""]
    out += ["| class | import | what it configures |", "|---|---|---|"]
    for c in classes:
        imp = f"gm.{c['name']}" if c["name"] in public else f"{c['module']}.{c['name']}"
        out.append(f"| [`{c['name']}`](#{c['name'].lower()}) | `{imp}` | {_md_cell(c['doc'])} |")
    out.append("")
    for c in classes:
        out += [f"## {c['name']}", "", f"`{c['module']}.{c['name']}`: {_clean(c['doc'])}", "",
                "| field | type | default | meaning |", "|---|---|---|---|"]
        for f in c["fields"]:
            out.append(f"| `{f['name']}` | `{_md_cell(f['type'])}` | `{_md_cell(f['default'])}` | {_md_cell(f['comment'])} |")
        out.append("")
    return "\n".join(out).rstrip() + "\n"


# ------------------------------------------------------------------------------------------------------------ main
def generated() -> dict[Path, str]:
    """The generated pages: path -> text."""
    return {CLI_MD: cli_markdown(), CONFIG_MD: config_markdown()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare with the committed files instead of writing")
    args = ap.parse_args(argv)
    stale = []
    for path, text in generated().items():
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(path.relative_to(ROOT))
        else:
            path.write_text(text)
            print(f"wrote {path.relative_to(ROOT)}")
    if stale:
        print("stale (run python tools/gen_docs.py): " + ", ".join(map(str, stale)), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
