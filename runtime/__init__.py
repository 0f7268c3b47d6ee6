"""The realtime daemon: lifecycle, fixed-rate loop, ZeroMQ API, curves, solving, safety, telemetry."""
