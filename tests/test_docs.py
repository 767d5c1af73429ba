"""The user docs: no lab-notebook residue (issue numbers, commit hashes, dates, probe sections), a current
command-line reference, every documented command parses, and the README's quick start runs as written."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from cv2x_marl.cli import COMMANDS, build_parser
from cv2x_marl.cli.reference import api, reference

ROOT = Path(__file__).resolve().parents[1]
#: the pages a user reads: the README and docs/ (the research log, docs/research/, is apart; CHANGELOG is history)
USER_PAGES = sorted(
    [ROOT / "README.md", *(p for p in (ROOT / "docs").rglob("*.md") if "research" not in p.relative_to(ROOT).parts)]
)
RESIDUE = {
    "an issue number": re.compile(r"(?i)\bissues?\s*#?\d+"),
    "a commit hash": re.compile(r"\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b"),
    "a date": re.compile(r"\b20\d\d-\d\d-\d\d\b"),
    "a probe section": re.compile(r"(?im)^#+ .*\bprobes?\b"),
}


def _name(p: Path) -> str:
    return str(p.relative_to(ROOT))


@pytest.mark.parametrize("page", USER_PAGES, ids=_name)
def test_user_pages_carry_no_lab_notebook_residue(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    found = [f"{what}: {m.group(0)!r}" for what, rx in RESIDUE.items() for m in rx.finditer(text)]
    assert found == [], f"{_name(page)} (move it to docs/research/ or the CHANGELOG)"


def test_the_residue_patterns_catch_what_they_name() -> None:
    assert RESIDUE["an issue number"].search("as issue 27 asked")
    assert RESIDUE["a commit hash"].search("commit 87150fb on the 2-core machine")
    assert not RESIDUE["a commit hash"].search("a deadline of 1000000 subframes")
    assert RESIDUE["a date"].search("measured 2026-11-02")
    assert RESIDUE["a probe section"].search("## Probe: the residual")


def test_the_command_line_reference_is_current() -> None:
    page = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert page == reference(), "regenerate with: python -m cv2x_marl.cli.reference > docs/cli.md"


def test_the_api_reference_is_current() -> None:
    page = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    assert page == api(), "regenerate with: python -m cv2x_marl.cli.reference api > docs/api.md"


def _commands(text: str) -> list[str]:
    """The ``cv2x-marl ...`` command lines of the fenced shell blocks (continuations joined, comments cut)."""
    out = []
    for block in re.findall(r"```(?:bash|sh|shell)\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #", 1)[0].strip()
            m = re.match(r"^(?:\S*/)?cv2x-marl\s+(.*)$", line)
            if m:
                out.append(m.group(1))
    return out


DOC_COMMANDS = [(p, c) for p in USER_PAGES for c in _commands(p.read_text(encoding="utf-8"))]


def test_the_docs_show_commands() -> None:
    assert len(DOC_COMMANDS) >= 20
    assert {shlex.split(c)[0] for _, c in DOC_COMMANDS} >= {"simulate", "evaluate", "benchmark", "train"}


@pytest.mark.parametrize(("page", "command"), DOC_COMMANDS, ids=[f"{_name(p)}: {c[:60]}" for p, c in DOC_COMMANDS])
def test_every_documented_command_parses(page: Path, command: str) -> None:
    argv = shlex.split(re.sub(r"\$\{?\w+\}?", "0", command))  # a loop's shell variable: a sample value
    assert argv[0] in COMMANDS, f"{_name(page)}: unknown command {argv[0]!r}"
    try:
        build_parser(only=argv[0]).parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{_name(page)}: `cv2x-marl {command}` does not parse (exit {exc.code})")


def _inline_commands(text: str) -> list[str]:
    """The inline ``cv2x-marl COMMAND ...`` code spans of a page (prose that names a command and its flags)."""
    names = "|".join(COMMANDS)
    rx = r"`(?:\S*/)?cv2x-marl ((?:" + names + r")\b[^`]*)`"
    return [" ".join(m.group(1).split()) for m in re.finditer(rx, text)]


INLINE = [(p, c) for p in USER_PAGES for c in _inline_commands(p.read_text(encoding="utf-8"))]


def _flags(command: str) -> set[str]:
    """Every option string of ``command``'s parser (its subcommands' too)."""
    parser = build_parser(only=command)
    sub = next(a for a in parser._actions if a.dest == "command")
    flags: set[str] = set()
    stack = [sub.choices[command]]  # type: ignore[attr-defined]
    while stack:
        p = stack.pop()
        for action in p._actions:
            flags.update(action.option_strings)
            if getattr(action, "choices", None) and isinstance(action.choices, dict):
                stack.extend(action.choices.values())
    return flags


@pytest.mark.parametrize(("page", "command"), INLINE, ids=[f"{_name(p)}: {c[:60]}" for p, c in INLINE])
def test_every_inline_command_names_real_flags(page: Path, command: str) -> None:
    """Prose names commands with placeholders (``--seed S``): their command and every flag must exist."""
    argv = command.split()
    used = {a.split("=", 1)[0].strip("[]") for a in argv if a.lstrip("[").startswith("--")}
    unknown = sorted(used - _flags(argv[0]))
    assert unknown == [], f"{_name(page)}: `cv2x-marl {command}` names unknown flags {unknown}"


def test_the_readme_quick_start_runs_as_written(capsys: pytest.CaptureFixture[str]) -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    quick = readme.split("## Quick start", 1)[1]
    code = re.findall(r"```python\n(.*?)```", quick, flags=re.S)[0]
    exec(compile(code, "README.md (Quick start)", "exec"), {})
    out = capsys.readouterr().out
    assert re.fullmatch(r"utility gain of a random mover: [+-]\d+\.\d\d\n", out), out


def test_the_getting_started_first_env_runs_as_written(capsys: pytest.CaptureFixture[str]) -> None:
    page = (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    section = page.split("## The first env", 1)[1]
    code = re.findall(r"```python\n(.*?)```", section, flags=re.S)[0]
    exec(compile(code, "docs/getting-started.md (The first env)", "exec"), {})
    assert capsys.readouterr().out.splitlines()[0] == "(351,)"


def test_the_policy_guide_runs_as_written(capsys: pytest.CaptureFixture[str]) -> None:
    page = (ROOT / "docs" / "policies.md").read_text(encoding="utf-8")
    section = page.split("## A scripted mover from the observation", 1)[1]
    code = re.findall(r"```python\n(.*?)```", section, flags=re.S)[0]
    exec(compile(code, "docs/policies.md (A scripted mover)", "exec"), {})
    out = capsys.readouterr().out
    assert re.fullmatch(r"mean utility gain over 2 episodes: [+-]\d+\.\d%\n", out), out
