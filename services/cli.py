"""The ``mapc`` entry point: the core commands of :mod:`mapcontainer.cli` plus the live-fleet ones.

The core package never imports zenoh or ``services``; the commands that need a live Zenoh fleet
(``fleet``, ``health``, live experiments) are registered here.
"""

from __future__ import annotations

import sys

from mapcontainer.cli import build_parser, run

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    return run(parser, argv)


if __name__ == "__main__":
    sys.exit(main())
