"""The generated reference of every option of every `smana` command (docs/reference/cli.md; the
command that writes it, and the config page, is docs_reference.py). Each command's entry is
called with argparse's parsing replaced by a catch, so that it gives the parser the command
builds without running anything; its options and subcommands are walked from there."""

from __future__ import annotations

import argparse
import contextlib

from smana.lab.docs_reference import COMMAND, HEADER, ROOT, anchor, cell, flat


class _Parsed(Exception):
    """Raised instead of parsing: carries the parser a command built."""

    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__(parser.prog)
        self.parser = parser


@contextlib.contextmanager
def _catching_parsers():
    real = argparse.ArgumentParser.parse_known_args

    def catch(self, args=None, namespace=None):
        raise _Parsed(self)

    argparse.ArgumentParser.parse_known_args = catch
    try:
        yield
    finally:
        argparse.ArgumentParser.parse_known_args = real


def parser_of(target: str) -> argparse.ArgumentParser | None:
    """The parser the command `target` ("module:function") builds, caught before it parses."""
    from smana.common.registry import load_spec

    func = load_spec(target, "command", kind="command")
    with _catching_parsers():
        try:
            func([])
        except _Parsed as caught:
            return caught.parser
    return None


def commands() -> dict[str, tuple[str, str]]:
    """`smana --help`'s commands: smana's own and its research harness's (plug-ins installed
    beside it are left out: the page is the same on every machine)."""
    from smana.deploy import cli

    return {n: (t, h) for n, (t, h) in cli.commands().items() if t.startswith("smana.")}


def _shared() -> dict[tuple[str, ...], str]:
    """The options every service command takes (common/cli.py `make_parser`): option strings ->
    help."""
    from smana.common.cli import make_parser

    p = make_parser("smana", "")
    return {
        tuple(a.option_strings): a.help
        for a in p._actions
        if a.option_strings and not isinstance(a, argparse._HelpAction)
    }


def _help(action: argparse.Action, prog: str) -> str:
    """argparse's own expansion of `%(default)s` and the like in a help text."""
    text = action.help or ""
    if "%" not in text:
        return text
    params = dict(vars(action), prog=prog)
    params = {k: v for k, v in params.items() if v is not argparse.SUPPRESS}
    params = {k: getattr(v, "__name__", v) for k, v in params.items()}
    if params.get("choices") is not None:
        params["choices"] = ", ".join(str(c) for c in params["choices"])
    return text % params


def _value_of(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    metavar = action.metavar
    if isinstance(metavar, tuple):
        metavar = " ".join(metavar)
    text = metavar or (action.dest.upper() if action.option_strings else action.dest)
    if action.nargs in ("*", "+"):
        text += " ..."
    elif action.nargs == "?":
        text = f"[{text}]"
    return text


def _default_of(action: argparse.Action) -> str:
    d = action.default
    empty = isinstance(d, str | list | tuple) and not d
    if d is None or d is argparse.SUPPRESS or d is False or empty or action.nargs == 0:
        return ""
    return f"`{_here(str(d))}`"


def _here(text: str) -> str:
    """A text with this checkout's path made relative (a default under the repository)."""
    return text.replace(f"{ROOT}/", "").replace(str(ROOT), ".")


def _parser_section(parser, prog: str, level: int, shared: dict) -> list[str]:
    out = [f"{'#' * level} `{prog}`\n"]
    if parser.description:  # its first paragraph: the command's --help has the rest
        out.append(cell(flat(parser.description.strip().split("\n\n")[0])) + "\n")
    rows, taken, subs = [], [], None
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        if isinstance(action, argparse._SubParsersAction):
            subs = action
            continue
        key = tuple(action.option_strings)
        if key and shared.get(key, object()) == action.help:
            taken.append(key[0])
            continue
        name = ", ".join(f"`{o}`" for o in action.option_strings) or f"`{_value_of(action)}`"
        value = _value_of(action) if action.option_strings else ""
        rows.append(
            f"| {name} | {cell(f'`{value}`' if value else '')} | {cell(_default_of(action))} "
            f"| {cell(flat(_here(_help(action, prog))))} |"
        )
    if rows:
        out += ["| argument | value | default | meaning |", "|---|---|---|---|", *rows, ""]
    if taken:
        if len(taken) == len(shared):
            out.append("And the [options every service command takes](#shared-options).\n")
        else:
            names = ", ".join(f"`{t}`" for t in taken)
            out.append(f"And the [shared options](#shared-options) {names}.\n")
    if subs is not None:
        helps = {a.dest: a.help for a in subs._choices_actions}
        out.append("| subcommand | what it does |")
        out.append("|---|---|")
        for name in subs.choices:
            out.append(f"| `{prog} {name}` | {cell(flat(helps.get(name) or ''))} |")
        out.append("")
        for name, sub in subs.choices.items():
            out += _parser_section(sub, f"{prog} {name}", min(level + 1, 4), shared)
    return out


def cli_reference() -> str:
    from smana.lab import bench

    shared = _shared()
    known = commands()
    width = "| command | what it does |\n|---|---|"
    out = [
        HEADER.format(command=COMMAND, source="the argparse parsers of every `smana` command"),
        "# Command-line reference\n",
        "Every `smana` command and its options, as `smana <command> --help` gives them. "
        "Exit status of every command: 0 done, 1 the command ran and failed, 2 misuse (one "
        "line on stderr naming the mistake). `smana --version` prints the version.\n",
        width,
    ]
    out += [
        f"| [`smana {n}`](#{anchor(f'smana {n}')}) | {cell(h)} |" for n, (_, h) in known.items()
    ]
    out += [
        "",
        "## Shared options\n",
        "Every service command (and `smana up`) takes these; `--config` and `--set` choose the "
        "config ([configuration reference](config.md)).\n",
        "| argument | meaning |",
        "|---|---|",
    ]
    out += [f"| {', '.join(f'`{o}`' for o in k)} | {cell(h or '')} |" for k, h in shared.items()]
    out.append("")
    for name, (target, text) in known.items():
        if name == "bench":  # a dispatcher without a parser of its own: one per benchmark
            out += ["## `smana bench`\n", cell(text) + "\n", "| benchmark | |", "|---|---|"]
            out += [f"| `smana bench {b}` | see below |" for b in bench.BENCHES]
            out.append("")
            for b, spec in bench.BENCHES.items():
                out += _parser_section(parser_of(spec), f"smana bench {b}", 3, shared)
            continue
        parser = parser_of(target)
        if parser is None:
            out += [f"## `smana {name}`\n", cell(text) + "\n"]
            continue
        out += _parser_section(parser, f"smana {name}", 2, shared)
    return "\n".join(out).rstrip() + "\n"
