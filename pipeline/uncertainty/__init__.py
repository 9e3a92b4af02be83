"""Uncertainty evaluation of a session's characteristics (``docs/uncertainty.md``).

* :mod:`.budget`: the per-source budget (GUM), combined and expanded uncertainty;
* :mod:`.consistency`: the chi-square test of the registration residuals
  against the stated sigmas, and the Birge-ratio inflation of the CMM sigma;
* :mod:`.decision`: ISO 14253-1 decision rules;
* :mod:`.temperature`: the correction of lengths to 20 degC (ISO 1);
* :mod:`.calibration`: the calibration's parameter uncertainty;
* :mod:`.eccentricity`: the perspective eccentricity term of circle targets;
* :mod:`.montecarlo`: the GUM Supplement 1 check.
"""
