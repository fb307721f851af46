"""One way a benchmark writes what it measured into a docs page: the text between
``<!-- NAME:start -->`` and ``<!-- NAME:end -->`` is replaced, the rest of the page kept.

    from docs_block import write_block      # beside the benchmark scripts
    write_block("docs/fleet.md", "fleet-scaling", table)
"""

from __future__ import annotations

import re
from pathlib import Path

from raytun3r_plugin.atomic_files import atomic_write_text


def write_block(path: str | Path, name: str, text: str) -> None:
    """Replace the ``name`` block of the page at ``path`` with ``text`` (written atomically).

    Raises:
        SystemExit: the page has no such block (nothing is written).
    """
    path = Path(path)
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    page = path.read_text(encoding="utf-8")
    if start not in page or end not in page:
        raise SystemExit(f"{path} has no {start} ... {end} block")
    block = f"{start}\n{text.strip()}\n{end}"
    pattern = re.escape(start) + ".*?" + re.escape(end)
    atomic_write_text(path, re.sub(pattern, lambda _: block, page, flags=re.S))
