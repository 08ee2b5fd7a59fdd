"""Command-line sub-commands, one module each (see surfsplat.cli)."""
