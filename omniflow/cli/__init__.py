"""The ``omniflow`` command (:mod:`omniflow.cli.pair`) and ``omniflow-stream``
(:mod:`omniflow.cli.stream`). Nothing else in ``omniflow`` imports this package."""

from omniflow.cli.pair import main

__all__ = ["main"]
