"""Command-line interface: one click command module per stage."""
