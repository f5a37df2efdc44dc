"""Errors the command line reports as user errors (exit 2, no traceback)."""


class UserError(Exception):
    """A mistake in what the user gave us (spec, file, option).

    The message is shown as-is, so it must name what was expected, what came,
    and where (file, line, key path) when that is known.
    """
