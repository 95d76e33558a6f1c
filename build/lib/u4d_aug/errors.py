"""One error type for bad user input: a one-line message that names the file or key and what was expected."""

import sys
from collections.abc import Callable


class InputError(ValueError):
    """Bad input from the user (a file, a field, a config key); the message is shown as is, without a traceback."""


def exit_code_of(run: Callable[[list[str] | None], int], argv: list[str] | None = None) -> int:
    """`run(argv)` for a script's `main`: an InputError becomes `error: ...` on stderr and exit code 2, no traceback."""
    try:
        return run(argv)
    except InputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
