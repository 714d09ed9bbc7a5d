"""MkDocs hooks (mkdocs.yml ``hooks:``): the figures and reports of ``results/`` in the site.

The pages of docs/ link them as ``../results/<name>``, which works on GitHub and in an editor;
the hook copies results/ into the site as ``results/`` and rewrites those links to match, so
``mkdocs build --strict`` checks them like any other link.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files
from mkdocs.structure.pages import Page

RESULTS = Path(__file__).resolve().parent / "results"
SUFFIXES = {".png", ".gif", ".md", ".csv"}


def on_files(files: Files, config: Any) -> Files:
    """Add results/<name> for every figure, report and table of results/."""
    for path in sorted(RESULTS.iterdir()):
        if path.is_file() and path.suffix in SUFFIXES:
            files.append(File(f"results/{path.name}", str(RESULTS.parent), config["site_dir"], config["use_directory_urls"]))
    return files


def on_page_markdown(markdown: str, page: Page, config: Any, files: Files) -> str:
    """``../results/`` (from a page at the top of docs/) is ``results/`` in the site."""
    depth = page.file.src_uri.count("/")
    return markdown.replace("](" + "../" * (depth + 1) + "results/", "](" + "../" * depth + "results/")
