"""Calibration of a head's link map m(p): plan poses, drive the head, record the tracker, fit, validate, report.

Modules: :mod:`.plan` (sampling plan), :mod:`.heads` (head drivers over the hardware, the daemon or an ideal
emulated mechanism), :mod:`.capture` (tracker sources and robust per-pose aggregation), :mod:`.journal`
(resumable record of poses), :mod:`.discovery` (travel limits and zero offsets), :mod:`.report` (report.json
and plot), :mod:`.workflow` (the whole run) and :mod:`.cli` (``likeness calibrate``).
"""
