"""The ``neoslam`` command line; each command parses, calls the library and prints. run.py:
``run``, ``view``, ``monitor``, ``router``; camera.py: ``camera``; bench.py: ``bench``; data.py:
``config``, ``map``, ``evaluate``, ``dataset``, ``compare``; report.py: what they print; flags.py:
options that set a config value. ``neoslam`` with options and no command is ``neoslam run``."""

from __future__ import annotations

import argparse
import logging

from .report import print_evaluation, print_summary

__all__ = ["build_parser", "main", "print_evaluation", "print_summary"]


def group(sub: argparse._SubParsersAction, name: str, dest: str, metavar: str,
          **kw: str) -> argparse._SubParsersAction:
    """A command of sub-commands (``config list``...); alone, it prints its help and exits 2."""
    p = sub.add_parser(name, **kw)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
    return p.add_subparsers(dest=dest, metavar=metavar)


def build_parser() -> argparse.ArgumentParser:
    from . import bench, camera, data, run

    parser = argparse.ArgumentParser(
        prog="neoslam", description="NeoSLAM / RatSLAM as a multiprocess zenoh pipeline.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Examples:\n  neoslam run                        # full NeoSLAM on the synthetic world\n"
               "  neoslam run -c irat2011 -p path=data/irat_aus_28112011.bag\n"
               "  neoslam bench emulate --tau 50,280,20,350 --rate 10 --duration 30 --topology both --out bench/results/emulate")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    run.register(sub)
    camera.register(sub)
    bench.register(group(sub, "bench", "bench", "BENCH", help="benchmarks",
                         description="Benchmarks writing JSON reports."))
    data.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2),
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if not getattr(args, "func", None):
        if args.command is None:
            args = parser.parse_args(["run", *(argv or [])])
        else:
            parser.print_help()
            return 2
    return int(args.func(args) or 0)
