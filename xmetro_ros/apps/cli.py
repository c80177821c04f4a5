"""`xmetro`: command-line entry point. Each area registers its own subcommands (``register(subparsers)``).

Only the area of the command being run is imported (``xmetro predict`` never loads the live DDS tools, and one
broken area does not hide the others); ``xmetro --help`` imports them all to list their options.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys

__all__ = ["AREAS", "DESCRIPTION", "build_parser", "main", "plain_text"]

#: What ``xmetro --help`` says first: what the tool is for, not how it is built.
DESCRIPTION = (
    "xmetro: how wrong a laser line scanner is likely to be, point by point, how sure that is, and why. "
    "Simulate and train, judge recorded bags offline (predict, report), calibrate a real scanner from recordings of "
    "certified artifacts, trace residuals on measured data (loop), and run the live node (xmetro_node). "
    "`xmetro COMMAND --help` describes each command; docs/ has the guides."
)

_ROLE = re.compile(r":(?:class|mod|func|meth|attr|data|obj):`~?([^`]+)`")


def plain_text(doc: str | None) -> str | None:
    """A docstring as a terminal shows it: Sphinx roles (:class:`~a.b.C`) and double back-quotes dropped."""
    if doc is None:
        return None
    s = _ROLE.sub(lambda m: m.group(1).split(".")[-1] if m.group(0).count("~") else m.group(1), doc)
    return s.replace("``", "`")

# command → (module that registers it, one-line help shown without importing the module)
AREAS: dict[str, tuple[str, str]] = {
    "simulate": ("xmetro_ros.apps.simulate", "simulate the study's campaign with the virtual scanner"),
    "train": ("xmetro_ros.apps.train", "run the study's learning pipeline (metrics, tables, SHAP, ONNX)"),
    "export-default": ("xmetro_ros.apps.train", "train or copy a model set and install it as the default"),
    "record": ("xmetro_ros.apps.record", "record ROS 2 topics to MCAP (rosbag2 format)"),
    "bag": ("xmetro_ros.apps.record", "bag tools (recover a killed recording)"),
    "replay": ("xmetro_ros.apps.replay", "replay a bag's scans and settings into a running xmetro_node"),
    "predict": ("xmetro_ros.apps.predict", "judge a bag's scans offline, as the live node would"),
    "report": ("xmetro_ros.apps.report", "write the HTML report of a judged bag (node or predict output)"),
    "demo": ("xmetro_ros.apps.demo", "start a node, replay bags/demo.mcap, write out/demo/report.html"),
    "fleet": ("xmetro_ros.apps.fleet", "re-judge many bags on Dask (local processes or a cluster)"),
    "loop": ("xmetro_ros.apps.loop", "trace the residual of the model to an undeclared effect and add it"),
    "calibrate": ("xmetro_ros.apps.calibrate", "train a model of a real scanner from a recorded calibration campaign"),
    "real-data": ("xmetro_ros.apps.real_data",
                  "calibrate on real profiles of a certified sphere and score the model on the held-out list"),
    "parts": ("xmetro_ros.apps.parts", "test parts from code: write their meshes, run the generalisation study"),
    "verify-recommend": ("xmetro_ros.apps.verify_recommend",
                         "follow the rescan recommendation in the virtual scanner: predicted vs actual error"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``xmetro`` parser. With ``command``, only that command's area is imported and registered in full;
    the other commands are listed by name and help."""
    from .. import __version__

    parser = argparse.ArgumentParser(prog="xmetro", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"xmetro {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = dict.fromkeys(m for m, _ in AREAS.values())  # ordered, unique
    wanted = {AREAS[command][0]} if command in AREAS else set(modules)
    registered: set[str] = set()
    for module in modules:
        if module not in wanted:
            continue
        try:
            area = importlib.import_module(module)
        except ModuleNotFoundError as e:
            if e.name != module:  # a real import error inside an area must surface
                raise
            continue  # an area not built in this install: listed below as not available
        area.register(sub)
        registered.update(sub.choices)
    for name, (module, help_text) in AREAS.items():
        if name not in registered:
            available = module in wanted
            sub.add_parser(name, help=help_text if not available else f"(not available: {module} is not installed)")
    _plain_descriptions(parser)
    return parser


def _plain_descriptions(parser: argparse.ArgumentParser) -> None:
    """Every (sub)command's description and option help without docstring markup (the areas pass ``__doc__``)."""
    parser.description = plain_text(parser.description)
    for a in parser._actions:
        if a.help and a.help is not argparse.SUPPRESS:
            a.help = plain_text(a.help)
        if isinstance(a, argparse._SubParsersAction):
            for sp in a.choices.values():
                _plain_descriptions(sp)


def main(argv: list[str] | None = None) -> int:
    """Run ``xmetro`` with ``argv`` (default: the process arguments); returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
