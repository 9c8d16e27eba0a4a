"""Ready-made mechanisms: `variator` (the seed paper's friction variator), `sleigh`
(Chaplygin sleigh), `chaplygin` (the Chaplygin sphere, in a unit quaternion),
`knife_edge` (on an incline), `disc` (rolling disc), `disc_speeds` (the same disc in
Kane's generalized speeds), `bicycle`
(the Whipple bicycle benchmark), `turntable` (a ball on a turntable, in a unit
quaternion), `rattleback` (an ellipsoid-bottomed body whose spin reverses, in a unit
quaternion) and `balance_assist` (a real bicycle's roll-rate feedback steer control,
fitted to measured weave eigenvalues)."""

from jaxnh.models import (
    balance_assist,
    bicycle,
    chaplygin,
    disc,
    disc_speeds,
    knife_edge,
    rattleback,
    sleigh,
    turntable,
    variator,
)


__all__ = [
    "balance_assist",
    "bicycle",
    "chaplygin",
    "disc",
    "disc_speeds",
    "knife_edge",
    "rattleback",
    "sleigh",
    "turntable",
    "variator",
]
