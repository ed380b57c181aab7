import json

import pytest

from artnvg_core.json_objects import JsonObject, parse_json


def test_a_json_object_names_the_first_key_it_gives_twice_which_a_dict_would_hide():
    data = json.loads('{"x": 0, "a": 1, "b": 2, "b": 3, "a": 4}', object_pairs_hook=JsonObject)
    assert data == {"x": 0, "a": 4, "b": 3} and data.twice == "b"
    assert json.loads('{"a": 1, "b": {"c": 2, "c": 2}}', object_pairs_hook=JsonObject)["b"].twice == "c"
    assert json.loads('{"a": 1, "A": 2, "b": null}', object_pairs_hook=JsonObject).twice is None


def test_parse_json_reads_objects_lists_and_bytes():
    data = parse_json(b'{"a": [1, 2], "b": {"c": 10}}', "f.json", parse_int=float)
    assert data == {"a": [1.0, 2.0], "b": {"c": 10.0}} and isinstance(data["b"], JsonObject)
    assert parse_json("[1]", "jobs.json", list) == [1]
    entries = parse_json('[{"a": 1, "a": 2}]', "jobs.json", None, once=False)
    assert entries[0].twice == "a"  # left for the caller, who refuses one job, not the file


@pytest.mark.parametrize("text, expected, message", [
    ("{not json", dict, r"^f\.json: not valid JSON \(line 1, column 2: Expecting property name .*\); see x$"),
    (b"\xff\xfe\xff", dict, r"^f\.json: not valid JSON \(not UTF-8 text\); see x$"),
    ("[" * 100_000, list, r"^f\.json: not valid JSON \(it nests too deeply\); see x$"),
    ("[1, 2]", dict, r"^f\.json: expected a JSON object, got a list$"),
    ('{"a": 1}', list, r"^f\.json: expected a JSON list, got an object$"),
    ('{"a": {"b": 1, "b": 2}}', dict, r"^f\.json: key 'b' is given twice in one object; give it once$"),
])
def test_parse_json_refuses_naming_what_it_reads(text, expected, message):
    with pytest.raises(ValueError, match=message):
        parse_json(text, "f.json", expected, hint="; see x")
