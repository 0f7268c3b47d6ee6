"""The studio's command (``likeness studio``), listed in the one registry :data:`likeness.cli.COMMANDS`."""
