"""The ``campaign`` command.

Each subcommand lives in its own module under ``campaign.commands`` and exposes
``HELP`` (one line), ``configure(parser)`` and ``main(args) -> int``. Modules are
imported only when their subcommand runs, so ``campaign analyze`` never pays
for MPI or HDF5 start-up.

Exit codes: 0 success, 2 user error (message, no traceback), 1 internal fault.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback

from campaign import __version__
from campaign.errors import UserError

SUBCOMMANDS = ("validate", "run", "status", "reduce", "plot", "analyze", "draw", "slurm", "export")


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # bad option: a user error, exit 2
        self.print_usage(sys.stderr)
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _load(name):
    return importlib.import_module(f"campaign.commands.{name}")


def build_parser(names=SUBCOMMANDS) -> argparse.ArgumentParser:
    parser = _Parser(prog="campaign", description=__doc__.split("\n\n")[0])
    parser.add_argument("--version", action="version", version=f"campaign {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in names:
        try:
            module = _load(name)
        except ModuleNotFoundError as exc:  # a subcommand not built yet
            if exc.name != f"campaign.commands.{name}":
                raise
            continue
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.configure(p)
        p.set_defaults(_main=module.main)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # Import only the module of the subcommand asked for (fast start-up).
    wanted = [a for a in argv if a in SUBCOMMANDS][:1]
    parser = build_parser(wanted or SUBCOMMANDS)
    args = parser.parse_args(argv)
    try:
        return int(args._main(args) or 0)
    except UserError as exc:
        print(f"campaign {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and the like: not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print(f"campaign {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception:  # an internal fault: show everything
        traceback.print_exc()
        print(f"campaign {args.command}: internal error (a bug; please report it with the traceback above)",
              file=sys.stderr)
        return 1
