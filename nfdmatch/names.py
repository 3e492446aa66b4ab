"""File names as curve ids, losslessly (docs/index-format.md, "Paths and ids").

A file name on Linux is bytes; Python gives it as text with each byte that is not UTF-8
as a lone surrogate (``os.fsdecode``, "surrogateescape": byte 0xff -> ``\\udcff``). HDF5's
UTF-8 strings, checksums and messages need valid UTF-8, so an id is the name written by
:func:`encode_name`: a backslash doubled (``\\\\``), an undecodable byte as ``\\xNN``
(lower-case hex), any other lone surrogate as ``\\udNNN``; every other character as it
is. The rule is one-to-one (two files never share an id) and :func:`decode_name` undoes
it, so an id opens its file again. A name without a backslash or an undecodable byte is
its own id.

Outputs print the decoded name (the raw bytes on a pipe or in a file, as ``ls`` and
``find`` do; JSON holds each undecodable byte as the escape ``\\udcNN``, which
``os.fsencode(json.loads(...))`` turns back into the byte); messages on stderr use
:func:`nfdmatch.errors.escape_name`, which shows the bytes as ``\\xNN`` too.
"""

from __future__ import annotations

import re

__all__ = ["encode_name", "decode_name"]

_ESCAPE = re.compile(r"\\(\\|x[89a-f][0-9a-f]|ud[89a-f][0-9a-f]{2})")


def encode_name(name: str) -> str:
    """The id of a file name (str as ``os.fsdecode`` gives it): valid UTF-8, one-to-one."""
    name = str(name)
    if "\\" not in name:
        try:
            name.encode("utf-8")
            return name
        except UnicodeEncodeError:
            pass
    out = []
    for ch in name:
        code = ord(ch)
        if ch == "\\":
            out.append("\\\\")
        elif 0xDC80 <= code <= 0xDCFF:
            out.append(f"\\x{code - 0xDC00:02x}")
        elif 0xD800 <= code <= 0xDFFF:
            out.append(f"\\u{code:04x}")
        else:
            out.append(ch)
    return "".join(out)


def _unescape(match: re.Match) -> str:
    text = match.group(1)
    if text == "\\":
        return "\\"
    if text[0] == "x":
        return chr(0xDC00 + int(text[1:], 16))
    return chr(int(text[1:], 16))


def decode_name(text: str) -> str:
    """The file name of an id (:func:`encode_name` undone): the str that opens the file
    (``os.fsencode`` gives its bytes). A backslash that starts no escape is kept as it is
    (ids stored before this rule held a file name's backslashes single)."""
    text = str(text)
    if "\\" not in text:
        return text
    return _ESCAPE.sub(_unescape, text)
