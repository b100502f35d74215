"""MkDocs hooks of the documentation site (``hooks:`` in mkdocs.yml).

A configuration key in a table cell of its own (``driver.columns.<name>.scale``, the
configuration reference's first column) may break after each dot and nowhere else: the site's
stylesheet (docs/stylesheets/extra.css) forbids breaking inline code in a table mid-word
(Material breaks it anywhere: ``driver.colum|ns``), and a ``<wbr>`` after each dot lets a long
key wrap at its parts, so the table still fits the page. ``<wbr>`` adds no character: a key
copied from the page is the key.
"""

from __future__ import annotations

import re
from typing import Any

# a cell that is one code span holding a dotted key: a letter first, then words, dots, [] and
# the <name> placeholder (HTML-escaped); not a number (0.006) nor an address or a path
_KEY_CELL = re.compile(r"<td><code>([A-Za-z_][\w\[\].]*(?:&lt;\w+&gt;[\w\[\].]*)*)</code></td>")


def wrap_keys(html: str) -> str:
    """``html`` with a ``<wbr>`` after each dot of every key alone in a table cell."""
    return _KEY_CELL.sub(lambda m: "<td><code>" + m[1].replace(".", ".<wbr>") + "</code></td>"
                         if "." in m[1] else m[0], html)


def on_page_content(html: str, **_: Any) -> str:
    return wrap_keys(html)
