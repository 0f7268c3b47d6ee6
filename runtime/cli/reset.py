"""``likeness reset``: clear a latched e-stop or fault (the head returns to inactive, torque off)."""

from __future__ import annotations

import argparse

from runtime.cli._client import add_client_options, lifecycle_request


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The client options."""
    add_client_options(parser)


def run(args: argparse.Namespace) -> int:
    """Send ``reset``."""
    return lifecycle_request(args, "reset")
