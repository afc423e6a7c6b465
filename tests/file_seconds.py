"""The seconds each test file took in a run of the suite, for tests/conftest.py's order (longest file first).

    .venv/bin/python -m pytest -n 2 --dist loadfile --junitxml=/tmp/junit.xml
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


def file_of(classname: str) -> str:
    """``tests.service.test_soak`` or ``tests.service.test_soak.TestClass`` -> ``tests/service/test_soak.py``."""
    parts = classname.split(".")
    module = next(i for i, part in enumerate(parts) if part.startswith("test_"))
    return "/".join(parts[: module + 1]) + ".py"


def seconds_per_file(junit_xml: Path) -> dict[str, int]:
    seconds: Counter[str] = Counter()
    for case in ET.parse(junit_xml).iter("testcase"):
        seconds[file_of(case.get("classname", ""))] += float(case.get("time") or 0.0)
    return {name: round(s) for name, s in sorted(seconds.items())}


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: tests/file_seconds.py JUNIT_XML", file=sys.stderr)
        return 2
    TABLE.write_text(json.dumps(seconds_per_file(Path(argv[0])), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
