"""The commands: `gcdtrav` and its subcommands (argument parsing and the entry of each)."""
