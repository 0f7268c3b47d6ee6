"""The design-time commands (``likeness offline mesh``, ``simulate``, ``dataset``, ``train``...): one module per
command, each with ``add_arguments(parser)`` and ``run(args)``, listed in the one registry
:data:`likeness.cli.COMMANDS`. The work itself lives in the library modules of :mod:`offline` they call."""
