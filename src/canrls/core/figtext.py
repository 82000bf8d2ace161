"""Untrusted text in matplotlib figures: every report of canrls renders strings through here.

A configuration, a model file, a DBC and a fleet's manifest carry names, units, drive
IDs and types into the figures of ``canrls diagnose --report``, ``canrls validate
--report`` and ``canrls fleet report``. Matplotlib reads text between two ``$`` as
mathtext, which refuses what it cannot parse (a unit ``$a^$`` ended the report with
exit 3) and typesets what it can: :func:`plain` escapes every ``$``, so a user's
string is drawn as the characters it holds.
"""

from __future__ import annotations

__all__ = ["plain"]


def plain(text: object) -> str:
    r"""``text`` as plain text for a matplotlib label, title or annotation: every ``$``
    as ``\$`` (matplotlib then counts no unescaped dollar, parses no mathtext and draws
    each ``\$`` as ``$``)."""
    return str(text).replace("$", r"\$")
