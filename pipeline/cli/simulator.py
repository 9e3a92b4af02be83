"""``crossfield romer-sim``: the simulated ROMER arm on a pseudo-terminal or TCP port
(``docs/serial-protocol.md``)."""

from __future__ import annotations

from crossfield.cli.common import Command
from crossfield.simulator import romer_sim

__all__ = ["COMMANDS"]

COMMANDS: tuple[Command, ...] = (
    Command(
        "romer-sim",
        romer_sim.add_arguments,
        romer_sim.serve,
        help="run the simulated ROMER arm on a pseudo-terminal or TCP port",
        description=romer_sim.DESCRIPTION,
    ),
)
