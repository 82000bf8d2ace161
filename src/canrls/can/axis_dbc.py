"""A DBC of canrls' own frames for every axis of a machine, for tools that read a bus
with a DBC (``cantools monitor``, ``cantools decode``, a CAN analyser): each axis's
parameter, status, command and acknowledgement frames on its own IDs (the shipped DBC's
IDs + the axis's offset), each message named ``AXIS_MESSAGE`` (:func:`axes_dbc`;
``canrls export-dbc``, docs/daemon.md)."""

from __future__ import annotations

import copy
from collections.abc import Mapping

import cantools

from canrls.can.estimator_frames import frame_ids
from canrls.can.protocol import DEFAULT_DBC, load_dbc

__all__ = ["axes_dbc"]


def axes_dbc(offsets: Mapping[str, int]) -> str:
    """The DBC text of canrls' own frames of each axis (name -> offset of its own
    frames, :func:`canrls.processor.axes.own_offset`); the name ``""`` (one drive, no
    axes) keeps the shipped names. The axes are checked first: their IDs never meet
    (:func:`canrls.processor.axes.check_own`)."""
    shipped = load_dbc(DEFAULT_DBC)[0]
    own = frame_ids().own
    messages = []
    for name, offset in offsets.items():
        for fid, msg in own.items():
            m = copy.deepcopy(shipped.get_message_by_name(msg))
            m.frame_id = fid + offset
            m.name = f"{name}_{msg}" if name else msg
            messages.append(m)
    db = cantools.database.Database(messages=messages, nodes=shipped.nodes,
                                    version=shipped.version, dbc_specifics=shipped.dbc)
    return str(db.as_dbc_string())
