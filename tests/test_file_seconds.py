"""tests/file_seconds.py: a JUnit report's seconds per test file, and a one-line error (the table left as it
was) for a report it cannot read."""

from __future__ import annotations

import json

import pytest
from file_seconds import main

REPORT = """<?xml version="1.0" encoding="utf-8"?>
<testsuites><testsuite name="pytest">
<testcase classname="tests.service.test_soak" name="test_a" time="10.4"/>
<testcase classname="tests.service.test_soak.TestKind" name="test_b" time="2.3"/>
<testcase classname="tests.test_cli" name="test_c" time="0.2"/>
<testcase classname="tests.test_cli" name="test_d"/>
</testsuite></testsuites>
"""


@pytest.fixture
def table(tmp_path):
    path = tmp_path / "file_seconds.json"
    path.write_text('{"tests/old.py": 1}\n')
    return path


def test_a_report_becomes_seconds_per_file(tmp_path, table):
    report = tmp_path / "junit.xml"
    report.write_text(REPORT)
    assert main([str(report)], table) == 0
    assert json.loads(table.read_text()) == {"tests/service/test_soak.py": 13, "tests/test_cli.py": 0}


@pytest.mark.parametrize("text, says", [
    ("<testsuites><testsuite>", "not XML"),
    ("<testsuites/>", "no testcase elements"),
    ('<testsuites><testcase classname="tests.helpers" name="x" time="1"/></testsuites>', "names no test_ module"),
    ('<testsuites><testcase classname="tests.test_x" name="x" time="soon"/></testsuites>', "soon"),
])
def test_a_report_it_cannot_read_is_one_line_and_leaves_the_table(tmp_path, table, capsys, text, says):
    report = tmp_path / "junit.xml"
    report.write_text(text)
    assert main([str(report)], table) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"{report}: ") and says in err and err.count("\n") == 1
    assert table.read_text() == '{"tests/old.py": 1}\n'


def test_a_missing_report_is_named(tmp_path, table, capsys):
    assert main([str(tmp_path / "absent.xml")], table) == 1
    assert "absent.xml: No such file or directory" in capsys.readouterr().err


def test_usage_without_one_report(capsys):
    assert main([]) == 2
    assert "usage" in capsys.readouterr().err
