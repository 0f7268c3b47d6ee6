"""Calibration of a head's link map m(p): plan poses, drive the head, record the tracker, fit, validate, report.

Modules: :mod:`.plan` (sampling plan), :mod:`.heads` (head drivers: a daemon through its protocol, or ideal
motors), :mod:`.processes` (the daemon and the simulated tracker as child processes), :mod:`.capture` (tracker
sources and robust per-pose aggregation), :mod:`.journal` (resumable record of poses), :mod:`.discovery` (travel
limits and zero offsets), :mod:`.report` (report.json and plot) and :mod:`.workflow` (the whole run). The command
is :mod:`offline.cli.calibrate` (``likeness calibrate``).
"""
