"""The ``recslam`` command line: one entry point, one subcommand per job.

Argument parsing lives here; the work lives in ``common``, ``services`` and ``dashboard``.
"""
