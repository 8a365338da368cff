"""``--set key=value`` parsing against typed options: types, bools, choices, bounds, unknown keys."""

from __future__ import annotations

import pytest

from pstoolkit.errors import UserError
from pstoolkit.plugin.options import Option, defaults, format_assignments, parse_assignments, table_assignments

OPTIONS = (
    Option("frames", int, 3, "frames per period", minimum=1, maximum=24),
    Option("lr", float, 1e-3, "learning rate", minimum=0.0),
    Option("robust", bool, False, "robust loss"),
    Option("loss", str, "l1", "image loss", choices=("l1", "l2")),
    Option("tag", str, "", "free text"),
)


def parse(*pairs: str) -> dict[str, object]:
    return parse_assignments(list(pairs), OPTIONS, owner="solver 'demo'")


def test_no_assignments_gives_the_defaults() -> None:
    assert parse() == {"frames": 3, "lr": 1e-3, "robust": False, "loss": "l1", "tag": ""}
    assert parse() == defaults(OPTIONS)


def test_values_are_converted_to_the_option_type() -> None:
    values = parse("frames=6", "lr=0.25", "loss=l2", "tag=a=b")
    assert values["frames"] == 6 and type(values["frames"]) is int
    assert values["lr"] == 0.25 and type(values["lr"]) is float
    assert values["loss"] == "l2"
    assert values["tag"] == "a=b"  # only the first '=' separates key and value


def test_a_later_assignment_wins() -> None:
    assert parse("frames=2", "frames=5")["frames"] == 5


@pytest.mark.parametrize("text", ["1", "true", "True", "YES", "on"])
def test_bool_true_spellings(text: str) -> None:
    assert parse(f"robust={text}")["robust"] is True


@pytest.mark.parametrize("text", ["0", "false", "No", "OFF"])
def test_bool_false_spellings(text: str) -> None:
    assert parse(f"robust={text}")["robust"] is False


@pytest.mark.parametrize(
    ("pair", "message"),
    [
        ("robust=maybe", "option robust: expected true or false, got 'maybe'"),
        ("frames=2.5", "option frames: expected int, got '2.5'"),
        ("lr=fast", "option lr: expected float, got 'fast'"),
        ("loss=l3", "option loss: 'l3' is not one of l1, l2"),
        ("frames=0", "option frames: 0 is below the minimum 1"),
        ("frames=25", "option frames: 25 is above the maximum 24"),
        ("lr=-1", "option lr: -1.0 is below the minimum 0"),
        # issue 19, item 5: NaN passes every range check, and neither it nor infinity is JSON
        ("lr=nan", "option lr: nan is not a finite number"),
        ("lr=NaN", "option lr: nan is not a finite number"),
        ("lr=inf", "option lr: inf is not a finite number"),
        ("lr=-Infinity", "option lr: -inf is not a finite number"),
        ("frames", "--set 'frames': expected key=value"),
        ("=3", "--set '=3': expected key=value"),
        ("iters=5", "solver 'demo' has no option 'iters' (options: frames, loss, lr, robust, tag)"),
    ],
)
def test_bad_assignments_name_the_problem(pair: str, message: str) -> None:
    with pytest.raises(UserError) as info:
        parse(pair)
    assert str(info.value) == message


def test_unknown_key_when_there_are_no_options() -> None:
    with pytest.raises(UserError, match=r"^solver 'flat' has no option 'x' \(options: none\)$"):
        parse_assignments(["x=1"], (), owner="solver 'flat'")


def test_describe_lists_type_default_and_choices() -> None:
    assert OPTIONS[3].describe() == "loss (str, default 'l1'; one of l1, l2): image loss"
    assert OPTIONS[0].describe() == "frames (int, default 3): frames per period"


TYPED = (
    *OPTIONS,
    Option("views", int, (), "view ids", multiple=True, minimum=0),
    Option("inner", str, (), "an inner entry's options", multiple=True, nested=True),
)


def test_format_assignments_parse_back_to_the_same_values() -> None:
    values = parse_assignments(["lr=0.1", "robust=yes", "tag=a=b", "views=2", "views=5", "inner.k=1"], TYPED, owner="solver 'demo'")
    pairs = format_assignments(values, TYPED)
    assert pairs == ["frames=3", "lr=0.1", "robust=true", "loss=l1", "tag=a=b", "views=2", "views=5", "inner.k=1"]
    assert parse_assignments(pairs, TYPED, owner="solver 'demo'") == values


def test_table_assignments_check_types_before_the_strings_are_parsed() -> None:
    """A settings file's typed values (TOML, result.json): an integer is a number too, nothing else
    converts, and the error names the file and the key (issue 24, part B)."""
    table = {"frames": 6, "lr": 1, "robust": True, "views": [1, 2], "inner": {"k": 0.5, "on": False}}
    pairs = table_assignments(table, TYPED, "solver 'demo'", "run.toml: options")
    assert pairs == ["frames=6", "lr=1.0", "robust=true", "views=1", "views=2", "inner.k=0.5", "inner.on=false"]
    assert table_assignments({"inner": ["k=1", "x=y"]}, TYPED, "solver 'demo'", "r.json: options") == ["inner.k=1", "inner.x=y"]
    for table, message in [
        ({"frames": "6"}, "run.toml: options.frames: expected an integer, got a string '6'"),
        ({"frames": 6.0}, "run.toml: options.frames: expected an integer, got a number 6.0"),
        ({"frames": True}, "run.toml: options.frames: expected an integer, got a boolean True"),
        ({"robust": 1}, "run.toml: options.robust: expected true or false, got an integer 1"),
        ({"lr": float("nan")}, "run.toml: options.lr: nan is not a finite number"),
        ({"frames": 30}, "run.toml: options.frames: 30 is above the maximum 24"),
        ({"views": [1, "2"]}, "run.toml: options.views: expected an integer, got a string '2'"),
        ({"inner": 3}, "run.toml: options.inner: expected a table of inner's options"),
        ({"inner": {"k": [1]}}, "run.toml: options.inner.k: expected a single value, got an array"),
        ({"frame": 6}, "run.toml: options.frame: solver 'demo' has no option 'frame' (options: frames, "),
    ]:
        with pytest.raises(UserError) as info:
            table_assignments(table, TYPED, "solver 'demo'", "run.toml: options")
        assert str(info.value).startswith(message), str(info.value)
