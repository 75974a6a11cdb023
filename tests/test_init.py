"""The public namespace (src/guidedmatch/__init__.py): ``import guidedmatch as gm``."""
import ast
import subprocess
import sys
from pathlib import Path

import guidedmatch as gm

SRC = Path(__file__).resolve().parents[1] / "src" / "guidedmatch"
API = ["detect", "Features", "match", "MatcherConfig", "MatchResult", "MatchStats", "match_bruteforce",
       "estimate_fundamental", "fit_spatial_order", "align_from_fundamental", "two_view_geometry", "TwoViewGeometry",
       "GuidedMatchError", "ConfigError", "InputError", "ImageReadError", "MODES", "Mode"]


def test_the_api_is_one_namespace():
    for name in gm.__all__:  # every listed name resolves
        getattr(gm, name)
    for name in API:
        assert name in gm.__all__ and name in dir(gm), name
        assert getattr(gm, name) is not None
    from guidedmatch.features import detect
    from guidedmatch.matcher import match

    assert gm.detect is detect and gm.match is match
    assert issubclass(gm.ConfigError, gm.GuidedMatchError) and issubclass(gm.GuidedMatchError, ValueError)


def test_unknown_attribute_is_an_attribute_error():
    import pytest

    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        gm.nope  # noqa: B018


def test_import_is_cheap():
    code = ("import sys, guidedmatch as gm; "
            "print(sorted(m for m in ('numpy', 'cv2', 'numba', 'scipy') if m in sys.modules)); gm.detect; gm.match")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(SRC.parent)}).stdout
    assert out.strip() == "[]"


def test_no_module_imports_the_cli():
    """Only the console-script entry point runs the CLI; evaluation/ and the library take plain arguments."""
    for path in SRC.rglob("*.py"):
        if path.name == "cli.py" or path.parent.name == "cli":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [a.name for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            assert not any(n == "cli" or n.endswith(".cli") for n in names), f"{path} imports the CLI"
