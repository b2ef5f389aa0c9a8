"""Text for the generated C code: literals that read back as exactly the value, comments that
cannot end early, identifiers, and the jinja2 templates of c_templates/."""
from __future__ import annotations

import functools
import math
import re

import jinja2

from fmubuilder.build import data_path

TEMPLATE_DIR = data_path("c_templates")
C_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


@functools.cache
def templates() -> jinja2.Environment:
    """The templates of c_templates/, with the filters c_string and c_comment (one environment, so
    each template is parsed once per process)."""
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATE_DIR), undefined=jinja2.StrictUndefined,
                             trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True)
    env.filters.update(c_string=c_string, c_comment=c_comment)
    return env


def c_double(value: float) -> str:
    """C literal that parses to exactly `value` (repr gives the shortest round-tripping decimal)."""
    value = float(value)
    if math.isnan(value):
        return "NAN"
    if math.isinf(value):
        return "HUGE_VAL" if value > 0 else "-HUGE_VAL"
    return repr(value)


def c_string(text: str) -> str:
    """A C string literal for any text: printable ASCII as is, everything else as octal
    escapes of its UTF-8 bytes (variable names may hold quotes, backslashes, non-ASCII)."""
    out = []
    for byte in str(text).encode("utf-8"):
        char = chr(byte)
        out.append(f"\\{byte:03o}" if char in '"\\?' or not 32 <= byte < 127 else char)
    return '"' + "".join(out) + '"'


def c_comment(text: str) -> str:
    """Text safe inside a C block comment: ASCII, one line, no comment terminator."""
    text = str(text).encode("ascii", "backslashreplace").decode("ascii")
    return " ".join(text.split()).replace("*/", "* /")
