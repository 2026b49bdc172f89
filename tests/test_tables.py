"""The one Markdown table writer: escaping, alignment and mismatched rows."""

import pytest

from crowdrl.tables import markdown_table


def test_cells_are_stringified_and_pipes_escaped():
    text = markdown_table(["a|b", "n"], [["x|y", 3], ["z", 0.5]])
    assert text.splitlines() == ["| a\\|b | n |", "|---|---|", "| x\\|y | 3 |", "| z | 0.5 |"]


def test_padded_columns_line_up_and_right_alignment_marks_the_rule():
    lines = markdown_table(["name", "sps"], [["circle", "43,602"], ["doorway", "7"]], right=[False, True], pad=True).splitlines()
    assert len({len(line) for line in lines}) == 1  # every line the same width
    assert lines[1] == "|---------|-------:|"
    assert lines[3] == "| doorway |      7 |"
    assert markdown_table(["a"], [], right=[True]).splitlines() == ["| a |", "|---:|"]


@pytest.mark.parametrize("kwargs, match", [({"rows": [["1", "2", "3"]]}, "row 0 has 3 cells"),
                                           ({"rows": [], "right": [True]}, "right has 1 entries")])
def test_shape_errors_name_what_is_wrong(kwargs, match):
    with pytest.raises(ValueError, match=match):
        markdown_table(["a", "b"], **kwargs)


def test_interval_cells_show_the_interval_only_when_asked_and_a_dash_for_undefined():
    from crowdrl.tables import interval_cell

    row = {"s": 0.8766, "s_lo": 0.8, "s_hi": 0.95, "nan": float("nan"), "nan_lo": 0.0, "nan_hi": 1.0}
    assert interval_cell(row, "s", 3) == "0.877 [0.800, 0.950]"
    assert interval_cell(row, "s", 1, interval=False) == "0.9"
    assert interval_cell(row, "nan", 3) == "–" and interval_cell(row, "absent", 3) == "–"
