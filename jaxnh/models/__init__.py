"""Ready-made mechanisms: `variator` (the seed paper's friction variator)."""

from . import variator

__all__ = ["variator"]
