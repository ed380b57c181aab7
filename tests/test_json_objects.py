import json

from artnvg_core.json_objects import JsonObject


def test_a_json_object_names_the_first_key_it_gives_twice_which_a_dict_would_hide():
    data = json.loads('{"x": 0, "a": 1, "b": 2, "b": 3, "a": 4}', object_pairs_hook=JsonObject)
    assert data == {"x": 0, "a": 4, "b": 3} and data.twice == "b"
    assert json.loads('{"a": 1, "b": {"c": 2, "c": 2}}', object_pairs_hook=JsonObject)["b"].twice == "c"
    assert json.loads('{"a": 1, "A": 2, "b": null}', object_pairs_hook=JsonObject).twice is None
