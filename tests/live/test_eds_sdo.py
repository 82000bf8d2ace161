"""A CiA 402 drive's TPDO mapping and ratings read from the node over SDO when canrls runs
on the bus (``canrls run --eds``): real SDO servers (``canopen.LocalNode``) on a python-can
virtual bus, a node that does not answer, an aborted upload, a mapping that is not the
EDS's default; nothing is ever written to a node."""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from canrls.can.eds import NodeReader, read_eds
from canrls.cli.main import main
from canrls.live.bus_link import open_bus
from canrls.processor.config import Overrides, load_config

canopen = pytest.importorskip("canopen")

EDS = Path(__file__).resolve().parents[1] / "data" / "cia402_drive.eds"
_CHANNELS = itertools.count()


class Nodes:
    """SDO servers of the EDS's object dictionary on one virtual channel; every
    download (write) a client attempts is recorded."""

    def __init__(self) -> None:
        self.channel = f"sdo-{os.getpid()}-{next(_CHANNELS)}"
        self.net = canopen.Network()
        self.net.connect(interface="virtual", channel=self.channel, ignore_config=True)
        self.writes: list[tuple[int, int, int]] = []

    def add(self, node: int, drop: tuple[int, ...] = ()) -> canopen.LocalNode:
        od = canopen.import_od(str(EDS), node_id=node)
        for index in drop:  # an object the node lacks: its upload is aborted
            del od[index]
        local = canopen.LocalNode(node, od)
        local.add_write_callback(lambda index, subindex, od, data:
                                 self.writes.append((node, index, subindex)))
        self.net.add_node(local)
        return local

    def reader(self) -> NodeReader:
        self.writes.clear()  # the test's own setting of the nodes is no client's write
        return NodeReader(lambda: open_bus({"interface": "virtual",
                                            "channel": self.channel}))


@pytest.fixture
def nodes() -> Iterator[Nodes]:
    n = Nodes()
    yield n
    n.net.disconnect()


def _swap_tpdo2(local: canopen.LocalNode) -> None:
    """Node's TPDO2 maps velocity before position (the EDS: position first) and sends on
    0x2A0 + node rather than 0x280 + node."""
    local.sdo[0x1A01][1].raw = 0x606C0020
    local.sdo[0x1A01][2].raw = 0x60640020
    local.sdo[0x1801][1].raw = 0x2A0 + local.id


def test_the_node_answers_its_mapping_and_ratings(nodes: Nodes) -> None:
    local = nodes.add(3)
    _swap_tpdo2(local)
    local.sdo[0x6076].raw = 450  # mN·m: not the EDS's 320
    reader = nodes.reader()
    try:
        d = read_eds(EDS, node=3, reader=reader)
    finally:
        reader.close()
    assert d.node == 3 and d.ratings.rated_torque == 0.45 and d.ratings.rated_current == 5.0
    assert "BO_ 675 TPDO2: 8 Drive" in d.dbc_text  # 0x2A3, the node's COB-ID
    assert " SG_ VelocityActualValue : 0|32@1-" in d.dbc_text  # the node's order
    assert " SG_ PositionActualValue : 32|32@1-" in d.dbc_text
    assert d.sources[0] == (f"node 3: TPDO mapping read over SDO (not the default of EDS "
                            f"{EDS}: the node's used)")
    assert "rated torque 0.45 N·m (linear: N) from node 3 over SDO (0x6076)" in d.sources
    assert nodes.writes == []


def test_an_aborted_upload_falls_back_to_the_eds(nodes: Nodes) -> None:
    nodes.add(1, drop=(0x6076,))
    reader = nodes.reader()
    try:
        d = read_eds(EDS, node=1, reader=reader)
    finally:
        reader.close()
    assert d.ratings.rated_torque == 0.32  # the EDS's default
    assert d.ratings.rated_current == 5.0 and d.from_node == {"rated_current"}
    assert "node 1: SDO abort 0x06020000 on 0x6076sub0" in d.sources
    assert f"rated torque 0.32 N·m (linear: N) from EDS {EDS} default (0x6076)" in d.sources


def test_a_silent_node_is_said_once_and_the_eds_used(nodes: Nodes) -> None:
    reader = nodes.reader()
    try:
        d = read_eds(EDS, node=2, reader=reader)
    finally:
        reader.close()
    assert d.node is None  # the EDS's COB-IDs at node 2: the rule places them
    assert "BO_ 386 TPDO1: 6 Drive" in d.dbc_text
    said = [x for x in d.sources if "SDO" in x]
    assert said == [f"node 2: no SDO answer in 0.3 s (not on the bus?): mapping and "
                    f"ratings from EDS {EDS} and flags"]


def _run(nodes: Nodes, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[str, str]:
    capsys.readouterr()
    nodes.writes.clear()
    assert main(["run", "-i", "virtual", "-c", nodes.channel, "--eds", str(EDS),
                 "--increments-per-rev", "131072", "--duration", "0.3", *extra]) == 0
    out = capsys.readouterr()
    return out.out, out.err


def test_canrls_run_reads_each_node_and_says_where_each_value_came_from(
        nodes: Nodes, capsys: pytest.CaptureFixture[str]) -> None:
    _swap_tpdo2(nodes.add(1))
    nodes.add(3, drop=(0x6076,))
    out, err = _run(nodes, capsys, "--axes", "cia402:1-3", "--rated-torque", "0.5")
    said = [line for line in out.splitlines() if line.startswith("canrls: node")
            or " from " in line]
    assert said[0] == (f"canrls: node 1: TPDO mapping read over SDO (not the default of "
                       f"EDS {EDS}: the node's used)")
    assert ("canrls: node 2: no SDO answer in 0.3 s (not on the bus?): mapping and ratings "
            f"from EDS {EDS} and flags") in said
    assert "canrls: node 3: SDO abort 0x06020000 on 0x6076sub0" in said
    assert "canrls: rated torque 0.32 N·m (linear: N) from node 1 over SDO (0x6076)" in said
    assert err == ""  # canopen's own lines of the timeout are not repeated
    assert nodes.writes == []


def test_the_protocol_is_on_the_nodes_ids_and_no_rule_moves_them(nodes: Nodes) -> None:
    _swap_tpdo2(nodes.add(1))
    reader = nodes.reader()
    try:
        cfg = load_config(None, Overrides(eds=str(EDS), increments_per_rev=131072,
                                          axes="cia402:1"))
        cfg.nodes = reader
        proto = cfg.axis_configs()["node1"].protocol()
    finally:
        reader.close()
    # 0x2A1 is no COB-ID of the cia402 rule: the node's own, kept
    assert {m.name: m.frame_id for m in proto.messages} == {"TPDO1": 0x181, "TPDO2": 0x2A1}
    assert proto.roles["speed"].signal == "VelocityActualValue"
    assert nodes.writes == []
