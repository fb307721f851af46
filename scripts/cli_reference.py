"""Write the command-line reference (docs/cli.md) from the parser itself.

    python scripts/cli_reference.py [--out docs/cli.md]

``tests/test_docs.py`` fails when the file and the parser disagree, so the reference cannot go
stale.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def reference() -> str:
    """The reference as markdown: each command's ``--help``, in the parser's order."""
    from raytun3r_plugin.apps.cli import build_parser

    os.environ["COLUMNS"] = "100"  # argparse wraps at the terminal's width: fix it
    parser = build_parser()
    parser.prog = "raytun3r"
    commands = next(
        action for action in parser._actions if isinstance(action, argparse._SubParsersAction)
    )
    parts = [
        "# Command-line reference",
        "",
        "Generated from the parser by `python scripts/cli_reference.py`; do not edit by hand.",
        "",
        "```",
        parser.format_help().rstrip(),
        "```",
    ]
    for name, sub in commands.choices.items():
        parts += ["", f"## raytun3r {name}", "", "```", sub.format_help().rstrip(), "```"]
    return "\n".join(parts) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/cli.md")
    args = parser.parse_args()
    Path(args.out).write_text(reference())
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
