"""Untrusted text in generated C: every generator of canrls renders strings through here.

A model file, a configuration and a DBC carry names, units and comments into the C that
``canrls export-c`` writes; none of it goes in raw:

* :func:`c_comment` -- text inside a ``/* ... */`` comment: refused unless it is one line
  of printable characters without a backslash (:func:`check_text`); the comment
  delimiters ``/*``, ``*/`` and trigraphs (``??``) are broken up with a space;
* :func:`c_identifier` -- a name that must be a C identifier (ASCII letters, digits and
  ``_``, not starting with a digit, at most :data:`MAX_IDENTIFIER` characters), refused
  otherwise; :func:`c_name_part` derives one from a parameter name (``cogging:6.sin``
  -> ``COGGING_6_SIN``);
* :func:`c_string` -- a string literal: printable ASCII as is, every other byte (and
  ``"``, ``\\``, ``?``) as an octal escape;
* :func:`c_int`, :func:`c_float` -- numbers, only from integers in the range of their C
  type and finite floats.

:func:`check_text` is also what the model's readers apply to units (a unit export-c
would refuse is refused where the model is read, by every command).
"""

from __future__ import annotations

import math
import re

from canrls.core.errors import CanrlsError, ConfigError

__all__ = ["MAX_TEXT", "MAX_IDENTIFIER", "check_text", "c_comment", "c_identifier",
           "c_name_part", "c_string", "c_int", "c_uint", "c_float"]

#: Longest text (name, unit, one line of a comment) rendered into C [characters].
MAX_TEXT = 1000
#: Longest identifier: C99 guarantees 63 significant initial characters.
MAX_IDENTIFIER = 63

_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_ErrorType = type[CanrlsError]


def check_text(text: object, what: str, error: _ErrorType = ConfigError) -> str:
    """``text`` if it is a string of at most :data:`MAX_TEXT` printable characters with
    no backslash (the only characters a line of a C comment cannot hold safely: a control
    character or a line end would leave the comment, a backslash before a line end joins
    lines); else ``error`` naming ``what`` and the first bad character."""
    if not isinstance(text, str):
        raise error(f"{what} = {text!r}: must be a string")
    if len(text) > MAX_TEXT:
        raise error(f"{what}: {len(text)} characters, more than {MAX_TEXT}")
    for i, ch in enumerate(text):
        if ch == "\\" or not ch.isprintable():
            raise error(f"{what} = {text[:80]!r}: character {i + 1} ({ch!r}, "
                        f"U+{ord(ch):04X}) is not allowed here (printable text only, "
                        f"no backslash)")
    return text


def c_comment(text: object, what: str, error: _ErrorType = ConfigError) -> str:
    """``text`` for the inside of a ``/* ... */`` comment (see the module docstring)."""
    s = check_text(text, what, error)
    while "/*" in s or "*/" in s or "??" in s:
        s = s.replace("/*", "/ *").replace("*/", "* /").replace("??", "? ?")
    return s


def c_identifier(name: object, what: str, error: _ErrorType = ConfigError) -> str:
    """``name`` if it is a C identifier of at most :data:`MAX_IDENTIFIER` characters."""
    if not isinstance(name, str) or not _IDENT.fullmatch(name):
        raise error(f"{what} = {name!r}: not a C identifier (ASCII letters, digits and "
                    f"_, not starting with a digit)")
    if len(name) > MAX_IDENTIFIER:
        raise error(f"{what} = {name[:80]!r}: {len(name)} characters, more than the "
                    f"{MAX_IDENTIFIER} a C identifier keeps")
    return name


def c_name_part(name: str, what: str, error: _ErrorType = ConfigError) -> str:
    """The part of a C identifier derived from a parameter or equation name: ``:`` and
    ``.`` become ``_``, letters capitals (``user:drag.c`` -> ``USER_DRAG_C``); any other
    character is refused (names are checked where they are made, this is the guard)."""
    part = name.replace(":", "_").replace(".", "_").upper()
    if not re.fullmatch(r"[A-Z0-9_]+", part):
        raise error(f"{what} = {name!r}: cannot be part of a C identifier (ASCII "
                    f"letters, digits, _, : and . only)")
    return part


def c_string(text: str) -> str:
    """``text`` as a C string literal (UTF-8; see the module docstring)."""
    out = []
    for b in text.encode("utf-8"):
        ch = chr(b)
        if 0x20 <= b < 0x7F and ch not in '"\\?':
            out.append(ch)
        else:
            out.append(f"\\{b:03o}")
    return '"' + "".join(out) + '"'


def c_int(v: object, bits: int = 32, what: str = "a constant",
          error: _ErrorType = ConfigError) -> str:
    """The integer ``v`` as a C constant expression of ``bits`` (32 or 64) signed bits
    (the most negative value as ``-MAX - 1``, which C has no literal for); refused when
    it is not an integer of that range."""
    v = _integer(v, what, error)
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    if not lo <= v <= hi:
        raise error(f"{what} = {v}: outside the {bits}-bit range of C")
    suffix = "LL" if bits == 64 else ""
    if v == lo:
        return f"(-{hi}{suffix} - 1)"
    return f"{v}{suffix}"


def _integer(v: object, what: str, error: _ErrorType) -> int:
    """``v`` as an int when it is an integer (Python's or numpy's), else ``error``."""
    if isinstance(v, bool):
        raise error(f"{what} = {v!r}: not an integer")
    if isinstance(v, int):
        return v
    try:
        iv = int(v)  # type: ignore[call-overload]  # any object: the errors refuse it
        same = iv == v
    except (TypeError, ValueError, OverflowError):
        same = False
    if not same:
        raise error(f"{what} = {v!r}: not an integer")
    return iv


def c_uint(v: object, bits: int = 32, what: str = "a constant",
           error: _ErrorType = ConfigError) -> str:
    """The integer ``v`` as a C constant of ``bits`` (32 or 64) unsigned bits
    (``123u``, ``123ULL``); refused when it is not an integer of that range."""
    iv = _integer(v, what, error)
    if not 0 <= iv < (1 << bits):
        raise error(f"{what} = {iv}: outside the unsigned {bits}-bit range of C")
    return f"{iv}{'ULL' if bits == 64 else 'u'}"


def c_float(v: object, what: str = "a number", error: _ErrorType = ConfigError) -> str:
    """A finite number as C text (``repr``, which reads back exactly); refused when it is
    not a finite real number."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise error(f"{what} = {v!r}: not a number")
    try:
        f = float(v)
    except OverflowError:
        raise error(f"{what} = {v!r}: beyond the range of a double") from None
    if not math.isfinite(f):
        raise error(f"{what} = {v!r}: not a finite number")
    return repr(f)
