"""``likeness offline dataset-merge``: join datasets of one head and skin, every pose keeping its split."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The datasets to join (folders or packs) and the folder to write."""
    p.description = ("Join two or more pose datasets of the same head and skin (same actuators and ranges, base "
                     "surface, face units and FEM problem; the first difference is named) into one consolidated "
                     "dataset folder, to train on a dataset grown by more poses. Each pose keeps the train, "
                     "validation or test split its own dataset gave it, so test poses stay unseen. A pack (.npz) is "
                     "unpacked and hash-checked first.")
    p.add_argument("--dataset", nargs="+", required=True, help="dataset folders or packs, in order")
    p.add_argument("--out", required=True, help="dataset folder to write (must not hold a dataset)")


def run(args: argparse.Namespace) -> int:
    """Join and say what the joined dataset holds."""
    import tempfile
    from pathlib import Path

    from models.errors import ConfigError, SpecError
    from offline.cli._common import dataset_folder
    from offline.dataset.merge import merge_datasets

    with tempfile.TemporaryDirectory(prefix="likeness-merge-") as tmp:
        try:
            folders = [dataset_folder(Path(d), Path(tmp) / str(i)) for i, d in enumerate(args.dataset)]
            ds = merge_datasets(folders, args.out, names=args.dataset)
        except SpecError:
            raise
        except (OSError, ValueError) as exc:
            raise ConfigError(str(exc)) from exc
    sizes = ds.splits.sizes()
    print(f"joined {len(args.dataset)} datasets into {args.out}: {len(ds.status)} poses ({len(ds.usable)} converged; "
          f"train {sizes['train']}, validation {sizes['validation']}, test {sizes['test']}); content "
          f"{ds.content_hash()}")
    return 0
