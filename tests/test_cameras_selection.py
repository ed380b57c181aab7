"""The view-list grammar shared by --views and the nodes: indices in file order, blank = every view."""

import pytest

from artnvg_core.cameras.selection import listed_views, parse_views


def test_indices_as_written_and_blank_is_every_view():
    assert parse_views("0, 5,9", 10) == [0, 5, 9]
    assert parse_views("9;2,2", 10) == [9, 2, 2]  # order and repeats as written
    for blank in (None, "", "  ", ",", " ; , "):
        assert parse_views(blank, 4) == [0, 1, 2, 3]


@pytest.mark.parametrize("text, count, message", [
    ("0,x", 10, r"^--views: expected comma-separated view indices such as 0,5,9, got 'x' in '0,x'$"),
    ("1.5", 10, r"got '1.5'"),
    ("3,10", 10, r"^--views: view index 10 is out of range for 10 cameras \(0..9\)$"),
    ("-1", 10, r"view index -1 is out of range"),
    ("0", 0, r"view index 0 is out of range for 0 cameras"),
])
def test_bad_entries_are_named(text, count, message):
    with pytest.raises(ValueError, match=message):
        parse_views(text, count, "--views")


def test_a_view_given_twice_is_named_where_each_view_is_one_file():
    assert parse_views("0,0", 3) == [0, 0]
    with pytest.raises(ValueError, match=r"^--views: view 2 is given twice in '2, 0,2'; give each view once$"):
        parse_views("2, 0,2", 3, "--views", distinct=True)


def test_the_checks_that_need_no_camera_count_run_before_the_cameras_are_known():
    """A node's view text is checked before the graph runs (nodes' VALUE_CHECKS), with the rule --views applies."""
    assert listed_views(" 9;2 ,", None) == [9, 2] and listed_views("", "views") == []
    for text, message in [("0,x", r"^views: expected comma-separated view indices"),
                          ("3,-1", r"^views: view index -1 is out of range: views count from 0$"),
                          ("4,1,4", r"^views: view 4 is given twice in '4,1,4'; give each view once$")]:
        with pytest.raises(ValueError, match=message):
            listed_views(text, "views", distinct=True)
