"""Command-line plumbing shared by the tools of every package (cli: exit codes, errors)."""
