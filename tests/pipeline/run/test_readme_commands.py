"""The README's command reference (the block under "## Command line") lists exactly the
options each command's ``--help`` shows, and every command."""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from pipeline.run.cli import cli

README = Path(__file__).resolve().parents[3] / "README.md"
#: Options of every command, documented once on the block's ``mscal [-v|-q] [--json] COMMAND`` line.
COMMON = {"-v", "--verbose", "-q", "--quiet", "--json", "-h", "--help", "--wait"}
OPTION = re.compile(r"(?<![\w/-])(--?[a-z][a-z0-9-]*)")


def _reference() -> dict[str, set[str]]:
    """Command path (``fit response``) -> options named in the README block; ``""`` for the
    common-options line."""
    text = README.read_text()
    start = text.index("## Command line")
    block = text[text.index("```\n", start) + 4:]
    block = block[:block.index("```")]
    out: dict[str, set[str]] = {}
    current = None
    for line in block.splitlines():
        line = line.split("  #", 1)[0]
        if line.startswith("mscal "):
            words = line.split()[1:]
            path, group = [], cli
            while words and isinstance(group, click.Group) and words[0] in group.commands:
                path.append(words[0])
                group = group.commands[words.pop(0)]
            current = " ".join(path)
            out.setdefault(current, set())
            rest = " ".join(words)
        elif line.startswith(" ") and current is not None:
            rest = line
        else:
            continue
        out[current] |= set(OPTION.findall(rest.replace('"*/15 * * * *"', "")))
    return out


def _help_options(path: str) -> set[str]:
    """Option names ``mscal PATH --help`` prints (from its text, not from click's objects)."""
    res = CliRunner().invoke(cli, [*path.split(), "--help"], terminal_width=200)
    assert res.exit_code == 0, res.output
    opts = res.output[res.output.index("Options:"):]
    names = set()
    for line in opts.replace(" / ", "/").splitlines():
        m = re.match(r"\s+((?:--?[a-z][a-z0-9-]*(?:/--?[a-z][a-z0-9-]*)?(?:, )?)+)", line)
        if m:
            names |= {n for part in m.group(1).split(", ") for n in part.split("/") if n}
    return names


def _commands(group: click.Group = cli, prefix: str = "") -> list[str]:
    out = []
    for name, cmd in group.commands.items():
        path = f"{prefix}{name}"
        out += _commands(cmd, path + " ") if isinstance(cmd, click.Group) else [path]
    return out


def test_the_reference_names_every_command() -> None:
    ref = _reference()
    assert sorted(k for k in ref if k) == sorted(_commands())
    assert ref[""] >= {"-v", "-q", "--json", "-h", "--wait", "--version"}


@pytest.mark.parametrize("path", sorted(_commands()))
def test_reference_options_match_help(path: str) -> None:
    ref = _reference()[path]
    shown = _help_options(path)
    assert COMMON - {"--wait"} <= shown  # every command has the common options
    shown -= COMMON
    # the README may give the short or the long form of an option with both (-o / --output)
    pairs = {"-o": "--output"}
    ref = {pairs.get(o, o) for o in ref}
    shown = {o for o in shown if not (o in pairs and pairs[o] in shown)}
    assert ref - shown == set(), f"README lists options that 'mscal {path}' does not have"
    assert shown - ref == set(), f"'mscal {path} --help' shows options the README does not list"
