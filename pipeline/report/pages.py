"""Rendering crossfield's report pages from their Jinja2 templates (``report/templates``).

Every HTML page crossfield writes (report.html, the verification record, the
calibration, plan and batch reports, the catalog's trends page) is a template in
:data:`crossfield.report.document.TEMPLATE_DIR` that includes the one style sheet
(``report.css``) and the one record header (``_header.html.j2``,
:mod:`crossfield.report.header`). A lab's folder of templates, when given, is searched
first, so a lab replaces a page, the style sheet or the header by a file of the same
name (docs/report.md, "Templates"). Autoescaping is on: values are escaped unless
passed as ``markupsafe.Markup``; an undefined variable is an error, not a blank.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["environment", "render_page"]


def environment(templates: str | Path | None = None) -> Any:
    """The Jinja2 environment: the lab's template folder first (when given), then crossfield's.

    One per folder and process: it keeps the templates it compiled (~5-8 ms a page) and
    compiles one again when its file changed (Jinja2's ``auto_reload``, the default)."""
    return _environment(str(templates) if templates else "")


@functools.lru_cache(maxsize=16)
def _environment(templates: str) -> Any:
    import jinja2

    from crossfield.report.document import TEMPLATE_DIR

    folders = [str(templates)] if templates else []
    loader = jinja2.FileSystemLoader([*folders, str(TEMPLATE_DIR)])
    return jinja2.Environment(loader=loader, autoescape=True, undefined=jinja2.StrictUndefined,
                              keep_trailing_newline=True)


def render_page(name: str, context: Mapping[str, Any], templates: str | Path | None = None) -> str:
    """The page of template ``name`` (e.g. ``"verification.html.j2"``) rendered with ``context``."""
    return environment(templates).get_template(name).render(dict(context))
