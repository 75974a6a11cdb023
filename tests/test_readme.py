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
