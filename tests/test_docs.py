"""README.md and docs/ agree with the code: every command shown runs, every link resolves.

The README's bash blocks are read line by line. Commands that set up a machine or take
minutes (``bash .ci/...``, ``pip install``, the test suite itself, the benchmarks) are
checked to be the documented entry points (the script exists, the extra and the pytest
marker are declared, the benchmark module imports) rather than run. The demo's three
commands run for real on a small render of the same scene (96 px, 2 frames, 4 spp), with
their outputs under a temporary folder. In the bash blocks of docs/*.md, every option given
to one of the project's commands must be one its ``--help`` lists, and every
``python -m MODULE`` must import. Relative links in README.md and docs/**/*.md must name
files that exist.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

#: The console scripts of pyproject.toml, run through their entry function so that the
#: checkout on PYTHONPATH is the one tested, installed or not.
ENTRY = {
    "omnisim": "omnisim.cli",
    "omnivalidate": "validation.cli",
    "omniflow": "omniflow.cli",
    "omniflow-stream": "omniflow.cli.stream",
}
#: The demo's render made small: 96 px (omniflow needs an annulus of h_min 16 px and more),
#: 2 frames (one pair), 4 spp.
SMALL_RENDER = ["--resolution", "96x96", "--frames", "2", "--spp", "4"]


def fenced_blocks(text: str, language: str) -> list[str]:
    """The bodies of the ```language fenced blocks of a Markdown text, in order."""
    return re.findall(rf"^```{language}\n(.*?)^```", text, flags=re.M | re.S)


def commands(block: str) -> list[list[str]]:
    """Each non-empty line of a bash block as argv, its trailing comment removed."""
    out = []
    for line in block.splitlines():
        argv = shlex.split(line, comments=True)
        if argv:
            out.append(argv)
    return out


def shell_lines(block: str) -> list[list[str]]:
    """The commands of a bash block as argv: continuations joined, here-documents skipped."""
    out, heredoc, pending = [], None, ""
    for line in block.splitlines():
        if heredoc is not None:
            heredoc = None if line.strip() == heredoc else heredoc
            continue
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        line, pending = pending + line, ""
        marker = re.search(r"<<-?'?(\w+)'?", line)
        if marker:
            heredoc = marker.group(1)
            line = line[: marker.start()]
        argv = shlex.split(line, comments=True)
        if argv:
            out.append(argv)
    return out


def relative_links(text: str) -> list[str]:
    """Targets of the Markdown links of a text that point inside the repository."""
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    return [t for t in targets if not re.match(r"[a-z]+:", t) and not t.startswith("#")]


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _readme_commands() -> list[list[str]]:
    return [argv for block in fenced_blocks(README.read_text(), "bash") for argv in commands(block)]


def test_the_parsers_on_a_small_text():
    text = "a\n```bash\nx --y 1   # note\n\nz 'a b'\n```\n```python\nimport os\n```\n"
    assert [commands(b) for b in fenced_blocks(text, "bash")] == [[["x", "--y", "1"], ["z", "a b"]]]
    assert fenced_blocks(text, "python") == ["import os\n"]
    links = "[a](docs/x.md) [b](https://e.org) [c](#top) [d](y.md#part)"
    assert relative_links(links) == ["docs/x.md", "y.md#part"]


def _check_entry_point(argv: list[str]) -> None:
    """A setup or long command: it must be one the project documents and ships."""
    project = _pyproject()
    if argv[0] == "bash":
        script = ROOT / argv[1]
        assert script.is_file() and script.read_text().startswith("#!"), argv
    elif argv[:2] == ["pip", "install"]:
        spec = next(a for a in argv[2:] if not a.startswith("-"))
        extras = re.findall(r"\[([^\]]*)\]", spec)
        declared = project["project"]["optional-dependencies"]
        for extra in extras[0].split(",") if extras else []:
            assert extra in declared, f"pip install {spec}: no extra {extra!r} in pyproject.toml"
    elif argv[:3] == ["python3", "-m", "pytest"]:
        markers = " ".join(project["tool"]["pytest"]["ini_options"]["markers"])
        for i, a in enumerate(argv[3:], start=3):
            if a == "-m":
                for word in re.findall(r"[a-z_]+", argv[i + 1]):
                    assert word in ("not", "and", "or") or f"{word}:" in markers, argv
        ci = (ROOT / ".ci" / "run").read_text()
        assert "python3 -m pytest -q" in ci  # the README's test command is CI's
    elif argv[:2] == ["python3", "-m"] and argv[2].startswith("benchmarks."):
        assert importlib.util.find_spec(argv[2]) is not None, argv
    elif argv[0] == "ruff":
        assert importlib.util.find_spec("ruff") is not None, "ruff is in the dev extra"
    else:
        raise AssertionError(f"README command not covered by tests/test_docs.py: {argv}")


