"""mkdocs hook: links from a docs page to files of the repository outside docs/ (examples/, conf/, lnf/, ...).

Such a link works on the repository's own file view, but the site has no copy of the file. The hook resolves
each relative link that leaves docs/: if it names a file or folder of the repository, the link becomes its
text (with the repository path beside it when the text does not already say it); if it names nothing, the hook
logs a warning, so ``mkdocs build --strict`` fails. Links inside docs/ are left to mkdocs' own validation.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

log = logging.getLogger("mkdocs.hooks.repo_links")

LINK = re.compile(r"(?<!!)\[(?P<text>[^\]\n]*)\]\((?P<target>[^)\s]+)\)")
FENCE = re.compile(r"^\s*(```|~~~)")


def _rewrite(line: str, page_dir: Path, docs_dir: Path, repo: Path, page: str) -> str:
    def replace(match: re.Match) -> str:
        target = match.group("target")
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
            return match.group(0)  # a URL, a mail link, an anchor of the page, an absolute path: not ours
        path = target.split("#", 1)[0]
        resolved = (page_dir / path).resolve()
        if resolved == docs_dir or docs_dir in resolved.parents:
            return match.group(0)  # inside docs/: mkdocs validates it
        if repo not in resolved.parents or not resolved.exists():
            log.warning("Doc file '%s' links to '%s', which is not a file or folder of the repository", page, target)
            return match.group(0)
        text, where = match.group("text"), resolved.relative_to(repo).as_posix()
        return text if where in text.strip("` ") else f"{text} (`{where}`)"

    return LINK.sub(replace, line)


def on_page_markdown(markdown: str, page, config, files) -> str:
    docs_dir = Path(config["docs_dir"]).resolve()
    repo = docs_dir.parent
    page_dir = (docs_dir / page.file.src_path).parent
    out, fenced = [], False
    for line in markdown.split("\n"):
        if FENCE.match(line):
            fenced = not fenced
        out.append(line if fenced else _rewrite(line, page_dir, docs_dir, repo, page.file.src_path))
    return "\n".join(out)
