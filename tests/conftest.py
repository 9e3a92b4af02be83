"""Shared test helpers as fixtures.

The folders mirror the stages and wings (acquire, centroid, triangulate, reference,
register, measure, report, session, recording, calibration, planning, batch,
structure). The helper modules beside this file (``session_tools``, ``cmm_plan``, ``calib_synthetic``,
``crb_tools``, ``synthetic_targets``) are importable from every folder: pytest puts
this folder on ``sys.path`` when it loads this conftest.
"""
