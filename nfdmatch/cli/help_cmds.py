"""`nfdmatch help [COMMAND...]`, `nfdmatch completion bash|zsh|fish` and the man page
(`nfdmatch help --man`: roff made from the commands' own help, so it never says other
than `--help`; `make install` writes it to ``nfdmatch.1`` and installs it)."""

from __future__ import annotations

import re
import textwrap
from typing import TYPE_CHECKING

import click

from .. import __version__
from .group import main

if TYPE_CHECKING:
    from collections.abc import Iterator

SHELLS = ("bash", "zsh", "fish")


@main.command("help")
@click.argument("command", nargs=-1, metavar="[COMMAND...]")
@click.option("--man", is_flag=True, help="Print the manual page (roff) of every command instead: man -l -.")
@click.pass_context
def help_command(ctx: click.Context, command: tuple[str, ...], man: bool) -> None:
    """Print the help of COMMAND (e.g. `nfdmatch help index build`), or of nfdmatch.

    \b
    Examples:
      nfdmatch help query
      nfdmatch help --man > nfdmatch.1 && man ./nfdmatch.1
    """
    root = ctx.find_root()
    if man:
        click.echo(man_page(root.command), nl=False)
        return
    target, path = _find(root, list(command))
    with click.Context(target, info_name=path[-1], parent=_parents(root, path)) as sub:
        click.echo(target.get_help(sub))


def _find(root: click.Context, words: list[str]) -> tuple[click.Command, list[str]]:
    """The command named by ``words`` under the root context's group, and its names."""
    cmd, path = root.command, [root.info_name or "nfdmatch"]
    for word in words:
        found = cmd.get_command(root, word) if isinstance(cmd, click.Group) else None
        if found is None:
            raise click.UsageError(f"no command {' '.join(path[1:] + [word])!r}; `nfdmatch --help` lists them")
        cmd, path = found, path + [word]
    return cmd, path


def _parents(root: click.Context, path: list[str]) -> click.Context:
    """A context chain for ``path`` (so the usage line reads `nfdmatch index build ...`)."""
    ctx, cmd = root, root.command  # the group's settings (-h) pass down the chain
    for word in path[1:-1]:
        cmd = cmd.get_command(ctx, word)  # type: ignore[attr-defined]  # a group: a word before the last
        ctx = click.Context(cmd, info_name=word, parent=ctx)
    return ctx


@main.command()
@click.argument("shell", type=click.Choice(SHELLS))
def completion(shell: str) -> None:
    """Print the completion script of SHELL for nfdmatch.

    \b
    Examples:
      eval "$(nfdmatch completion bash)"        # in ~/.bashrc
      eval "$(nfdmatch completion zsh)"         # in ~/.zshrc
      nfdmatch completion fish > ~/.config/fish/completions/nfdmatch.fish
    """
    from click.shell_completion import get_completion_class

    complete = get_completion_class(shell)(main, {}, "nfdmatch", "_NFDMATCH_COMPLETE")  # type: ignore[misc]  # one of SHELLS
    click.echo(complete.source())


# --------------------------------------------------------------------------- the man page


def _roff(text: str) -> str:
    """``text`` safe in roff: backslashes and hyphens escaped, no line starting a request."""
    text = text.replace("\\", "\\e").replace("-", "\\-")
    return "\n".join("\\&" + line if line[:1] in (".", "'") else line for line in text.split("\n"))


def _paragraphs(help_text: str | None) -> str:
    """A command's help as roff: paragraphs joined, ``\\b`` blocks kept line by line."""
    out = []
    for block in re.split(r"\n\s*\n", click.unstyle(help_text or "").strip()):
        lines = block.split("\n")
        if lines[0].strip() == "\b":
            block = textwrap.dedent("\n".join(line.rstrip() for line in lines[1:]))
            out.append(".PP\n.nf\n" + _roff(block) + "\n.fi")
        else:
            out.append(".PP\n" + _roff(" ".join(line.strip() for line in lines)))
    return "\n".join(out)


def _commands(
    group: click.Group, ctx: click.Context, prefix: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], click.Command, click.Context]]:
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        if cmd is None or cmd.hidden:
            continue
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, click.Context(cmd, info_name=name, parent=ctx), prefix + (name,))
        else:
            yield prefix + (name,), cmd, click.Context(cmd, info_name=name, parent=ctx)


def man_page(group: click.Group) -> str:
    """The manual page of nfdmatch (roff, section 1): the group's help, then every command's
    usage, help and options, as their ``--help`` says them."""
    root = click.Context(group, info_name="nfdmatch", **group.context_settings)
    lines = [  # no date: the page changes only when the help does
        f'.TH NFDMATCH 1 "" "nfdmatch {__version__}" "User Commands"',
        ".SH NAME",
        "nfdmatch \\- " + _roff(group.get_short_help_str(limit=200).rstrip(".")),
        ".SH SYNOPSIS",
        ".B nfdmatch",
        "[\\fIOPTIONS\\fR] \\fICOMMAND\\fR [\\fIARGS\\fR]...",
        ".SH DESCRIPTION",
        _paragraphs(group.help),
        ".SH COMMANDS",
    ]
    for names, cmd, ctx in _commands(group, root):
        pieces = cmd.collect_usage_pieces(ctx)
        lines += [
            ".SS " + _roff(" ".join(("nfdmatch",) + names)),
            ".B " + _roff(" ".join(("nfdmatch",) + names)),
            _roff(" ".join(pieces)),
            _paragraphs(cmd.help),
        ]
        options = [p.get_help_record(ctx) for p in cmd.get_params(ctx)]
        for record in filter(None, options):
            lines += [".TP", "\\fB" + _roff(record[0]) + "\\fR", _roff(click.unstyle(record[1]))]
    lines += [
        ".SH EXIT STATUS",
        ".TP\n0\nanswered: every input read, rows found",
        ".TP\n1\nnothing matched: a filter left every query empty; index verify: problems found",
        ".TP\n2\nerror: a usage error, a missing or damaged index, or no input could be read",
        ".TP\n3\npartial: some inputs could not be read, the rest was answered",
        ".TP\n130, 143\ninterrupted (SIGINT) or terminated (SIGTERM)",
        ".SH SEE ALSO",
        "README.md and docs/ in the source tree.",
    ]
    return "\n".join(lines) + "\n"
