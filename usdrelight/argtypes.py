"""argparse value types shared by the command line and its sub-command modules (one definition each)."""
from __future__ import annotations

import argparse
from pathlib import Path


def positive_int(text: str) -> int:
    """An integer >= 1."""
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def non_negative_int(text: str) -> int:
    """An integer >= 0."""
    v = int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {v}")
    return v


def number(text: str) -> float:
    """A number as written in ASCII digits (``float`` alone also reads ``1_0`` as 10 and other scripts' digits)."""
    if not text.isascii() or "_" in text:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}")
    return float(text)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    v = number(text)
    if not (v > 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return v


def path(text: str) -> Path:
    """A file or folder path, not empty (an empty one meant the current folder, silently)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must not be empty (write '.' for the current folder)")
    return Path(text)


def port(text: str) -> int:
    """A TCP port number, 0 .. 65535 (0: any free port)."""
    v = int(text)
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"must be in 0..65535, got {v}")
    return v


TIME_HELP = ("the USD time code the stage is read at: its lights, camera, meshes and materials (default: the "
             "stage's startTimeCode, else each attribute's first time sample)")


def add_time_argument(parser) -> None:
    """``--time T``: the USD time code a command reads lights at (render, convert, relight)."""
    parser.add_argument("--time", type=number, metavar="T", help=TIME_HELP)


def add_frames_argument(parser, what: str) -> None:
    """``--frames [START:END[:STEP]]`` (without a value: the stage's own range); ``what`` the command writes."""
    parser.add_argument("--frames", nargs="?", const="", metavar="START:END[:STEP]",
                        help=f"{what} for every USD time code from START to END (inclusive; STEP default 1); "
                             f"without a value: the stage's startTimeCode:endTimeCode")


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are the command line's one line on stderr and exit status 2 (argparse's own
    prints the whole usage block first); sub-command parsers made from it are of this class too."""

    def error(self, message: str):
        text = " ".join(str(message).split())
        self.exit(2, f"usdrelight: error: {self.prog}: {text} (see {self.prog} --help)\n")
