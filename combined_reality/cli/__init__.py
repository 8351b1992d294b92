"""The `combined-reality` command line: one module per subcommand (its parser and its run)
over `common` (errors, output, the cylinder file, the rig).

Exit status: 0 success, 2 bad input (files, options), 1 a failure of the tool, 130
interrupted. Errors are one sentence on stderr; --debug shows the traceback.
"""
from __future__ import annotations

import argparse
import sys
from typing import Sequence

from . import (batch, calibrate, demo, diagnose, friction_compare, friction_map, identify, import_run, live, procedure,
               simulate,
               virtual_rig)
from .common import OneLineParser, eprint

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="combined-reality",
                                description="Find out what a servopneumatic cylinder really does: simulate it, "
                                            "identify its friction from recorded runs, calibrate what its cylinder "
                                            "file only guesses, run the model beside a live rig, and diagnose why "
                                            "the simulation still differs.")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    p.add_argument("--version", action="version", version=f"combined-reality {_version()}",
                   help="show the installed version and exit")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    simulate.add_parser(sub)
    identify.add_parser(sub)
    calibrate.add_parser(sub)
    demo.add_parser(sub)
    virtual_rig.add_parser(sub)
    live.add_parsers(sub)
    diagnose.add_parser(sub)
    friction_map.add_parser(sub)
    friction_compare.add_parser(sub)
    procedure.add_parser(sub)
    batch.add_parser(sub)
    import_run.add_parser(sub)
    return p


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("combined-reality")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # a bad option (said in one line) or --help
        return e.code if isinstance(e.code, int) else 2
    from ..errors import CombinedRealityError, shorten  # (after the parse: --help loads no application)
    from ..files import os_error

    try:
        return args.func(args)
    except CombinedRealityError as e:  # every error of the tool: the request's fault (2) or the machine's (1)
        if args.debug:
            raise
        eprint(f"combined-reality {args.command}: {e}")
        return e.exit_status
    except KeyboardInterrupt:
        eprint(f"combined-reality {args.command}: interrupted.")
        return 130
    except OSError as e:  # a file the tool could not read or write: its path and the reason
        if args.debug:
            raise
        err = os_error(e, e.filename, doing="cannot use") if e.filename else None
        if err is None:
            eprint(f"combined-reality {args.command}: {e.strerror or e}.")
            return 1
        eprint(f"combined-reality {args.command}: {err}")
        return err.exit_status
    except MemoryError:
        if args.debug:
            raise
        eprint(f"combined-reality {args.command}: out of memory; give it less data at once (fewer or shorter runs).")
        return 1
    except Exception as e:  # a failure of the tool, not of the input
        if args.debug:
            raise
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        eprint(f"combined-reality {args.command}: internal error: {shorten(first, 200)} (run with --debug for the "
               "traceback).")
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
