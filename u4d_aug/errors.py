"""One error type for bad user input: a one-line message that names the file or key and what was expected."""


class InputError(ValueError):
    """Bad input from the user (a file, a field, a config key); the message is shown as is, without a traceback."""
