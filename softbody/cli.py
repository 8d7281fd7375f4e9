"""The ``softbody`` command line.

Each subcommand lives in its own module, which provides ``add_arguments(parser)`` and
``run(args) -> int``; it is imported only when that subcommand runs, so ``softbody --help``
stays fast. Every parser reads negative numbers in any float form (``-1e5``, ``-.5``,
``-2E-3``) as values, so ``--gravity 0 0 -1e5`` works.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys

#: name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("softbody.demo", "mesh, simulate and optimise the example robot; write renders and metrics"),
    "mesh": ("softbody.meshing.cli", "mesh an example robot, an STL/OBJ/STEP file or a gmsh script"),
    "run": ("softbody.runner", "simulate a mesh with given material and options; write a result .npz"),
    "view": ("softbody.viewer", "open a result in the browser viewer (viser)"),
    "render": ("softbody.render", "render a result offscreen to PNG, GIF or MP4 (pyvista)"),
    "bench": ("softbody.bench", "run a benchmark; writes DIR/<name>.json and a PNG"),
    "advise": ("softbody.advisor", "pick the cheapest mesh, time step and PD tolerance that meet an error"),
    "cache": ("softbody.cache", "show or clear the compiled programs kept between runs"),
    "sweep": ("softbody.control.sweep", "run a parameter sweep on Ray workers (resumable): a CSV table and a PNG"),
}


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` that reads every negative number as a value.

    argparse takes a token starting with ``-`` for an option unless it looks like a negative
    number, and its own test knows only ``-5`` and ``-.5`` forms: ``--gravity 0 0 -1e5``
    fails with "expected 3 arguments". Here ``-1e5``, ``-2E-3``, ``-5.`` and ``-.5e2`` are
    numbers too.
    """

    NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = self.NEGATIVE_NUMBER


def port_number(text: str) -> int:
    """The ``type`` of a ``--port`` option: a TCP port number, an integer from 0 to 65535.

    Raises:
        argparse.ArgumentTypeError: ``text`` is not such an integer (argparse then prints
            the message and exits with status 2).
    """
    try:
        port = int(text)
    except ValueError:
        port = None
    if port is None or not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a TCP port: give an integer from 0 to 65535 "
                                         "(0: any free port)")
    return port


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="softbody",
        description="Differentiable soft-robot design and control workbench.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_module, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, description=help_text, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv or argv[0] not in COMMANDS:
        args = parser.parse_args(argv)  # prints help / error for unknown commands
        parser.print_help()
        return 0 if args.command is None and not argv else 2
    name = argv[0]
    module_name, help_text = COMMANDS[name]
    module = importlib.import_module(module_name)
    sub = Parser(prog=f"softbody {name}", description=help_text)
    module.add_arguments(sub)
    args = sub.parse_args(argv[1:])
    return int(module.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
