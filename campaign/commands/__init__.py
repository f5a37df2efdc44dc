"""One module per ``campaign`` subcommand: HELP, configure(parser), main(args) -> int."""
