"""The one entry point of every family: `python -m benchmarks.<family> <subcommand> [options]`.

A family (`benchmarks/<family>/__init__.py`) names its subcommands in `SUBCOMMANDS`
({subcommand: (module, what it measures)}); each module has `add_arguments(parser)` and
`run(args)`, and its docstring is the subcommand's description. Every subcommand also takes `--variant
LABEL`, the last part of its report's name (`_report.report_name`). Bad input that usvc reports
(a `UsvcError`: a scene config that is not there, a file of the wrong kind) ends the run with one
line naming the subcommand, exit status 1, not a traceback.
"""

from __future__ import annotations

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)

import argparse
import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

FAMILIES = ("query", "train", "pipeline", "accuracy")


def family_package(family: str) -> ModuleType:
    if family not in FAMILIES:
        raise ValueError(f"no benchmark family {family!r} (families: {', '.join(FAMILIES)})")
    return importlib.import_module(f"benchmarks.{family}")


def subcommand_module(family: str, subcommand: str) -> ModuleType:
    return importlib.import_module(f"benchmarks.{family}.{family_package(family).SUBCOMMANDS[subcommand][0]}")


def build_parser(family: str) -> argparse.ArgumentParser:
    """The family's parser: one subparser per subcommand, each with its module's arguments."""
    package = family_package(family)
    parser = argparse.ArgumentParser(prog=f"python -m benchmarks.{family}", description=package.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    subparsers = parser.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=True)
    for name, (_, what) in package.SUBCOMMANDS.items():
        module = subcommand_module(family, name)
        sub = subparsers.add_parser(name, help=what, description=module.__doc__,
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(sub)
        sub.add_argument("--variant", metavar="LABEL",
                         help="the last part of the report's name: results/benchmarks/"
                              f"{family}_{name.replace('-', '_')}[_<scene>][_<variant>...]_LABEL.json")
        sub.set_defaults(family=family, run=module.run, parser=sub)
    return parser


def main(family: str, argv: Sequence[str] | None = None) -> None:
    args = build_parser(family).parse_args(argv)
    if args.variant is not None and not args.variant.replace("_", "").replace("-", "").isalnum():
        args.parser.error(f"--variant {args.variant!r}: letters, digits, _ and - only")
    from usvc.core.errors import UsvcError

    try:
        args.run(args)
    except UsvcError as error:
        print(f"{args.parser.prog}: {error}", file=sys.stderr)
        raise SystemExit(1) from None
