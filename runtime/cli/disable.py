"""``likeness disable``: torque off."""

from __future__ import annotations

import argparse

from runtime.cli._client import add_client_options, lifecycle_request


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The client options."""
    add_client_options(parser)


def run(args: argparse.Namespace) -> int:
    """Send ``disable``."""
    return lifecycle_request(args, "disable")
