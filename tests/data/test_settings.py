import pytest

from torchmocap.data.settings import with_defaults


def test_defaults_filled_and_given_wins():
    assert with_defaults("data.x", None, {"a": 1, "b": 2}) == {"a": 1, "b": 2}
    assert with_defaults("data.x", {"b": 5}, {"a": 1, "b": 2}) == {"a": 1, "b": 5}


def test_unknown_key_named_with_prefix():
    with pytest.raises(ValueError, match=r"data\.x: unknown setting\(s\) \['c'\]; expected "
                       r"\['a', 'b'\]"):
        with_defaults("data.x", {"c": 1, "a": 0}, {"a": 1, "b": 2})
