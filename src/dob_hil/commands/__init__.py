"""One module per ``dob-hil`` subcommand, each with ``main(args) -> int``."""
