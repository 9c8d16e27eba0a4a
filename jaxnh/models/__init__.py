"""Ready-made mechanisms: `variator` (the seed paper's friction variator), `sleigh`
(Chaplygin sleigh), `knife_edge` (on an incline), `disc` (rolling disc) and `bicycle`
(the Whipple bicycle benchmark)."""

from jaxnh.models import bicycle, disc, knife_edge, sleigh, variator


__all__ = ["bicycle", "disc", "knife_edge", "sleigh", "variator"]
