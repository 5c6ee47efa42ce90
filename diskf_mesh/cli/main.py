"""The ``diskf-mesh`` command line.

Each subcommand lives in its own module under ``diskf_mesh.cli`` (or
``sim``/``agents``) exposing ``register(subparsers)``, which adds a parser and
sets ``func``. User errors raise ``InputError`` and end as one line
``error: <field>: <message>`` with exit status 2, never a traceback; an
estimator's numerical failure is one line ``error: ...`` with exit status
1; a
warning of the library (e.g. a KCF step that may diverge) is one line
``warning: <message>``.

``diskf-mesh --help`` loads every command module (a command, its own), so a module imports what only its
action needs (matplotlib, tqdm, the studies) inside the action: ``--help``
and the commands that draw nothing never load a plotting library.
"""
from __future__ import annotations

import argparse
import difflib
import importlib
import os
import re
import signal
import sys
import threading
import warnings

import numpy as np

from diskf_mesh import __version__
from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.process import stopping

# every command's module: a command loads its own alone (it starts faster: ``up`` and the processes of a
# run, ``experiment``); without a command, or with a word that names none, every module is loaded (the list
# of commands and the nearest match of a word)
COMMANDS = {
    "experiment": "diskf_mesh.cli.experiment",
    "replay": "diskf_mesh.cli.replay",
    "inspect": "diskf_mesh.cli.inspect",
    "simulate": "diskf_mesh.cli.simulate",
    "figures": "diskf_mesh.cli.figures",
    "report": "diskf_mesh.cli.report",
    "resilience": "diskf_mesh.cli.resilience",
    "credentials": "diskf_mesh.cli.credentials",
    "world": "sim.world",
    "agent": "agents.agent",
    "up": "sim.launcher",
    "router": "sim.router",
    "host": "sim.host",
}
COMMAND_MODULES = tuple(COMMANDS.values())


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own usage errors: one line, status 2
        """An unknown option or command is named first, with its nearest
        match (argparse reports a missing required option before it)."""
        argv = getattr(self, "argv", ())
        choice = re.match(r"argument command: invalid choice: '?([^' ]+)'?", message)
        if message.startswith("unrecognized arguments: "):
            message = _unknown(self, message.removeprefix("unrecognized arguments: ").split(), argv)
        elif choice:
            close = difflib.get_close_matches(choice[1], sorted(_commands(self)), n=1, cutoff=0.6)
            message = f"unknown command {choice[1]}" + (f" (did you mean {close[0]}?)" if close else "")
        elif (stray := _stray_option(self, argv)) is not None:
            message = _unknown(self, [stray], argv)
        self.exit(2, f"error: {message}\n")

    def format_help(self) -> str:
        """Plain text: the description without markup or internal names, and
        every exit status (``help_text``)."""
        from diskf_mesh.cli import help_text

        description, epilog = self.description, self.epilog
        helps = [(a, a.help) for a in self._actions]
        groups = [(g, g.title, g.description) for g in self._action_groups]
        for g, title, text in groups:
            g.title, g.description = help_text.plain_line(title), help_text.plain_line(text)
        self.description, self.epilog = help_text.plain(description), help_text.exit_statuses()
        for a, text in helps:
            a.help = help_text.plain_line(text)
        try:
            return super().format_help()
        finally:
            self.description, self.epilog = description, epilog
            for a, text in helps:
                a.help = text
            for g, title, text in groups:
                g.title, g.description = title, text


def _unknown(parser: argparse.ArgumentParser, words: list, argv=()) -> str:
    """'unknown option --versoin (did you mean --version?)' for the first
    word that is an option, else argparse's own words. The options offered
    are those of the command named in ``argv`` (all of them without one)."""
    for word in words:
        if word.startswith("-"):
            flag = word.split("=", 1)[0]
            names = {o.lstrip("-"): o for o in _long_options(_command_parser(parser, argv)) if o != flag}
            close = difflib.get_close_matches(flag.lstrip("-"), sorted(names), n=1, cutoff=0.6)  # "--" alike in all
            return f"unknown option {flag}" + (f" (did you mean {names[close[0]]}?)" if close else "")
    return "unrecognized arguments: " + " ".join(words)


def _stray_option(parser: argparse.ArgumentParser, argv) -> str | None:
    """The first --word of ``argv`` that is no option of its command (nor
    an abbreviation of one), or None."""
    known = [o for o in _command_parser(parser, argv)._option_string_actions if o.startswith("--")]
    for word in argv:
        flag = word.split("=", 1)[0]
        if flag.startswith("--") and flag != "--" and not any(o.startswith(flag) for o in known):
            return flag
    return None


