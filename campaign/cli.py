"""The ``campaign`` command.

Each subcommand lives in its own module under ``campaign.commands`` and exposes
``HELP`` (one line), ``configure(parser)`` and ``main(args) -> int``. Modules are
imported only when their subcommand runs, so ``campaign analyze`` never pays
for MPI or HDF5 start-up.

Exit codes: 0 success, 2 user error (message, no traceback), 3 a file could not be written
any more (a full disk or quota, a failing file system: one paragraph, no traceback; ``campaign
run`` keeps what it finished and resumes when rerun), 1 internal fault (with its traceback).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback

from campaign.version import __version__
from campaign.errors import UserError, WriteFault

SUBCOMMANDS = ("validate", "run", "status", "reduce", "plot", "analyze", "draw", "slurm", "export", "verify",
               "calibrate")


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


#: Commands that read stores and name one without block checksums (docs/STORE.md, "Stores written
#: before the block checksums"); ``verify`` says it in its report, ``run`` when it resumes one.
READERS = ("status", "reduce", "plot", "export", "analyze", "draw")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        return _main(argv)
    finally:
        if "campaign.storage.checksums" in sys.modules:
            from campaign.storage.checksums import unprotected_note, unprotected_seen
            from campaign.storage.layout import FORMAT_VERSION, SCHEMA

            seen = unprotected_seen()
            command = next((a for a in argv if a in SUBCOMMANDS), None)
            if command in READERS:
                for path, schema, version in seen:
                    if schema == SCHEMA and version == FORMAT_VERSION:
                        print(f"campaign {command}: {unprotected_note(path)}", file=sys.stderr)


def _main(argv) -> int:
    # Import only the module of the subcommand asked for (fast start-up).
    wanted = [a for a in argv if a in SUBCOMMANDS][:1]
    parser = build_parser(wanted or SUBCOMMANDS)
    args = parser.parse_args(argv)
    try:
        return int(args._main(args) or 0)
    except UserError as exc:
        print(f"campaign {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except WriteFault as exc:  # campaign run's stop on a full disk: the paragraph says it all
        print(f"campaign {args.command}: {exc}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError:  # output piped into `head` and the like: not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print(f"campaign {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # an internal fault: show everything (unless the file system refused a write)
        code = _write_fault_exit(args.command, exc)
        if code is not None:
            return code
        traceback.print_exc()
        print(f"campaign {args.command}: internal error (a bug; please report it with the traceback above)",
              file=sys.stderr)
        return 1


def _write_fault_exit(command, exc):
    """The last resort for a write the file system refused in any command (a full disk while
    ``campaign reduce`` writes its tables, a read-only directory): one paragraph and the exit
    status, 3 (2 for a path that cannot be written at all), no traceback; None for any other
    error. After a failed HDF5 write the HDF5 files this process had open for writing are
    neutralised and the process ends at once, without shutting HDF5 down (which can crash
    after a failed write)."""
    import errno
    import os
    import re

    from campaign.storage.faults import describe_filesystem, neutralise_open_files, write_fault

    m = re.search(r"filename = '([^']*)'", str(exc))
    path = getattr(exc, "filename", None) or (m.group(1) if m else None)
    fault = write_fault(exc, path or "?", "writing")
    if fault is None:
        return
    if m is not None and "h5py" in sys.modules:
        neutralise_open_files(path)
    reason = os.strerror(fault.errno)
    if fault.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        text, code = f"error: cannot write {path or 'a file'}: {reason}; choose another output, or make it writable", 2
    else:
        head = "out of space" if fault.out_of_space else "cannot write"
        fix = "free space (or raise the quota)" if fault.out_of_space else "fix the file system"
        if path:
            text = (f"{head}: writing {path} failed: {reason}, on {describe_filesystem(path)}. {fix[0].upper() + fix[1:]} "
                    "and run the command again")
        else:
            text = (f"{head}: a write failed: {reason} (the file system named no file). {fix[0].upper() + fix[1:]} "
                    "where the command writes (its output) and run it again")
        code = 3
    print(f"campaign {command}: {text}", file=sys.stderr)
    if m is not None and "h5py" in sys.modules:  # HDF5 failed a write
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code
