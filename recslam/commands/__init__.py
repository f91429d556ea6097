"""Subcommands of ``recslam``; each module exposes ``register(subparsers)``."""