def _commands(parser: argparse.ArgumentParser) -> set:
    return {name for a in parser._actions if isinstance(a, argparse._SubParsersAction) for name in a.choices}


def _command_parser(parser: argparse.ArgumentParser, argv) -> argparse.ArgumentParser:
    """The subcommand's parser of the first word of ``argv`` that names one, else ``parser``."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for word in argv:
                if word in action.choices:
                    return action.choices[word]
    return parser


def _long_options(parser: argparse.ArgumentParser) -> set:
    """Every --option of ``parser`` and of its subcommands (argparse reports
    a subcommand's unknown option from the top parser) that --help shows
    (an old spelling is not offered)."""
    out = {o for o, a in parser._option_string_actions.items() if o.startswith("--") and a.help != argparse.SUPPRESS}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                out |= _long_options(sub)
    return out




def build_parser(modules=COMMAND_MODULES) -> argparse.ArgumentParser:
    parser = _Parser(prog="diskf-mesh", description="Decentralized input and state estimation (DISKF) on a Zenoh mesh. "
                     "'diskf-mesh COMMAND --help' describes a command.",
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"diskf-mesh {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for mod in modules:
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as e:
            if e.name == mod:
                continue  # subcommand not built yet
            raise
        m.register(sub)
    return parser


def _one_line(message, category, filename, lineno, line=None) -> str:
    return f"warning: {message}\n"


def main(argv=None, modules=COMMAND_MODULES) -> int:
    """Run one command; ``modules`` limits the subcommands loaded (a
    command loads only its own, ``COMMANDS``, to start fast). ``up`` starts its run's
    zygote first of all (``sim.zygote.prestart``)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if modules is COMMAND_MODULES and argv[:1] and argv[0] in COMMANDS:
        modules = (COMMANDS[argv[0]],)
    if threading.current_thread() is threading.main_thread():
        # SIGTERM as SystemExit(143) where the main thread is, so that finally blocks run (partial files
        # removed, children stopped), and SIGINT as stopping.Interrupted (exit 130, never killed by SIGINT),
        # both outside imports; a command that handles a signal itself replaces this
        for sig, default, handler in ((signal.SIGTERM, signal.SIG_DFL, stopping.terminated),
                                      (signal.SIGINT, signal.default_int_handler, stopping.interrupted)):
            if signal.getsignal(sig) is default:
                signal.signal(sig, handler)
    # Ctrl-C or SIGTERM at any moment, start-up included: one line, no traceback
    try:
        if argv[:1] == ["up"]:
            zygote = importlib.import_module("sim.zygote")  # the apps are reached by name, as COMMAND_MODULES are
            zygote.prestart(argv)
            try:
                return _main(argv, modules)
            finally:
                zygote.close_prestarted()
        return _main(argv, modules)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except SystemExit as e:
        if e.code == 143:  # SIGTERM (here, or a command's own handler)
            print("terminated", file=sys.stderr)
            return 143
        raise


def _main(argv, modules) -> int:
    if argv[:1] and argv[0].startswith("-") and argv[0] not in ("-h", "--help", "--version"):
        build_parser(()).error(f"unrecognized arguments: {argv[0]}")  # before 'required: command'
    parser = build_parser(modules)
    for p in (parser, *(c for a in parser._actions if isinstance(a, argparse._SubParsersAction)
                        for c in a.choices.values())):
        p.argv = list(argv)  # an unknown option's suggestion comes from the command's own options
    args = parser.parse_args(argv)
    args.argv = list(argv)  # the command line, for the provenance of what it writes
    try:
        with warnings.catch_warnings():
            warnings.formatwarning = _one_line  # restored on leaving the block
            code = int(args.func(args) or 0)
            sys.stdout.flush()  # a closed pipe shows here, not as a traceback at exit
            return code
    except BrokenPipeError:  # the reader went away (`... | head -1`): end quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except np.linalg.LinAlgError as e:  # an estimator's numerical failure (``engine.Diverged``): one line
        print(f"error: {e}", file=sys.stderr)
        return 1


def run_one(command: str, module: str, argv=None) -> int:
    """``python -m <module>``: only the subcommand ``command`` that ``module``
    registers, with the same error handling as ``diskf-mesh``."""
    return main([command, *(sys.argv[1:] if argv is None else argv)], modules=(module,))


if __name__ == "__main__":
    sys.exit(main())
