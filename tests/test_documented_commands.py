"""Every command line the README and ``docs/`` show parses with its command's own parser.

The commands are discovered, not listed: each ``python -m fvin_mpc.<module> ...`` — and each
research study's ``python -m benchmarks ...`` or ``python -m benchmarks.<module> ...``, run from a
clone — in a fenced code block (backslash continuations joined) or an inline code span (which may
wrap across lines) is parsed by that module's ``build_parser()`` (``benchmarks/__main__.py``'s for
``python -m benchmarks``), without running anything. A command whose options were renamed or
removed, or whose documented values its parser refuses, fails here with the file and line it is
written on. Sub-commands (``benchmarks <study>``, ``benchmarks.spherical_report collect``) are
parsed by the top-level parser, which hands them to the sub-command's.

Left out, and counted: templates rather than command lines — a ``<placeholder>``, an ALL-CAPS
metavariable (``--variant V``) or an ellipsis stands for values the reader fills in.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The module a documented command runs: ``fvin_mpc.<module>``, ``benchmarks`` or ``benchmarks.<module>``.
COMMAND = re.compile(r"python -m ((?:fvin_mpc|benchmarks)\b(?:\.[A-Za-z_][\w.]*)?)")
FENCE = re.compile(r"^\s*(```|~~~)")
INLINE_CODE = re.compile(r"(`+)(.+?)\1", re.S)
#: Where a documented command's own arguments end: a shell comment or operator, then a redirection
#: (``<`` and ``>`` only after looking for ``<placeholders>``, which contain them).
SHELL_END = re.compile(r"\s#|&&|\|\||[;|]|\$\(|\)")
REDIRECTION = re.compile(r"[<>]")
#: Values for the reader to fill in: ``<placeholder>``, ellipsis, a shell variable, ``[--optional]``.
PLACEHOLDER = re.compile(r"<[A-Za-z][^<>]*>|…|\.\.\.|\$\{?\w|\[-")
METAVARIABLE = re.compile(r"^[A-Z][A-Z0-9_]*$")


@dataclass(frozen=True)
class DocumentedCommand:
    source: str
    line: int
    module: str  # the full module name: fvin_mpc.swingup, benchmarks, benchmarks.spherical_report
    text: str | None  # the arguments as written, up to the end of the command; None: a template

    def __str__(self) -> str:
        return f"{self.source}:{self.line}: python -m {self.module} {self.text}".rstrip()


def markdown_files() -> list[Path]:
    return sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])


def _commands_in(text: str, source: str, line: int) -> list[DocumentedCommand]:
    found = []
    for match in COMMAND.finditer(text):
        rest = text[match.end():]
        # The module name may end a sentence (``fvin_mpc.train.``): the dot is not part of it.
        module = match.group(1).rstrip(".")
        opening = text[match.start() - 1] if match.start() > 0 else ""
        if opening in ("'", '"') and opening in rest:  # a command kept in a quoted string: S="python -m ..."
            rest = rest[: rest.index(opening)]
        end = SHELL_END.search(rest)
        rest = rest[: end.start()] if end else rest
        if PLACEHOLDER.search(rest):
            found.append(DocumentedCommand(source, line, module, None))
            continue
        end = REDIRECTION.search(rest)
        found.append(DocumentedCommand(source, line, module, " ".join((rest[: end.start()] if end else rest).split())))
    return found


def documented_commands(path: Path, root: Path = ROOT) -> list[DocumentedCommand]:
    """The commands written in one Markdown file, each with the line it starts on."""
    source = str(path.relative_to(root))
    lines = path.read_text().splitlines()
    commands: list[DocumentedCommand] = []
    prose: list[tuple[int, str]] = []  # (line number, text) outside fenced blocks
    fenced, pending, pending_line = False, "", 0
    for number, line in enumerate(lines, 1):
        if FENCE.match(line):
            fenced, pending = not fenced, ""
            continue
        if not fenced:
            prose.append((number, line))
            continue
        if not pending:
            pending_line = number
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        commands += _commands_in(pending + line, source, pending_line)
        pending = ""
    # Inline code spans may wrap across lines within a paragraph, never across a blank line.
    paragraph: list[tuple[int, str]] = []
    for number, line in [*prose, (0, "")]:
        if line.strip():
            paragraph.append((number, line))
            continue
        text = "\n".join(text for _, text in paragraph)
        starts = [n for n, _ in paragraph]
        for span in INLINE_CODE.finditer(text):
            first_line = starts[text.count("\n", 0, span.start())] if starts else 0
            commands += _commands_in(" ".join(span.group(2).split()), source, first_line)
        paragraph = []
    return commands


def all_documented_commands() -> list[DocumentedCommand]:
    return [command for path in markdown_files() for command in documented_commands(path)]


COMMANDS = all_documented_commands()
COMMAND_LINES = [command for command in COMMANDS if command.text is not None]


def parser_for(command: DocumentedCommand, argv: list[str]):
    """The parser the command line goes to (the studies' sub-commands through ``benchmarks``' top-level parser)."""
    module = importlib.import_module("benchmarks.__main__" if command.module == "benchmarks" else command.module)
    assert hasattr(module, "build_parser"), f"{command}: {command.module} has no build_parser()"
    return module.build_parser()


def test_the_documents_hold_command_lines():
    """The discovery itself works: the README alone shows dozens, and every command module appears,
    the research studies' commands in ``benchmarks/`` among them."""
    assert len(COMMAND_LINES) > 100
    documented = {command.module for command in COMMAND_LINES}
    assert {f"fvin_mpc.{name}" for name in ("swingup", "train", "collect", "evaluate", "fly")} <= documented
    assert {"benchmarks", "benchmarks.pendulum_v1_report", "benchmarks.spherical_report"} <= documented


