"""Show-control inputs beside the ZeroMQ protocol: OSC, sACN (E1.31) and MIDI timecode (``docs/show_control.md``).

Their I/O runs in the API server process, on threads of its own (:mod:`runtime.inputs.hub`); what they receive
becomes ready-made core commands on the same link as the protocol's. Parsing is the libraries' (python-osc, sacn,
mido, timecode); the pure parts (address map, DMX slot decoding and merging, MTC assembly) are stepped in tests.
"""
