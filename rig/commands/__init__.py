"""One module per ``rig`` subcommand, each exposing ``add_arguments(parser)`` and
``run(args) -> int``.  Imported lazily so ``rig --help`` stays fast."""
