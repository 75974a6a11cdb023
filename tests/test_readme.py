import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _commands():
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```bash\n(.*?)\n```", text, re.S)


def test_readme_has_two_setup_commands_and_ci_runs_the_test_one():
    cmds = _commands()
    assert len(cmds) >= 2
    demo, tests = cmds[0].strip(), cmds[1].strip()
    assert demo.endswith("guidedmatch demo")
    assert "pytest" in tests
    assert tests.endswith("python -m pytest -q --doctest-modules src/guidedmatch tests")  # docstring examples run too
    ci = (ROOT / ".ci" / "run").read_text()
    assert tests in ci.splitlines(), ".ci/run must run exactly the README test command"


def _tool(name):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_links_the_benchmark_page_that_holds_the_generated_sections():
    assert "(docs/benchmarks.md)" in (ROOT / "README.md").read_text()
    page = (ROOT / "docs" / "benchmarks.md").read_text()
    for marker in ("results", "pairs", "perf", "sfm"):
        assert page.count(f"<!-- {marker}:start -->") == 1 and page.count(f"<!-- {marker}:end -->") == 1, marker
    assert _tool("readme_results").TARGET == ROOT / "docs" / "benchmarks.md"


def test_benchmark_page_sections_regenerate_from_the_committed_json():
    """tools/readme_sfm.py and tools/readme_results.py --pairs reproduce what docs/benchmarks.md holds (rerun them
    after a benchmark)."""
    import json

    page = (ROOT / "docs" / "benchmarks.md").read_text()
    sfm = _tool("readme_sfm")
    assert sfm.splice(page, sfm.section(json.loads((ROOT / "benchmarks/results/sfm/sfm.json").read_text()))) == page
    pairs = _tool("readme_results").pairs_headline(json.loads((ROOT / "benchmarks/results/pairs/pairs.json").read_text()))
    assert pairs in page
