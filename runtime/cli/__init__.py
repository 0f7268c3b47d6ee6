"""The runtime's commands (``likeness demo``, ``daemon``, ``stream``, ``status``...): one module per command, each
with ``add_arguments(parser)`` and ``run(args)``, listed in the one registry :data:`likeness.cli.COMMANDS`."""
