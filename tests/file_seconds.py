"""The seconds each test file took in a run of the suite, for tests/conftest.py's order (longest file first).

    .venv/bin/python -m pytest -n 3 --dist loadfile --junitxml=/tmp/junit.xml
    .venv/bin/python tests/file_seconds.py /tmp/junit.xml      # rewrites tests/file_seconds.json

A file's seconds are the sum of its tests' (set-up, call and teardown, as the JUnit report counts them), rounded.
"""

from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path

TABLE = Path(__file__).with_name("file_seconds.json")


class ReportError(ValueError):
    """The JUnit report cannot be read as one of pytest's."""


def file_of(classname: str) -> str:
    """``tests.service.test_soak`` or ``tests.service.test_soak.TestClass`` -> ``tests/service/test_soak.py``."""
    parts = classname.split(".")
    module = next((i for i, part in enumerate(parts) if part.startswith("test_")), None)
    if module is None:
        raise ReportError(f"testcase classname {classname!r} names no test_ module")
    return "/".join(parts[: module + 1]) + ".py"


def seconds_per_file(junit_xml: Path) -> dict[str, int]:
    """Seconds per test file in ``junit_xml``; ReportError when it is not a JUnit report of pytest's."""
    try:
        cases = list(ET.parse(junit_xml).iter("testcase"))
    except ET.ParseError as err:
        raise ReportError(f"not XML ({err})") from None
    if not cases:
        raise ReportError("no testcase elements")
    seconds: Counter[str] = Counter()
    for case in cases:
        try:
            seconds[file_of(case.get("classname", ""))] += float(case.get("time") or 0.0)
        except ValueError as err:
            raise ReportError(str(err)) from None
    return {name: round(s) for name, s in sorted(seconds.items())}


def main(argv: list[str], table: Path = TABLE) -> int:
    """Rewrite ``table`` from the report ``argv[0]``; it is left as it was when the report cannot be read."""
    if len(argv) != 1:
        print("usage: tests/file_seconds.py JUNIT_XML", file=sys.stderr)
        return 2
    report = Path(argv[0])
    try:
        seconds = seconds_per_file(report)
    except (OSError, ReportError) as err:
        print(f"{report}: {getattr(err, 'strerror', None) or err}", file=sys.stderr)
        return 1
    table.write_text(json.dumps(seconds, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
