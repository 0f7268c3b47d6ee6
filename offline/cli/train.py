"""``likeness offline train``: train the KSNN skin predictor on a pose dataset and export it to ONNX."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The dataset, the output folder and the training settings."""
    p.description = ("Train three shallow tanh networks (x, y, z vertex offsets) on a pose dataset's "
                     "train split (epoch and hidden size chosen on its validation split, from A, 1.5A, 2A by "
                     "default), export one ONNX predictor with its metadata, evaluate it once on the test "
                     "split, and write predictor_report.json, vertex_error.png and training_curves.png. "
                     "Rerunning resumes from the checkpoints in OUT/checkpoints.")
    p.add_argument("--dataset", required=True, help="pose dataset folder (from `likeness offline dataset`)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--epochs", type=int, default=300)
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--lr", type=float, default=3e-3)
    p.add_argument("--weight-decay", type=float, default=0.0,
                   help="Adam's L2 weight decay on every parameter (default 0): holds the hidden layer's slopes, "
                   "so the fit cannot steepen between poses")
    p.add_argument("--patience", type=int, default=60, help="stop after this many epochs without improvement")
    p.add_argument("--hidden", nargs="*", default=None,
                   help="hidden sizes to try: integers or multiples of the actuator count A (e.g. `--hidden A` "
                   "for the paper's H = A; default: A 1.5A 2A)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch and onnxruntime threads")
    p.add_argument("--no-rest-anchor", action="store_true",
                   help="do not pin the prediction to zero at the dataset's rest pose (the head's neutral)")
    p.add_argument("--edge-weight", type=float, default=0.0,
                   help="weight of a surface-strain term in the loss (squared error of each surface edge's vector "
                   "over its rest length) beside the offsets' scaled MSE; it also enters the validation objective "
                   "(default 0: offsets only)")
    p.add_argument("--error-power", type=float, default=2.0,
                   help="power p of the offsets' loss term: the mean of each vertex's squared error to the p/2, "
                   "to the 2/p; 2 (default) is the MSE, a larger p aims the fit at the largest errors; it also "
                   "enters the validation objective")
    p.add_argument("--tail", nargs=2, type=float, default=None, metavar=("THRESHOLD_MM", "WEIGHT"),
                   help="a hinge on the error's tail: WEIGHT x the mean over poses and vertices of the squared excess "
                   "of each vertex's Euclidean error over THRESHOLD_MM millimetres, beside the offsets' term (only "
                   "errors past the threshold pay it); it also enters the validation objective (default: none)")
    p.add_argument("--output-rank", default="0",
                   help="rank r of each axis' output layer, an integer or a multiple of A (e.g. 2A): the hidden "
                   "units feed r output directions (W2 = C U), a wide hidden layer at the in-cycle solve cost of "
                   "r x H instead of H x H per step; 0 (default): full rank")
    p.add_argument("--init", default="", metavar="CHECKPOINT",
                   help="start from the best weights of an earlier run's checkpoint (OUT/checkpoints/ksnn_h<H>.pt) "
                   "on the same dataset, with one hidden size and output rank of that run: a fine-tune with "
                   "other settings (e.g. a smaller --lr, a --tail); default: a random start")
    p.add_argument("--int8", action="store_true", help="also export the int8 (MatMulNBits) variant and its error")


def run(args: argparse.Namespace) -> int:
    """Train, export, report."""
    import json

    from models.errors import ConfigError, UsageError
    from offline.train.ksnn import TrainConfig
    from offline.train.pipeline import train_pipeline

    if args.epochs < 1 or args.batch_size < 1:
        raise UsageError("--epochs and --batch-size must be positive")
    if not args.weight_decay >= 0:
        raise UsageError(f"--weight-decay must be zero or positive, got {args.weight_decay}")
    if not args.edge_weight >= 0:
        raise UsageError(f"--edge-weight must be zero or positive, got {args.edge_weight}")
    if not args.error_power >= 2.0:
        raise UsageError(f"--error-power must be at least 2, got {args.error_power}")
    tail_mm, tail_weight = args.tail if args.tail is not None else (0.0, 0.0)
    if not (tail_mm >= 0 and tail_weight >= 0):
        raise UsageError(f"--tail: the threshold and the weight must be zero or positive, got {tail_mm}, "
                         f"{tail_weight}")
    from offline.train.ksnn import output_rank

    try:
        output_rank(args.output_rank, 1)
    except ValueError as exc:
        raise UsageError(f"--output-rank: {exc}") from exc
    config = TrainConfig(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                         weight_decay=args.weight_decay,
                         patience=args.patience, threads=args.threads, rest_anchor=not args.no_rest_anchor,
                         edge_weight=args.edge_weight, error_power=args.error_power,
                         tail_threshold=tail_mm * 1e-3, tail_weight=tail_weight,
                         output_rank=args.output_rank if args.output_rank.strip() not in ("", "0") else 0,
                         init=args.init)
    try:
        report = train_pipeline(args.dataset, args.out, config, hidden=args.hidden, int8=args.int8)
    except (ValueError, FileNotFoundError) as exc:
        raise ConfigError(str(exc)) from exc
    test = {k: v for k, v in report["test"].items() if k != "per_region"}
    print(json.dumps({"predictor": report["predictor"], "hidden": report["training"]["selected_hidden"],
                      "test": test, **({"int8": report["int8"]} if "int8" in report else {})}, indent=1))
    return 0
