"""User-facing errors: one line that says what is wrong and how to fix it."""


class FmuBuilderError(Exception):
    """An error caused by the user's input or environment, not by a bug.

    The CLI prints the message as a single line and exits with a non-zero code,
    without a traceback.
    """


def first_line(exc: BaseException) -> str:
    """An exception's message cut to one line, or its type's name when it has none."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def suggestion(name: str, names) -> str:
    """' (did you mean ...?)' with up to three of `names` close to the mistyped `name`, or ''."""
    import difflib
    close = difflib.get_close_matches(name, list(names), n=3)
    return f" (did you mean {', '.join(repr(c) for c in close)}?)" if close else ""
