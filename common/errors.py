"""One exception base for the project; each module defines its own subclass."""


class RecslamError(Exception):
    """Base of every error raised on purpose by recslam."""
