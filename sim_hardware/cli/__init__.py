"""The emulators' commands (``likeness sim dynamixel``, ``canopen``, ``inject``, ``tracker``): one module per
command, each with ``add_arguments(parser)`` and ``run(args)``, listed in the one registry
:data:`likeness.cli.COMMANDS`."""
