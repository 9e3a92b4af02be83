"""Station planning: predict a station's uncertainties before building it (``docs/planning.md``).

* :mod:`crossfield.planning.station`: the station description (TOML or a simulator scenario)
  and its design variants;
* :mod:`crossfield.planning.routes`: the analytic and the Monte Carlo prediction;
* :mod:`crossfield.planning.sweeps`: the layout sweeps (the paper's Fig. 3) and the recommendation;
* :mod:`crossfield.planning.report`: plan.html (inline SVG plots) and plan.json;
* :mod:`crossfield.cli.planning`: ``crossfield plan`` and ``crossfield crb``.
"""