def _run(argv: list[str], tmp: Path) -> None:
    """Run one of the demo's commands with its outputs moved under tmp."""
    argv = [str(tmp / a[len("runs/") :]) if a.startswith("runs/") else a for a in argv]
    if argv[:2] == ["omnisim", "render"]:
        argv += SMALL_RENDER
    code = f"import sys; from {ENTRY[argv[0]]} import main; sys.exit(main(sys.argv[1:]))"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", code, *argv[1:]], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    tail = proc.stderr[-2000:]
    assert proc.returncode == 0, f"{shlex.join(argv)}: exit {proc.returncode}\n{tail}"


def test_setup_and_long_commands_are_the_documented_entry_points():
    long = [a for a in _readme_commands() if a[0] not in ENTRY]
    assert long, "README.md shows no setup command"
    for argv in long:
        _check_entry_point(argv)


@pytest.mark.render
@pytest.mark.slow
def test_the_demo_commands_run_on_a_small_render(tmp_path):
    demo = [a for a in _readme_commands() if a[0] in ENTRY]
    assert [a[:2] for a in demo][:1] == [["omnisim", "render"]], "the demo renders first"
    for argv in demo:
        _run(argv, tmp_path)
    assert (tmp_path / "default" / "report" / "report.html").is_file()


_HELP: dict[tuple[str, ...], str] = {}


#: Subcommands of the console scripts; ``omniflow`` with none is ``omniflow pair``,
#: ``omnivalidate`` with none scores one dataset.
SUBCOMMANDS = {"omnisim": None, "omniflow": ("pair", "stream"), "omnivalidate": ("suite", "sweep")}


def _command_of(argv: list[str]) -> tuple[str, ...]:
    """The console script and subcommand a documented command line runs."""
    subs = SUBCOMMANDS.get(argv[0], ())
    if subs is None:
        return tuple(argv[:2])
    if len(argv) > 1 and argv[1] in subs:
        return tuple(argv[:2])
    return ("omniflow", "pair") if argv[0] == "omniflow" else (argv[0],)


def _help(command: tuple[str, ...], flag: str = "--help") -> str:
    """The ``--help`` (or ``--help-expert``) text of a console script and subcommand, cached."""
    key = (*command, flag)
    if key not in _HELP:
        code = f"import sys; from {ENTRY[command[0]]} import main; sys.exit(main(sys.argv[1:]))"
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        proc = subprocess.run([sys.executable, "-c", code, *command[1:], flag], cwd=ROOT,
                              env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
        assert proc.returncode == 0, f"{' '.join(command)} {flag}: exit {proc.returncode}"
        _HELP[key] = proc.stdout
    return _HELP[key]


@pytest.mark.parametrize("page", sorted((ROOT / "docs").glob("*.md")), ids=lambda p: p.name)
def test_documented_options_exist(page):
    for block in fenced_blocks(page.read_text(), "bash"):
        for argv in shell_lines(block):
            if argv[0] in ENTRY:
                command = _command_of(argv)
                text = _help(command)
                if argv[0] == "omniflow":  # expert options are listed by --help-expert
                    text += _help(command, "--help-expert")
                for opt in (a.split("=")[0] for a in argv if a.startswith("--")):
                    assert opt in text, f"{page.name}: {' '.join(command)} has no option {opt}"
            elif argv[0].startswith("python") and argv[1:2] == ["-m"]:
                assert importlib.util.find_spec(argv[2]) is not None, f"{page.name}: {argv}"


def test_shell_lines_join_and_skip():
    block = "a --x \\\n  --y 1\npython - <<'EOF'\nimport os\nEOF\nb  # c\n"
    assert shell_lines(block) == [["a", "--x", "--y", "1"], ["python", "-"], ["b"]]


def test_the_python_example_imports():
    for block in fenced_blocks(README.read_text(), "python"):
        lines = block.splitlines()
        imports = "\n".join(line for line in lines if line.startswith(("from", "import")))
        exec(compile(imports, "README.md", "exec"), {})


@pytest.mark.parametrize(
    "page",
    [README, *sorted((ROOT / "docs").rglob("*.md"))],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_relative_links_point_at_files(page):
    missing = [t for t in relative_links(page.read_text())
               if not (page.parent / t.split("#")[0]).exists()]  # fmt: skip
    assert not missing, f"{page.relative_to(ROOT)}: links to missing files {missing}"
