"""``likeness offline dataset-unpack``: unpack a dataset pack into a dataset folder (hash-checked)."""

from __future__ import annotations

import argparse


def add_arguments(u: argparse.ArgumentParser) -> None:
    """The pack file and the dataset folder to write."""
    u.description = ("Write a pack from `likeness offline dataset-pack` back as a consolidated dataset folder (no "
                     "per-pose files) and check its content hash, so training and evaluation read exactly the packed "
                     "dataset. Refuses a folder that holds another dataset.")
    u.add_argument("pack", help="pack file (.npz)")
    u.add_argument("--out", required=True, help="dataset folder to write")


def run(args: argparse.Namespace) -> int:
    """Unpack a pack into a dataset folder and say what it holds and who made it."""
    from models.errors import ConfigError, SpecError
    from offline.dataset.pack import read_header, unpack_dataset

    try:
        header = read_header(args.pack)["header"]
        ds = unpack_dataset(args.pack, args.out)
    except SpecError:
        raise
    except (OSError, ValueError) as exc:
        raise ConfigError(str(exc)) from exc
    print(f"unpacked {header['n_poses']} poses ({len(ds.usable)} converged, {header['n_vertices']} vertices) into "
          f"{args.out}; content {ds.content_hash()}; made by: {header['made_by'] or 'not recorded'}")
    return 0
