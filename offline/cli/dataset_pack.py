"""``likeness offline dataset-pack``: pack a pose dataset into one compressed file (lossless, hash-checked)."""

from __future__ import annotations

import argparse


def add_arguments(k: argparse.ArgumentParser) -> None:
    """The dataset folder, the pack file and who made the dataset."""
    k.description = ("Write what training and evaluation read of a dataset folder (manifest, samples, base surface, "
                     "splits, actuators, offsets, status) into one compressed .npz, to ship with a head or move "
                     "between machines; the pack records the dataset's content hash and the command that made it. "
                     "`likeness offline al-benchmark` unpacks the pool it finds beside the config.")
    k.add_argument("--dataset", required=True, help="dataset folder")
    k.add_argument("--out", required=True, help="pack file to write (.npz)")
    k.add_argument("--made-by", default="", help="the command that simulated the dataset (recorded in the pack)")


def run(args: argparse.Namespace) -> int:
    """Pack a dataset folder and print what the pack holds."""
    from pathlib import Path

    from models.errors import ConfigError, SpecError
    from offline.dataset.pack import pack_dataset

    try:
        header = pack_dataset(args.dataset, args.out, made_by=args.made_by)
    except SpecError:
        raise
    except (OSError, ValueError) as exc:
        raise ConfigError(str(exc)) from exc
    size = Path(args.out).stat().st_size
    print(f"packed {header['n_poses']} poses ({header['converged']} converged, {header['n_vertices']} vertices) "
          f"into {args.out} ({size / 1e6:.1f} MB); content {header['content_hash']}")
    return 0
