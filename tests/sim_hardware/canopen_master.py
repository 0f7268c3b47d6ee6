"""The canonical bring-up of canopen's own CiA 402 master (``BaseNode402``) against an emulated drive."""

from __future__ import annotations

import canopen
from canopen.profiles.p402 import BaseNode402

from sim_hardware.canopen.od import build_od

#: How long the master waits for a drive to reach a state (s): canopen's own bounds (0.4-0.8 s) are for real drives
#: on a dedicated bus, not for emulated ones on a loaded two-core host; each wait ends as soon as the state is seen.
PATIENCE_S = 10.0


def setup_master(net: canopen.Network, node_id: int, heartbeat_wait_s: float = PATIENCE_S) -> BaseNode402:
    """Pre-op, read all PDOs, map CSP PDOs (controlword + target out, statusword + position in) on SYNC."""
    node = BaseNode402(node_id, build_od(node_id))
    node.TIMEOUT_RESET_FAULT = node.TIMEOUT_SWITCH_OP_MODE = node.TIMEOUT_SWITCH_STATE_FINAL = PATIENCE_S
    node.TIMEOUT_SWITCH_STATE_SINGLE = 2.0  # then the controlword is sent again
    net.add_node(node)
    node.nmt.state = "PRE-OPERATIONAL"
    node.nmt.wait_for_heartbeat(heartbeat_wait_s)
    node.setup_402_state_machine(read_pdos=True)  # reads 0x1400-0x1403, 0x1600-0x1603, 0x1800-0x1803, 0x1A00-0x1A03
    node.tpdo[1].clear()
    node.tpdo[1].add_variable(0x6041)
    node.tpdo[1].add_variable(0x6064)
    node.tpdo[1].trans_type = 1
    node.tpdo[1].enabled = True
    node.rpdo[1].clear()
    node.rpdo[1].add_variable(0x6040)
    node.rpdo[1].add_variable(0x607A)
    node.rpdo[1].trans_type = 1
    node.rpdo[1].enabled = True
    node.tpdo.save()
    node.rpdo.save()
    node.setup_402_state_machine(read_pdos=False)
    return node
