"""``posecal docs [NAME]``: the documentation that ships with posecal (formats, service, methods).

The ``docs/*.md`` files are installed with the package (``<prefix>/share/posecal/docs``);
in a source checkout they are read from the tree itself.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import CliError, CliFailure


def docs_dir() -> Path | None:
    """Where the documentation is: the source tree's ``docs/``, else the installed copy."""
    for folder in (Path(__file__).resolve().parents[2] / "docs", Path(sys.prefix) / "share" / "posecal" / "docs"):
        if (folder / "FORMATS.md").is_file():
            return folder
    return None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("docs", help="print a page of the documentation (e.g. formats, service, posture)",
                       description="Without NAME: list the pages and where they are. With NAME "
                       "(case-insensitive, without .md): print that page.")
    p.add_argument("name", nargs="?", metavar="NAME", help="a page, e.g. formats")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    folder = docs_dir()
    if folder is None:
        raise CliFailure("the documentation is not installed with this copy of posecal")
    pages = {p.stem.lower(): p for p in sorted(folder.glob("*.md"))}
    if args.name is None:
        print(f"{folder}:")
        for stem, path in pages.items():
            print(f"  {stem:12s} {path.read_text().splitlines()[0].lstrip('# ')}")
        return 0
    page = pages.get(args.name.lower().removesuffix(".md"))
    if page is None:
        raise CliError(f"no page {args.name!r}; pages: {', '.join(pages)}")
    sys.stdout.write(page.read_text())
    return 0
