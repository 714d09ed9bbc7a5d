"""MkDocs hooks (mkdocs.yml ``hooks:``): the figures, tables and reports of ``results/`` in the site.

The pages of docs/ link them as ``../results/<name>``, which works on GitHub and in an editor;
the hook copies results/ into the site as ``results/`` and rewrites those links to match, so
``mkdocs build --strict`` checks them like any other link. The reports (``results/*.md``) are
pages reached from the Results page and ``results/README.md``, not entries of the nav.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files, InclusionLevel
from mkdocs.structure.pages import Page

RESULTS = Path(__file__).resolve().parent / "results"
SUFFIXES = {".png", ".gif", ".md", ".csv"}


def on_files(files: Files, config: Any) -> Files:
    """Add results/<name> for every figure, report and table of results/ (the reports outside the nav)."""
    for path in sorted(RESULTS.iterdir()):
        if path.is_file() and path.suffix in SUFFIXES:
            inclusion = InclusionLevel.NOT_IN_NAV if path.suffix == ".md" else InclusionLevel.UNDEFINED
            # results/README.md would be the index of results/, the URL of docs/results.md: give it its own
            dest_uri = None
            if path.name == "README.md":
                dest_uri = "results/README/index.html" if config["use_directory_urls"] else "results/README.html"
            files.append(
                File(
                    f"results/{path.name}",
                    str(RESULTS.parent),
                    config["site_dir"],
                    config["use_directory_urls"],
                    dest_uri=dest_uri,
                    inclusion=inclusion,
                )
            )
    return files


def on_page_markdown(markdown: str, page: Page, config: Any, files: Files) -> str:
    """``../results/`` (from a page at the top of docs/) is ``results/`` in the site, and
    ``../docs/`` (from a page of results/) is the site's root."""
    depth = page.file.src_uri.count("/")
    markdown = markdown.replace("](" + "../" * (depth + 1) + "results/", "](" + "../" * depth + "results/")
    if page.file.src_uri.startswith("results/"):
        markdown = markdown.replace("](../docs/", "](../")
    return markdown
