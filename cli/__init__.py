"""The ``tapecell`` command line: one module a subcommand in ``commands/``, on top of
``estimator``, ``cell`` and ``sim`` (loaded only by the subcommands that need it)."""
