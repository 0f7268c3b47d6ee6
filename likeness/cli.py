"""The ``likeness`` command: one registry of every subcommand, and one place where errors become exit statuses.

:data:`COMMANDS` names each command, the group it belongs to (top level, ``offline``, ``sim``), the module that
implements it and its one-line summary, so ``likeness --help`` and ``likeness offline --help`` list commands
without importing any command module. Only the module of the command being run is imported; it exposes
``add_arguments(parser)`` and ``run(args) -> int`` and imports only the standard library at module level, so a
runtime install never loads offline dependencies. Commands raise the project's errors (:mod:`models.errors`, the
drivers' ``BusError``, the protocol client's ``DaemonError``/``DaemonTimeout``); :func:`main` turns them into one
line on stderr and the exit status of their kind (:data:`EXIT_STATUS`).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from dataclasses import dataclass

from likeness import __version__

#: The group of a top-level command.
TOP = ""
#: ``likeness offline ...``: design-time tools.
OFFLINE = "offline"
#: ``likeness sim ...``: emulated hardware.
SIM = "sim"


@dataclass(frozen=True)
class Command:
    """One ``likeness`` command: its name, its group (:data:`TOP`, :data:`OFFLINE`, :data:`SIM`), the module that
    implements it (``add_arguments`` and ``run``) and the one-line summary ``--help`` lists."""

    name: str
    group: str
    module: str
    summary: str


@dataclass(frozen=True)
class Group:
    """A command group: its one-line summary and the metavar its command list shows under."""

    summary: str
    metavar: str


GROUPS: dict[str, Group] = {
    SIM: Group("serve emulated hardware (CANopen drives, Dynamixel servos)", "DEVICE"),
    OFFLINE: Group("design-time tools: mesh, simulate, fit materials, train", "TOOL"),
}

#: Every command, in help order (a group is listed where its first command is).
COMMANDS: tuple[Command, ...] = (
    Command("demo", TOP, "runtime.cli.demo", "play the sample head's performance on emulated hardware and plot it"),
    Command("daemon", TOP, "runtime.cli.daemon", "run the realtime motor daemon of a head"),
    Command("stream", TOP, "runtime.cli.stream", "stream a clip (JSON or CSV) to the daemon in real time"),
    Command("status", TOP, "runtime.cli.status", "print the daemon's status"),
    Command("estop", TOP, "runtime.cli.estop", "latch the daemon's e-stop (motion stops, torque off as configured)"),
    Command("reset", TOP, "runtime.cli.reset",
            "clear a latched e-stop or fault (head returns to inactive, torque off)"),
    Command("enable", TOP, "runtime.cli.enable", "torque on: the head starts following commands"),
    Command("disable", TOP, "runtime.cli.disable", "torque off"),
    Command("keys", TOP, "runtime.cli.keys", "create a CURVE key pair (NAME.key public, NAME.key_secret secret)"),
    Command("plot", TOP, "runtime.cli.plot", "plot a recording: commanded vs measured per actuator (PNG)"),
    Command("recording", TOP, "runtime.cli.recording", "list, inspect and replay recordings (.lrec, .npz)"),
    Command("calibrate", TOP, "offline.cli.calibrate", "fit the link map m(p) of a head from tracked marker poses"),
    Command("dynamixel", SIM, "sim_hardware.cli.dynamixel",
            "emulate Dynamixel protocol 2.0 servos on a pseudo-terminal"),
    Command("canopen", SIM, "sim_hardware.cli.canopen", "serve emulated CiA 402 drives over the socketcand protocol"),
    Command("inject", SIM, "sim_hardware.cli.inject", "inject a fault into a running emulator"),
    Command("tracker", SIM, "sim_hardware.cli.tracker",
            "publish the sample head's simulated marker tracker over ZeroMQ"),
    Command("mesh", OFFLINE, "offline.cli.mesh",
            "build the sample head's skin tet mesh (skin.vtu, face_units.npz, mesh_report.json)"),
    Command("simulate", OFFLINE, "offline.cli.simulate",
            "solve one skin pose: skull fixed, link node sets moved rigidly; writes the deformed mesh"),
    Command("optimize-thickness", OFFLINE, "offline.cli.optimize_thickness",
            "optimize the skin's thickness field so posed surfaces match targets (today: the ground-truth block "
            "test)"),
    Command("clone", OFFLINE, "offline.cli.clone",
            "optimize skin thickness and actuation so the head reproduces target expressions (face cloning)"),
    Command("export-mold", OFFLINE, "offline.cli.export_mold",
            "STL files (mm) of a skin and its two-part casting mold, checked"),
    Command("uniaxial", OFFLINE, "offline.cli.uniaxial",
            "virtual uniaxial tension/compression test (FEM), writes strain,force_N CSV"),
    Command("fit-material", OFFLINE, "offline.cli.fit_material",
            "fit hyperelastic parameters to measured force-strain data"),
    Command("dataset", OFFLINE, "offline.cli.dataset",
            "simulate sampled actuator poses into a pose dataset (resumable)"),
    Command("dataset-pack", OFFLINE, "offline.cli.dataset_pack",
            "pack a pose dataset into one compressed file (lossless, hash-checked)"),
    Command("dataset-unpack", OFFLINE, "offline.cli.dataset_unpack",
            "unpack a dataset pack into a dataset folder (hash-checked)"),
    Command("dataset-merge", OFFLINE, "offline.cli.dataset_merge",
            "join datasets of one head and skin, every pose keeping its split"),
    Command("train", OFFLINE, "offline.cli.train",
            "train the KSNN skin predictor on a pose dataset, export ONNX + report"),
    Command("evaluate", OFFLINE, "offline.cli.evaluate",
            "recompute a predictor's test metrics and compare with its report"),
    Command("sweep", OFFLINE, "offline.cli.sweep",
            "one actuator swept from a dataset's pose, solved from rest, beside predictors at one vertex"),
    Command("capacity", OFFLINE, "offline.cli.capacity",
            "the error floor each hidden size sets on a dataset's poses (the output layer's rank)"),
    Command("guard", OFFLINE, "offline.cli.guard",
            "skin-strain guard: footprint, FEM poses, agreement and refinement reports"),
    Command("refinement-study", OFFLINE, "offline.cli.refinement_study",
            "outer-surface displacement change of representative poses between mesh refinements"),
    Command("al-benchmark", OFFLINE, "offline.cli.al_benchmark",
            "benchmark GEN-LAL active learning against baselines (resumable)"),
    Command("studio", TOP, "studio.cli.studio", "pose, animate and perform a head in the browser"),
    Command("blender", TOP, "studio.cli.blender",
            "install the Blender add-on (animate a head on its predicted skin, export clips, stream live)"),
    Command("mechanism", OFFLINE, "offline.cli.mechanism",
            "check a head's mechanism file (bodies, joints, rods, motors) and draw it over the face"),
)

#: Exit status of a ``likeness`` command by kind of error, the one table from errors to exit codes. Kinds are named,
#: not imported, so that this module imports no other package; a kind not listed takes its nearest listed base's
#: status. 2: the command line, the request, the config or an asset is wrong; 3: hardware (a bus failed or the
#: daemon could not start); 4: no daemon answered; 5: refused in the head's present state (inactive, fault,
#: e-stop); 70: a bug. A daemon's error reply (``DaemonError``) counts as the typed error its code stands for.
EXIT_STATUS: dict[str, int] = {
    "models.errors.LikenessError": 2,
    "models.errors.UsageError": 2,
    "models.errors.SpecError": 2,
    "drivers.errors.ConfigError": 2,
    "models.errors.ConfigError": 2,
    "models.errors.BadRequest": 2,
    "models.errors.BadValue": 2,
    "models.errors.NotFound": 2,
    "models.errors.TooLarge": 2,
    "models.errors.HardwareError": 3,
    "models.errors.StartError": 3,
    "drivers.errors.BusError": 3,
    "models.client.DaemonTimeout": 4,
    "models.client.DaemonError": 2,
    "models.errors.BadState": 5,
    "models.errors.InternalError": 70,
}


def _kind_names(exc: BaseException) -> list[str]:
    return [f"{cls.__module__}.{cls.__qualname__}" for cls in type(exc).__mro__]


def reported(exc: BaseException) -> bool:
    """Whether ``exc`` is one of the errors a command reports as one line (a kind of :data:`EXIT_STATUS`)."""
    return any(name in EXIT_STATUS for name in _kind_names(exc))


def exit_status(exc: BaseException) -> int:
    """The exit status for ``exc`` from :data:`EXIT_STATUS` (a daemon's error reply by the kind its code stands for;
    2 for anything not listed)."""
    if "models.client.DaemonError" in _kind_names(exc) and isinstance(getattr(exc, "error", None), BaseException):
        exc = exc.error  # type: ignore[attr-defined]
    for name in _kind_names(exc):
        status = EXIT_STATUS.get(name)
        if status is not None:
            return status
    return 2


def find_command(argv: Sequence[str]) -> Command | None:
    """The command ``argv`` names (its first word, and for a group the word after it), None when it names none.
    Top-level and group options take no values, so the words are the arguments that do not start with ``-``."""
    words = [a for a in argv if not a.startswith("-")]
    if not words:
        return None
    group = words[0] if words[0] in GROUPS else TOP
    name = words[0] if group == TOP else (words[1] if len(words) > 1 else None)
    return next((c for c in COMMANDS if c.group == group and c.name == name), None)


def build_parser(command: Command | None = None) -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The argument parser of every command (names and summaries from :data:`COMMANDS`), with the options of
    ``command`` only (its module is the one imported); also returns the group parsers by group name."""
    parser = argparse.ArgumentParser(
        prog="likeness",
        description="Likeness: skin simulation, learned predictors and the realtime head daemon.",
    )
    parser.add_argument("--version", action="version", version=f"likeness {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="likeness_command", metavar="COMMAND")  # not "command": a subcommand has --command
    groups: dict[str, argparse.ArgumentParser] = {}
    group_subs: dict[str, argparse._SubParsersAction] = {TOP: sub}
    for cmd in COMMANDS:
        if cmd.group not in group_subs:
            group = GROUPS[cmd.group]
            groups[cmd.group] = sub.add_parser(cmd.group, help=group.summary)
            group_subs[cmd.group] = groups[cmd.group].add_subparsers(dest=f"{cmd.group}_command",
                                                                     metavar=group.metavar)
        p = group_subs[cmd.group].add_parser(cmd.name, help=cmd.summary)
        p.set_defaults(likeness_module=cmd.module)
        if cmd == command:
            importlib.import_module(cmd.module).add_arguments(p)
    return parser, groups


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = find_command(argv)
    parser, groups = build_parser(command)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=(logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.likeness_command is None:
        parser.print_help()
        return 2
    if args.likeness_command in groups and getattr(args, f"{args.likeness_command}_command") is None:
        groups[args.likeness_command].print_help()
        return 2
    try:
        return int(importlib.import_module(args.likeness_module).run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader went away (``likeness status | head``): stop quietly, as Unix tools do
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception as exc:
        if not reported(exc):
            raise
        print(f"likeness {args.likeness_command}: error: {exc}", file=sys.stderr)
        return exit_status(exc)


if __name__ == "__main__":
    raise SystemExit(main())
