"""Exceptions raised by satloc.

Every error caused by bad input names the file or field at fault and what was expected.
"""


class SatlocError(Exception):
    """Base class of every error satloc raises on purpose."""


class ConfigError(SatlocError, ValueError):
    """A configuration or scene field is missing, unknown or of the wrong type/value."""


class FormatError(SatlocError, ValueError):
    """A saved artefact is damaged, of another format or written by an incompatible version."""


class SatlocWarning(UserWarning):
    """Input that satloc reads but that is probably not what was meant (e.g. a satellite image that converts
    to a nearly black or constant picture); the message names the file."""


def run_script(main, argv=None) -> int:
    """Run an example script's ``main(argv)``: 0 when it returns; on a :class:`SatlocError` (bad input, named
    in its message) print ``<script>: error: <message>`` alone to stderr, without a traceback, and return 1.
    Other exceptions are bugs and keep their traceback. Use as ``sys.exit(run_script(main))``."""
    import os
    import sys

    try:
        main(argv)
    except SatlocError as e:
        print(f"{os.path.basename(sys.argv[0]) or 'satloc'}: error: {e}", file=sys.stderr)
        return 1
    return 0
