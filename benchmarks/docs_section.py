"""Replace a benchmark's generated section of a page in ``docs/``, leaving the hand-written text around it."""

from __future__ import annotations

from pathlib import Path

from voxnerf.data.image_io import write_atomic


def markers(name: str) -> tuple[str, str]:
    """The HTML comments that open and close section ``name`` in a markdown page."""
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def replace_section(page: Path, name: str, text: str) -> None:
    """Put ``text`` between ``page``'s markers of section ``name`` (markers kept), written atomically.
    ValueError naming the page and the marker when either marker is missing or out of order."""
    begin, end = markers(name)
    doc = page.read_text()
    start, stop = doc.find(begin), doc.find(end)
    if start < 0 or stop < start:
        raise ValueError(f"{page}: no '{begin}' ... '{end}' section to replace")
    write_atomic(page, (doc[: start + len(begin)] + "\n" + text.strip("\n") + "\n" + doc[stop:]).encode())


def publish(out: Path, results: dict, text: str, page: Path, name: str, write_docs: bool,
            docs_text: str | None = None) -> None:
    """A benchmark's ending: ``results`` to ``out/results.json``, its markdown ``text`` to ``out/table.md`` and
    standard output, and with ``write_docs`` into section ``name`` of ``page`` (``docs_text`` there instead, when
    the page keeps a shorter table than ``table.md``)."""
    import json

    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    (out / "table.md").write_text(text + "\n")
    print(text)
    if write_docs:
        replace_section(page, name, text if docs_text is None else docs_text)
