"""`egovib` console script (INTERFACES.md section 3).

Each command's module has `register(subparsers)`, whose parser sets `func(args) -> int`.
A run ends: bad input (EgovibError) in its one line, exit 2; Ctrl-C in one line, 130
(also during start-up); SIGTERM in one line, 143 (128 + 15: "stopped", not "bad input"),
unwinding like Ctrl-C so staging directories go at once (a second SIGTERM ends the
process without cleanup); both are recorded before they raise, so a library that
swallows the exception still cannot commit an output. Any other exception is a bug: one
line naming the command, its input and the exception, exit 1, the traceback in a log
file whose path is printed. Every way out releases the outputs the run claimed.

Other installed packages add commands through the entry-point group COMMAND_GROUP (the
repository's research package: bench, demo, ...); without it each of those is refused in
one line. Module-level imports are the standard library's and errors.py: the command
modules (and numpy, scipy, numba) load in build_parser, once main() handles signals.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib
import logging
import os
import platform
import shlex
import signal
import sys
import tempfile
import threading
import traceback
from importlib.metadata import entry_points
from pathlib import Path

from egovib_ros import __version__
from egovib_ros.errors import EgovibError

# Order = order in `egovib --help`.
COMMAND_MODULES = (
    "egovib_ros.cli.simulate",  # simulate sweep|motion|robot
    "egovib_ros.cli.calibrate",
    "egovib_ros.cli.denoise",
    "egovib_ros.cli.model",  # model show
    "egovib_ros.cli.evaluate",  # evaluate
    "egovib_ros.cli.detect",  # detect
    "egovib_ros.cli.gap",  # gap
)
#: Entry points of this group add commands, each named for its command line ("bench";
#: "gap validate": under `egovib gap`) and loading a register(subparsers).
COMMAND_GROUP = "egovib.commands"
#: The research package's commands (research/pyproject.toml), refused where it is missing.
REPOSITORY_COMMANDS = ("bench", "demo", "figures", "gap validate", "live-bench", "real")
EXIT_BUG, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_TERMINATED = 1, 2, 130, 143
# Arguments that name what a command reads, in the order they are named in a bug report.
_INPUT_ARGUMENTS = ("bags", "bag", "real", "npz", "model")
_stopped: list[type[BaseException]] = []  # Ctrl-C or SIGTERM received during this run


class Terminated(BaseException):
    """SIGTERM arrived. A BaseException, like KeyboardInterrupt: no `except Exception`
    swallows it, and every `finally` (staging directories, writers, Dask clusters) runs."""


def build_parser() -> argparse.ArgumentParser:
    # deferred: the command modules and the library load once main() handles signals
    from egovib_ros.cli.options import OneLineErrorParser

    parser = OneLineErrorParser(  # one-line errors for bad options, like every bad input
        prog="egovib",
        description="Ego-vibration removal for robot accelerometers (spectral subtraction).",
    )
    parser.add_argument("--version", action="version", version=f"egovib {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    add_commands(parser)
    return parser


def add_commands(parser) -> None:
    """The commands of COMMAND_GROUP in the order of their names (a command before its
    actions), each register() given the sub-commands of the command its name continues."""
    for entry in sorted(entry_points(group=COMMAND_GROUP), key=lambda e: e.name):
        *parents, _ = entry.name.split()
        target = parser
        for word in parents:
            target = target.commands.choices[word]
        commands = target.commands or target.add_subparsers(dest="action", metavar="ACTION")
        entry.load()(commands)


def missing_command(parser, argv: list[str]) -> str | None:
    """The repository command `argv` starts with when no installed package adds it."""
    for command in REPOSITORY_COMMANDS:
        words = command.split()
        if argv[: len(words)] != words:
            continue
        target = parser
        for word in words:
            if target.commands is None or word not in target.commands.choices:
                return command
            target = target.commands.choices[word]
    return None


def main(argv: list[str] | None = None) -> int:
    try:  # first: a Ctrl-C even before our handlers are in place ends in one line
        _stopped.clear()
        with _signals_raise():
            return _main(list(sys.argv[1:] if argv is None else argv))
    except KeyboardInterrupt:
        print("egovib: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Terminated:
        print("egovib: terminated (SIGTERM)", file=sys.stderr)
        return EXIT_TERMINATED
    finally:
        outputs = sys.modules.get("egovib_ros.outputs")  # claimed nothing if not loaded
        if outputs is not None:
            outputs.release_outputs()
            outputs.clear_stop()
        _stopped.clear()


_said: set[str] = set()  # the log messages said in this run


def _said_once(record) -> bool:
    """A log filter: each message once per run (evaluate's denoisers, one per method, would
    each say the same warning)."""
    text = record.getMessage()
    if text in _said:
        return False
    _said.add(text)
    return True


def _main(argv: list[str]) -> int:
    args = None
    try:
        before = list(logging.getLogger().handlers)
        logging.basicConfig(format="egovib: %(levelname)s: %(message)s")
        for handler in logging.getLogger().handlers:  # ours only, not a host's (pytest's)
            if handler not in before:
                handler.addFilter(_said_once)
        _said.clear()  # per run (main may run several times in one process)
        parser = build_parser()
        missing = missing_command(parser, argv)
        if missing:
            raise EgovibError(
                f"egovib {missing} is a tool of the egovib_ros repository, not of the "
                "installed package: run it in a clone's venv (make venv installs research/)"
            )
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # --help / --version (0), a bad option (2, one line printed)
            return exc.code if isinstance(exc.code, int) else EXIT_BAD_INPUT
        _raise_if_stopped()
        code = int(args.func(args) or 0)
        _raise_if_stopped()
        return code
    except EgovibError as exc:
        _raise_if_stopped()  # an error that a swallowed Ctrl-C or SIGTERM left behind
        print(f"egovib: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:  # a bug
        _raise_if_stopped()  # e.g. an extension module's import failing on a Ctrl-C
        print(_internal_error(exc, args, argv), file=sys.stderr)
        return EXIT_BUG


def _raise_if_stopped() -> None:
    """A Ctrl-C or SIGTERM whose exception a library swallowed (C code clearing errors while
    modules load) still stops the run, here or before an output is committed."""
    if _stopped:
        raise _stopped[0]()


def _request_stop(exception: type[BaseException]) -> None:
    """Record the stop here and, once loaded, where outputs are committed."""
    if not _stopped:
        _stopped.append(exception)
    outputs = sys.modules.get("egovib_ros.outputs")
    if outputs is not None and hasattr(outputs, "request_stop"):  # not while it loads
        outputs.request_stop(exception)


@contextlib.contextmanager
def _signals_raise():
    """While the command runs, Ctrl-C raises KeyboardInterrupt and SIGTERM Terminated, each
    recorded first; only in the main thread, never for a signal this process was started
    ignoring (a background job's SIGINT); the previous handlers restored afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_sigint(signum, frame):
        _request_stop(KeyboardInterrupt)
        raise KeyboardInterrupt

    def on_sigterm(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends it at once
        _request_stop(Terminated)
        raise Terminated

    previous_hook = sys.unraisablehook

    def on_unraisable(unraisable):
        # A stop raised inside a callback Python cannot propagate from (the import system's
        # module-lock weakref callback, Ctrl-C during start-up) would print "Exception
        # ignored" with a traceback; it is recorded already and acted on where outputs are
        # committed: not printed. (Re-sending the signal from a timer thread landed, under
        # load, after the command, in whatever ran next.)
        if not (_stopped and unraisable.exc_type in (KeyboardInterrupt, Terminated)):
            previous_hook(unraisable)

    previous = {}
    for number, handler in ((signal.SIGINT, on_sigint), (signal.SIGTERM, on_sigterm)):
        if signal.getsignal(number) is not signal.SIG_IGN:
            previous[number] = signal.signal(number, handler)
    sys.unraisablehook = on_unraisable
    try:
        yield
    finally:
        sys.unraisablehook = previous_hook
        for number, handler in previous.items():
            signal.signal(number, signal.SIG_DFL if handler is None else handler)


def _internal_error(exc: Exception, args, argv: list[str]) -> str:
    """The one line for an unexpected exception; its traceback goes to a log file."""
    command = _command_name(args, argv)
    inputs = _inputs(args)
    what = f"{command} ({inputs})" if inputs else command
    text = str(exc).strip().splitlines()
    summary = f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
    log, problem = write_traceback_log(exc, command, argv)
    where = f"traceback written to {log}" if log else f"traceback not written ({problem})"
    return f"egovib: internal error in {what}: {summary}; {where}"


def _command_name(args, argv: list[str]) -> str:
    if args is None:
        words = [a for a in argv[:1] if not a.startswith("-")]
        return words[0] if words else "egovib"
    parts = [getattr(args, "command", None)]
    for sub in ("scenario", "real_command", "action"):
        value = getattr(args, sub, None)
        if isinstance(value, str):
            parts.append(value)
    return " ".join(p for p in parts if p) or "egovib"


def _inputs(args) -> str:
    for name in _INPUT_ARGUMENTS:
        value = getattr(args, name, None)
        if isinstance(value, (list, tuple)):
            if value:
                more = f" and {len(value) - 1} more" if len(value) > 1 else ""
                return f"{value[0]}{more}"
        elif value:
            return str(value)
    return ""


def log_directories() -> list:
    """Where a traceback log may go: $XDG_STATE_HOME/egovib (default ~/.local/state/egovib),
    then the system temp directory."""
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(
        os.path.expanduser("~"), ".local", "state"
    )
    return [Path(state) / "egovib", Path(tempfile.gettempdir())]


def write_traceback_log(exc: BaseException, command: str, argv: list[str]):
    """(path, None) of the log written, or (None, reason) if no directory would take it."""
    stamp = datetime.datetime.now().strftime("%Y%m%dT%H%M%S")
    name = f"egovib-{command.replace(' ', '-')}-{stamp}-{os.getpid()}.log"
    text = (
        f"egovib {__version__}, Python {platform.python_version()}, {platform.platform()}\n"
        f"command: egovib {shlex.join(argv)}\n"
        f"working directory: {os.getcwd()}\n\n"
        + "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
        + (f"\nin the workers:\n{exc.details}" if getattr(exc, "details", "") else "")
    )
    problem = "no log directory"
    for directory in log_directories():
        path = directory / name
        try:
            directory.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            return path, None
        except OSError as error:
            problem = f"{directory}: {error.strerror or error}"
            with contextlib.suppress(OSError):
                path.unlink()
    return None, problem
