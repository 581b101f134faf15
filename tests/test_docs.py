"""The documentation stays true: the site builds with no warning, and every ``fedmap`` command
shown in README.md and docs/*.md names a real command and only options it has."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import typer

import fedmap.cli
from fedmap.cli import main

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
SHELL_STOP = {">", ">>", "|", "&&", ";", "2>&1", "&"}

#: Commands shown in the docs that the option check below cannot vouch for; each is run
#: by a test instead (listed here so the list stays small and explicit).
SLOW_EXAMPLES: dict[str, str] = {}


def _commands() -> list[tuple[str, str]]:
    """``(file, command line)`` for every ``fedmap ...`` line in a shell code block and every
    inline code span that starts with ``fedmap ``."""
    found = []
    for path in DOCS:
        text = path.read_text()
        name = str(path.relative_to(ROOT))
        for lang, body in re.findall(r"^```(\w*)\n(.*?)^```", text, flags=re.S | re.M):
            if lang not in ("bash", "sh", "console", ""):
                continue
            for line in body.replace("\\\n", " ").splitlines():
                line = line.strip().removeprefix("$ ")
                if line.startswith("fedmap "):
                    found.append((name, line))
        prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
        found += [(name, m) for m in re.findall(r"`(fedmap [^`]+)`", prose)]
    return found


COMMANDS = _commands()
#: The commands that are groups of commands (their first word).
GROUPS = ("node",)


def _options() -> tuple[set[str], dict[str, set[str]]]:
    group = typer.main.get_command(fedmap.cli.app)
    opts = lambda params: {o for p in params for o in (*p.opts, *p.secondary_opts) if o.startswith("-")}
    commands = {name: opts(cmd.params) | {"--help"} for name, cmd in group.commands.items()}
    for name, cmd in group.commands.items():  # a group's commands (fedmap node rover) by their two words
        for sub, inner in getattr(cmd, "commands", {}).items():
            commands[f"{name} {sub}"] = opts(inner.params) | {"--help"}
    return opts(group.params) | {"--help"}, commands


def _parse(line: str) -> tuple[str | None, list[str]]:
    """The subcommand and the options a command line uses (shell comments and redirections dropped)."""
    tokens = []
    for tok in shlex.split(line, comments=True)[1:]:
        if tok in SHELL_STOP:
            break
        tok = tok.strip("[]")
        if tok and tok != "...":
            tokens.append(tok)
    words = [t for t in tokens if not t.startswith("-")]
    sub = words[0] if words else None
    if sub in GROUPS and len(words) > 1:  # fedmap node rover ...
        sub = f"{sub} {words[1]}"
    used = [t.split("=", 1)[0] for t in tokens if re.match(r"^--?[A-Za-z]", t)]
    return sub, used


def test_docs_show_commands():
    assert len(COMMANDS) > 40
    assert any(line.startswith("fedmap base-station") for _, line in COMMANDS)


@pytest.mark.parametrize("where,line", COMMANDS, ids=[f"{w}:{c[:60]}" for w, c in COMMANDS])
def test_every_documented_command_uses_real_options(where, line):
    if line in SLOW_EXAMPLES:
        return
    global_opts, commands = _options()
    sub, used = _parse(line)
    if sub is None:  # `fedmap --help`
        assert set(used) <= global_opts, line
        return
    assert sub in commands, f"{where}: unknown command {sub!r} in {line!r}"
    unknown = [o for o in used if o not in commands[sub] | global_opts]
    assert not unknown, f"{where}: {line!r} uses options that `fedmap {sub}` does not have: {unknown}"


def test_help_of_every_documented_command(capsys):
    for sub in sorted({s for s in (_parse(line)[0] for _, line in COMMANDS) if s}):
        assert main([*sub.split(), "--help"]) == 0, sub
        assert "Usage" in capsys.readouterr().out, sub


def test_documented_benchmark_scripts_exist():
    scripts = {m for path in DOCS for m in re.findall(r"python (benchmarks/\w+\.py)", path.read_text())}
    assert scripts
    missing = [s for s in scripts if not (ROOT / s).is_file()]
    assert not missing, missing


def test_readme_links_resolve():
    text = (ROOT / "README.md").read_text()
    links = [t.split("#")[0] for t in re.findall(r"\]\(([^)]+)\)", text) if "://" not in t]
    missing = [t for t in links if t and not (ROOT / t).exists()]
    assert not missing, missing


def test_readme_commands_are_what_ci_runs():
    readme = (ROOT / "README.md").read_text()
    test_cmd = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    assert test_cmd in readme
    assert readme.index(test_cmd) < readme.index("## ")  # the two commands come first
    assert "pip install -e . && fedmap demo" in readme[: readme.index("## ")]


@pytest.mark.slow
def test_mkdocs_build_strict(tmp_path):
    pytest.importorskip("mkdocs", reason="mkdocs is in the test extra: pip install -e '.[test]'")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                        "-d", str(tmp_path / "site")], capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "WARNING" not in r.stderr + r.stdout, r.stderr
    assert (tmp_path / "site" / "api" / "pipeline" / "index.html").is_file()
    assert "run_pipeline" in (tmp_path / "site" / "api" / "pipeline" / "index.html").read_text()


def test_the_api_index_lists_every_api_page():
    index = (ROOT / "docs" / "api" / "index.md").read_text()
    pages = sorted(p.name for p in (ROOT / "docs" / "api").glob("*.md") if p.name != "index.md")
    missing = [p for p in pages if f"]({p})" not in index]
    assert not missing, f"docs/api/index.md does not list {missing}"
