"""Errors the command line reports as user errors (exit 2, no traceback)."""


class UserError(Exception):
    """A mistake in what the user gave us (spec, file, option).

    The message is shown as-is, so it must name what was expected, what came,
    and where (file, line, key path) when that is known.
    """


class MissingExtra(UserError, ImportError):
    """An optional dependency is not installed. A user error on the command line (exit 2),
    and an ImportError for Python callers."""


def require(module: str, extra: str, what: str):
    """Import and return ``module``, or raise MissingExtra naming the extra that brings it:
    ``require("pandas", "frames", "campaign.read_packings")``."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtra(f"{what} needs the {module} package, which is not installed: "
                           f"pip install 'jamming-campaign[{extra}]'") from None
