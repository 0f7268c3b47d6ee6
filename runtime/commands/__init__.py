"""The runtime's ``likeness`` subcommands, one module each (standard library only at module level)."""
