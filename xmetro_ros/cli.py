"""`xmetro`: command-line entry point. Each area registers its own subcommands (``register(subparsers)``)."""

from __future__ import annotations

import argparse
import importlib
import sys

__all__ = ["build_parser", "main"]

# (module, what it adds) — imported lazily so that `xmetro --help` stays fast and one broken area does not hide
# the others.
_AREAS = [
    ("xmetro_ros.sim.cli", "simulate"),
    ("xmetro_ros.learn.cli", "train"),
    ("xmetro_ros.bag.cli", "record"),
    ("xmetro_ros.replay", "replay"),
    ("xmetro_ros.predict", "predict"),
    ("xmetro_ros.demo", "demo"),
    ("xmetro_ros.loop.cli", "loop"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="xmetro", description=__doc__)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module, what in _AREAS:
        try:
            area = importlib.import_module(module)
        except ModuleNotFoundError as e:
            if e.name != module:  # a real import error inside an area must surface
                raise
            # An area not built in this install: its subcommand is absent (and says so when asked for).
            sub.add_parser(what, help=f"(not available: {module} is not installed)")
            continue
        area.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
