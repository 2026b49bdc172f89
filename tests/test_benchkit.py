"""``experiments/benchkit.py``: the table and the ``--json`` object every benchmark and check prints."""

import argparse
import json

import benchkit

ROWS = [{"name": "a|b", "ms": 1.23456, "n": 3, "ok": True, "extra": [1, 2]},
        {"name": "c", "ms": 12345.6, "n": None, "ok": False, "extra": []}]
COLUMNS = [benchkit.Column("name"), benchkit.Column("ms", "ms/call", ".2f"), "n", "ok",
           benchkit.Column(lambda r: len(r["extra"]), "extras")]


def test_table_is_aligned_markdown(capsys):
    out = benchkit.emit(ROWS, columns=COLUMNS, title="a title", meta={"k": 1}, notes=["a note"])
    text = capsys.readouterr().out
    title, blank, head, rule, *body = text.splitlines()
    assert (title, blank) == ("a title", "")
    lines = [head, rule, *body[:2]]
    assert len({len(line) for line in lines}) == 1  # aligned
    assert head.split("|")[1:-1] == [" name ", "  ms/call ", "   n ", " ok  ", " extras "]
    assert rule.startswith("|------|") and rule.endswith("-------:|")  # text left, numbers right
    assert body[0] == "| a\\|b |     1.23 |   3 | yes |      2 |"  # | escaped, format spec applied
    assert body[1] == "| c    | 12345.60 |   - | no  |      0 |"  # None as -
    assert body[-1] == "a note"
    assert out == {"meta": {"k": 1}, "rows": ROWS}


def test_json_is_one_object_with_every_key(capsys, tmp_path):
    p = argparse.ArgumentParser()
    benchkit.add_json_argument(p)
    assert p.parse_args(["--json"]).json is True
    benchkit.emit(ROWS, columns=COLUMNS, title="t", meta={"k": 1}, as_json=True, extra={"memory": None})
    assert json.loads(capsys.readouterr().out) == {"meta": {"k": 1}, "rows": ROWS, "memory": None}
    p = argparse.ArgumentParser()
    benchkit.add_json_argument(p, path=True)
    assert p.parse_args(["--json"]).json == "-" and p.parse_args([]).json is None
    target = tmp_path / "out.json"
    benchkit.emit(ROWS, columns=COLUMNS, title="t", as_json=str(target))
    assert capsys.readouterr().out.startswith("t\n")  # the table, and the JSON in the file
    assert json.loads(target.read_text())["rows"] == ROWS
