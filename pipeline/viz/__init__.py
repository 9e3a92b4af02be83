"""Visualisation: the Rerun logger, its blueprint, MCAP -> Rerun, and the viewer commands."""
