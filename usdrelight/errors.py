"""The one exception type that the CLI turns into a single line on stderr."""


class UsdRelightError(Exception):
    """A user-facing error: bad input, unreadable file, unwritable output.

    The message is one line that names the offending file or value; the CLI prints it as
    ``usdrelight: error: <message>`` and exits with status 2, without a traceback.
    """


def one_line(exc: BaseException) -> str:
    """``exc``'s message on one line (its lines stripped and joined with "; ")."""
    return "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
