"""Pose datasets: actuator sampling, per-pose simulation on an engine, per-pose files and memory-mapped arrays."""
