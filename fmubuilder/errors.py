"""User-facing errors: one line that says what is wrong and how to fix it."""


class FmuBuilderError(Exception):
    """An error caused by the user's input or environment, not by a bug.

    The CLI prints the message as a single line and exits with a non-zero code,
    without a traceback.
    """