def test_a_stale_option_is_caught(capsys):
    """The check can fail: an option no parser knows is refused."""
    stale = DocumentedCommand("probe.md", 1, "fvin_mpc.swingup", "--scene pendulum --no-such-option 3")
    with pytest.raises(AssertionError, match="no-such-option"):
        test_the_documented_command_parses(stale)


def test_discovery_joins_continuations_and_wrapped_inline_code(tmp_path):
    document = tmp_path / "doc.md"
    document.write_text("Run `python -m fvin_mpc.swingup\n--duration 12` or\n\n```bash\n"
                        "OMP_NUM_THREADS=1 python -m fvin_mpc.train --data data/a.npz \\\n    --quiet  # comment\n"
                        "python -m benchmarks <study> --help\n"
                        'S="python -m benchmarks ops --quick"; $S > out.txt\n```\n'
                        "See `python -m fvin_mpc.fly`, `python -m benchmarks.spherical_report collect --seed 1`.\n")
    found = documented_commands(document, tmp_path)
    assert [(c.module, c.text, c.line) for c in found] == [
        ("fvin_mpc.train", "--data data/a.npz --quiet", 5), ("benchmarks", None, 7), ("benchmarks", "ops --quick", 8),
        ("fvin_mpc.swingup", "--duration 12", 1), ("fvin_mpc.fly", "", 10),
        ("benchmarks.spherical_report", "collect --seed 1", 10)]


@pytest.mark.parametrize("command", COMMANDS, ids=str)
def test_the_documented_command_parses(command):
    if command.text is None:
        pytest.skip("a template: a placeholder, shell variable, [optional] part or ellipsis stands for values")
    try:
        argv = shlex.split(command.text)
    except ValueError as error:
        pytest.fail(f"{command}: not a shell command line ({error})")
    if any(METAVARIABLE.match(token) for token in argv):
        pytest.skip("a template: an ALL-CAPS metavariable stands for a value")
    parser = parser_for(command, argv)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            parser.parse_args(argv)
        except SystemExit as exit_info:
            assert exit_info.code == 0, f"{command}\n{err.getvalue().strip().splitlines()[-1]}"
