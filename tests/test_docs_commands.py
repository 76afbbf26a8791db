"""Every documented command runs as written: each shell command in README.md, CHANGELOG.md
and docs/**/*.md that calls ``python scripts/NAME.py`` is parsed with that script's own
parser (``build_parser()``; nothing is simulated), and the scene and training files it
names under ``configs/`` exist.

Commands are read from fenced code blocks (with ``\\`` continuations, ``#`` comments, and
``&&`` / ``;`` / `` | `` chains) and from inline code spans (which may wrap lines; a span
that starts with ``scripts/NAME.py`` and arguments counts, without ``python``). A
synopsis is parsed too, as a user would fill it in: ``[`` and ``]`` and ``...`` are
dropped, and an upper-case placeholder (``N``, ``SECONDS``) given to a number option
stands for 1.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
SPAN = re.compile(r"`([^`]+)`")
CHAIN = re.compile(r"\s(?:&&|\|\||;|\|)\s|;$")
SCRIPT_FIRST = re.compile(r"^scripts/\w+\.py\s+\S")
PLACEHOLDER = re.compile(r"^(?:[A-Z][A-Z0-9_]*|\$\w+|<[^>]+>)$")


def markdown_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return files + [p for p in (ROOT / "CHANGELOG.md",) if p.exists()]


def commands_in(text: str) -> list[str]:
    """Every ``python scripts/NAME.py ...`` command of a markdown text, one string each."""
    found = []
    for block in FENCE.findall(text):
        joined = re.sub(r"\\\n", " ", block)
        for line in joined.splitlines():
            found += [c for c in CHAIN.split(line) if "python scripts/" in c]
    prose = FENCE.sub("", text)
    for span in SPAN.findall(prose):
        span = " ".join(span.split())
        # a span that starts with a script and gives it arguments is a command too
        found += [c for c in CHAIN.split(span) if "python scripts/" in c or SCRIPT_FIRST.match(c)]
    return [c.strip() for c in found]


def argv_of(command: str) -> tuple[str, list[str]]:
    """``(script name, its arguments)`` of one command, synopsis brackets dropped."""
    command = command.replace("[", " ").replace("]", " ")
    words = shlex.split(command, comments=True)
    start = next(i for i, w in enumerate(words) if re.fullmatch(r"scripts/\w+\.py", w))
    return words[start], [w for w in words[start + 1:] if w not in ("...", "…")]


_PARSERS: dict[str, argparse.ArgumentParser] = {}


def parser_of(script: str) -> argparse.ArgumentParser:
    if script not in _PARSERS:
        path = ROOT / script
        spec = importlib.util.spec_from_file_location(f"_doc_script_{path.stem}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        _PARSERS[script] = module.build_parser()
    return _PARSERS[script]


def _numeric_options(parser: argparse.ArgumentParser) -> set[str]:
    return {s for a in parser._actions if a.type in (int, float) for s in a.option_strings}


def problem(command: str) -> str | None:
    """Why the command would not run as written (None when it parses)."""
    try:
        script, args = argv_of(command)
    except (ValueError, StopIteration) as err:
        return f"cannot be read as a shell command ({err})"
    if not (ROOT / script).exists():
        return f"{script}: no such script"
    parser = parser_of(script)
    numeric = _numeric_options(parser)
    args = [("1" if PLACEHOLDER.match(w) and i and args[i - 1] in numeric else w) for i, w in enumerate(args)]
    missing = [w for w in args if w.startswith("configs/") and not (ROOT / w).exists()]
    if missing:
        return f"names {missing[0]}, which does not exist"
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            parser.parse_args(args)
    except SystemExit as exc:
        if exc.code:
            return err.getvalue().strip().splitlines()[-1]
    return None


def documented_commands() -> list[tuple[str, str]]:
    return [(str(p.relative_to(ROOT)), c) for p in markdown_files() for c in commands_in(p.read_text())]


def test_every_documented_command_parses():
    commands = documented_commands()
    # the collector finds the commands the documents hold (a broken reader would find none)
    assert len(commands) > 60, f"only {len(commands)} documented commands found"
    assert {argv_of(c)[0] for _, c in commands} >= {"scripts/train.py", "scripts/evaluate.py", "scripts/simulate.py",
                                                   "scripts/bench.py", "scripts/perceive.py"}
    bad = [f"{where}: `{c}`: {why}" for where, c in commands if (why := problem(c)) is not None]
    assert not bad, "documented commands that do not run as written:\n" + "\n".join(bad)


def test_a_broken_command_is_reported():
    """The check fails on the mistakes it exists for: a second override after --set before
    the file, an unknown flag, a missing required option, a file that does not exist."""
    text = """
Train with `python scripts/train.py configs/train_capture_falling.yaml --bogus 3`, or

```
python scripts/train.py --set run.seed=1 configs/train_capture_falling.yaml
python scripts/evaluate.py configs/capture_env_falling.yaml --policy scripted \\
    --out out/eval   # no --episodes
python scripts/simulate.py configs/no_such_scene.yaml --out out/x
python scripts/simulate.py configs/rope_net.yaml --out out/rope && ls out/rope
```
"""
    commands = commands_in(text)
    assert len(commands) == 5
    order = ("--bogus", "--set run.seed=1", "no --episodes", "no_such_scene", "rope_net")
    why = [problem(next(c for c in commands if key in c or (key == "no --episodes" and "--policy" in c)))
           for key in order]
    assert "unrecognized arguments: --bogus 3" in why[0]
    assert "is not KEY=VALUE" in why[1] and "configs/train_capture_falling.yaml" in why[1]
    assert "required: --episodes" in why[2]
    assert "configs/no_such_scene.yaml" in why[3]
    assert why[4] is None


@pytest.mark.parametrize("script", ["train", "evaluate", "simulate", "tune_pid", "capture_sweep", "sweep"])
def test_set_takes_several_overrides_either_way(script):
    """``--set a=1 b=2`` and ``--set a=1 --set b=2`` give the same list, in order."""
    parser = parser_of(f"scripts/{script}.py")
    rest = {"train": ["F"], "evaluate": ["F", "--policy", "scripted", "--episodes", "1", "--out", "o"],
            "simulate": ["F", "--out", "o"], "tune_pid": ["F", "--out", "o"], "capture_sweep": ["F"],
            "sweep": ["F", "--policy", "scripted", "--vary", "env.policy_rate=10,25", "--episodes", "2", "--out", "o"]}[script]
    one = parser.parse_args([*rest, "--set", "a.b=1", "c=[1, 2]", "--set", "d=x"])
    two = parser.parse_args([*rest, "--set", "a.b=1", "--set", "c=[1, 2]", "--set", "d=x"])
    assert one.overrides == two.overrides == ["a.b=1", "c=[1, 2]", "d=x"]
