"""Thin CLI modules for the non-stage subcommands: HELP, add_arguments(parser), main(args)."""
