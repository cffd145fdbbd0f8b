"""Docs that run: the README's code blocks execute, its `place3d` lines parse, docs/commands.md covers
every subcommand (issue 15, item 6)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from place3d_app import server_request
from place3d_app.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
COMMANDS_DOC = ROOT / "docs" / "commands.md"

#: commands cheap enough to run on every test run (no scene, no P-SOG)
CHEAP = {("backends",), ("lidars",), ("--version",)}


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every ``` fenced block, in order."""
    return [(m.group(1), m.group(2)) for m in re.finditer(r"^```(\w*)\n(.*?)^```$", text, re.S | re.M)]


def _argv(line: str) -> list[str]:
    """The arguments the CLI's parser gets for a ``place3d ...`` line: the ``place3d`` entry point
    (``place3d_app``) takes ``--server`` before the parser sees the command."""
    return server_request(shlex.split(line)[1:], {})[2]


def place3d_lines(text: str) -> list[str]:
    """Every line of a fenced non-Python block that starts with ``place3d `` (or ``$ place3d ``), without its
    trailing comment."""
    lines = []
    for lang, body in fenced_blocks(text):
        if lang == "python":
            continue
        for line in body.splitlines():
            line = line.strip().removeprefix("$ ")      # docs/commands.md shows a prompt
            if line.startswith("place3d "):
                lines.append(line.split(" #", 1)[0].strip())
    return lines


def _env(tmp_path) -> dict:
    env = dict(os.environ, PLACE3D_CACHE=str(tmp_path / "cache"))
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def test_readme_has_python_and_place3d_blocks():
    # the tests below would pass vacuously on a README without code
    text = README.read_text()
    assert any(lang == "python" for lang, _ in fenced_blocks(text))
    assert len(place3d_lines(text)) >= 5


@pytest.mark.parametrize("index", range(sum(lang == "python" for lang, _ in fenced_blocks(README.read_text()))))
def test_readme_python_block_runs(index, tmp_path):
    """Each ```python block runs as written, in a fresh interpreter, from an unrelated folder, with a fresh
    P-SOG cache (so the example is honest about a first run)."""
    code = [body for lang, body in fenced_blocks(README.read_text()) if lang == "python"][index]
    script = tmp_path / "snippet.py"
    script.write_text(code)
    work = tmp_path / "cwd"
    work.mkdir()
    r = subprocess.run([sys.executable, str(script)], cwd=work, env=_env(tmp_path), capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, f"README python block {index} failed:\n{code}\n--- stderr:\n{r.stderr}"


@pytest.mark.parametrize("line", place3d_lines(README.read_text()))
def test_readme_place3d_line_parses(line):
    """Every `place3d ...` line in the README is accepted by the CLI's parser (names, options, choices)."""
    argv = _argv(line)
    if argv == ["--version"]:
        return    # argparse's version action exits; run below
    args = build_parser().parse_args(argv)
    assert callable(args.func)


@pytest.mark.parametrize("argv", sorted(CHEAP))
def test_cheap_commands_run(argv, tmp_path):
    r = subprocess.run([sys.executable, "-m", "place3d_app.cli", *argv], cwd=tmp_path, env=_env(tmp_path),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip(), f"place3d {' '.join(argv)} printed nothing"
    if argv == ("--version",):
        assert r.stdout.startswith("place3d-kernels ")
    if argv == ("backends",):
        assert re.search(r"^available\s+reference\b", r.stdout, re.M)
        # every missing row names its reason
        for row in r.stdout.splitlines():
            if row.startswith("missing"):
                assert len(row.split(None, 2)) == 3, f"missing backend without a reason: {row!r}"
        import place3d_kernels as p3k

        names = p3k.available_backends()
        if "warp:cpu" in names and not any(n.startswith("warp:cuda") for n in names):
            # Warp without a CUDA device: the report says why (issue 15: it never did)
            assert re.search(r"^missing\s+warp:cuda\s+\S", r.stdout, re.M), r.stdout


def test_readme_mentions_every_command():
    text = README.read_text()
    for name in _subcommands():
        assert re.search(rf"\b{name}\b", text), f"README does not mention `place3d {name}`"


def _subcommands() -> list[str]:
    ap = build_parser()
    sub = next(a for a in ap._actions if a.__class__.__name__ == "_SubParsersAction")
    return sorted(sub.choices)


def test_commands_doc_has_a_section_per_subcommand():
    """docs/commands.md has a ``## place3d NAME`` section for every subcommand (and --version), each with an
    example block: adding a command without documenting it fails here."""
    text = COMMANDS_DOC.read_text()
    names = _subcommands()
    assert len(names) >= 9
    headings = re.findall(r"^## `?place3d ([\w-]+)", text, re.M)
    for name in names + ["--version"]:
        assert name in headings, f"docs/commands.md has no '## place3d {name}' section"
    for name in names:
        section = text.split(f"## place3d {name}", 1)[1].split("\n## ", 1)[0]
        assert "```" in section, f"docs/commands.md: section 'place3d {name}' has no example"
    lines = place3d_lines(text)
    assert len(lines) >= len(names)
    for line in lines:
        argv = _argv(line)
        if argv != ["--version"] and "--help" not in argv:
            build_parser().parse_args(argv)


def test_shipped_carla_map_by_name_from_any_folder(tmp_path, monkeypatch):
    """The README's `--scene opendrive:Town01` names a shipped map: accepted from a folder without it."""
    from place3d_kernels.spec import SceneSpec

    monkeypatch.chdir(tmp_path)
    assert SceneSpec("opendrive:Town01").validate().kind == "opendrive"
    with pytest.raises(FileNotFoundError, match="shipped maps by name"):
        SceneSpec("opendrive:Town99").validate()


def test_package_docstring_example_runs():
    """The example in ``help(place3d_kernels)`` runs and prints what it shows (P-SOG cache: per test)."""
    import doctest

    import place3d_kernels

    r = doctest.testmod(place3d_kernels, verbose=False)
    assert r.attempted >= 3 and r.failed == 0


def test_bench_table_is_readable(capsys, tmp_path, monkeypatch):
    """`place3d bench` ends in a table (workloads x backends, units in the labels), not raw dicts."""
    from place3d_app.cli import main
    from place3d_app.kernel_bench import format_table

    res = {"info": {"cpu": "CPU", "cores": 2, "date": "2026-11-24"},
           "backends": {"reference": {"placement_eval_ms": 3080.0, "traverse_steps": 5},
                        "warp:cpu": {"placement_eval_ms": 42.7, "raycast_town_mrays_s": 1.9}}}
    lines = format_table(res).splitlines()
    assert lines[1].split() == ["workload", "reference", "warp:cpu"]
    assert lines[3].split()[-2:] == ["3,080", "42.7"] and "[ms]" in lines[3]
    assert lines[4].split()[-2:] == ["-", "1.9"] and "[M rays/s]" in lines[4]
    assert len(lines) == 5                   # traverse_steps is a count, not a figure: no row
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "--output", "b.csv"]) == 2        # refused before any timing
    assert not list(tmp_path.iterdir())
    assert "only .json" in capsys.readouterr().err
