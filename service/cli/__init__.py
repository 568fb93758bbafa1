"""The ``posecal`` command line: one sub-command per module in this package.

Each sub-command module defines ``register(subparsers)``, which adds its parser
and sets ``func``; the function returns an exit code. Exit codes: 0 success; 1 a
computation that could not be done on valid input (:class:`CliFailure`); 2 a
usage or input error (:class:`CliError`, the code argparse uses for bad
arguments). Both errors become a one-line message on stderr with the reason.
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import logging
import os
import sys
from pathlib import Path

__all__ = ["CliError", "CliFailure", "export_formats", "main", "positive_int", "report_native_crashes"]

# Modules that provide sub-commands, imported lazily so that ``posecal synth``
# never pays for importing the web stack.
_COMMANDS = ("synth", "estimate", "sync", "refine", "model", "selfcal", "capture", "serve", "worker", "demo",
             "docs")


class CliError(Exception):
    """A usage or input error: printed without a traceback, exit code 2."""

    exit_code = 2


class CliFailure(CliError):
    """A computation that could not be done on valid input (the reason says why): exit code 1."""

    exit_code = 1


def positive_int(text: str) -> int:
    """argparse ``type`` for an integer of at least 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def export_formats(args: argparse.Namespace) -> dict[str, tuple[Path, str]]:
    """The ``--export-*`` files asked for (``posecal estimate``, ``posecal selfcal``): flag ->
    (path, format); a calibration suffix that is none of the formats is a usage error,
    raised before anything is computed."""
    from service.exports import calibration_format

    out = {}
    for flag in ("calibration", "trc", "bvh", "csv"):
        path = getattr(args, f"export_{flag}")
        if path is None:
            continue
        try:
            out[f"--export-{flag}"] = (Path(path), calibration_format(path) if flag == "calibration" else flag)
        except ValueError as exc:
            raise CliError(f"--export-{flag}: {exc}") from None
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="posecal",
        description="Walking pose and camera viewpoints from uncalibrated cameras.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version", version=f"posecal {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:  # a sub-command not written yet
            if exc.name != f"{__name__}.{name}":
                raise
            continue
        module.register(sub)
    for command in sub.choices.values():  # -v before or after the sub-command
        try:
            command.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                                 help="debug logging")
        except argparse.ArgumentError:  # the sub-command has its own -v
            pass
    return parser


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("posecal")
    except PackageNotFoundError:  # run from a source tree that is not installed
        return "unknown (not installed)"


def report_native_crashes() -> None:
    """Print every thread's Python stack to stderr if a native library crashes the process,
    here and in the processes it starts (``PYTHONFAULTHANDLER``, for spawned workers).

    Heap corruption inside a native library (OpenCV 5.0, Mesa's software renderer) was seen to
    abort a few of the long evaluation runs on this project's machine, without a trace and
    not reproducibly (docs/SERVICE.md, "When a process crashes"); the stack says which call
    it was. A handler already installed (pytest's, pointed at a crash log) is left alone.
    """
    if not faulthandler.is_enabled():
        faulthandler.enable(all_threads=True)
    os.environ.setdefault("PYTHONFAULTHANDLER", "1")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    report_native_crashes()
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    logging.getLogger("OpenGL").setLevel(logging.WARNING)
    logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)  # a line per plugin at start
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"posecal {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader went away (`posecal docs | head`): not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
