"""Subcommands of ``tapecell``: one module each, exposing ``register(subparsers)``."""
