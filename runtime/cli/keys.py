"""``likeness keys``: create CURVE key pairs for the daemon and its clients, and allow-list client keys."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The key pair's name, folder and allow-list folder."""
    p = parser
    p.add_argument("name", help="key pair name, e.g. 'daemon' or 'showcontrol'")
    p.add_argument("--out", type=Path, default=Path("keys"), help="directory for the key files (default ./keys)")
    p.add_argument("--allow", type=Path, default=None, metavar="DIR",
                   help="also copy the public key into this allow-list directory (the daemon's curve_allow_dir)")


def run(args: argparse.Namespace) -> int:
    """Create the key pair (never overwriting one) and copy the public key into the allow-list folder."""
    import os
    import re
    import shutil

    from models.errors import UsageError

    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}", args.name):
        raise UsageError(f"key name {args.name!r}: use letters, digits, _ . - (max 64)")
    from zmq.auth import create_certificates

    args.out.mkdir(parents=True, exist_ok=True)
    public = args.out / f"{args.name}.key"
    secret = args.out / f"{args.name}.key_secret"
    if public.exists() or secret.exists():
        raise UsageError(f"{public} or {secret} already exists; refusing to overwrite a key")
    pub, sec = create_certificates(str(args.out), args.name)
    os.chmod(sec, 0o600)
    print(f"public key: {pub}\nsecret key: {sec} (keep it private)")
    if args.allow is not None:
        args.allow.mkdir(parents=True, exist_ok=True)
        dest = args.allow / Path(pub).name
        shutil.copyfile(pub, dest)
        print(f"allowed: {dest}")
    return 0
