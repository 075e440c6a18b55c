import pytest

from lerobot_condground.core.conditions import NAMED_CONDITIONS, PAPER_GRID, ConditionSpec, check_task


def test_named_grid_is_the_papers():
    assert len(PAPER_GRID) == 20
    assert PAPER_GRID[0] == "clean" and PAPER_GRID[-1] == "full_mixed"
    assert ConditionSpec.parse("full_mixed").competitor_classes() == [
        ("object", "color"),
        ("object", "shape"),
        ("object", "neither"),
        ("receptacle", "color"),
        ("receptacle", "shape"),
        ("receptacle", "neither"),
    ]
    assert ConditionSpec.parse("receptacle_shape_2") == ConditionSpec(receptacle_shape=2)


def test_by_fields_and_back_to_name():
    spec = ConditionSpec.parse("object_color=2,receptacle_shape=1")
    assert spec == ConditionSpec(object_color=2, receptacle_shape=1)
    assert spec.name == "object_color=2,receptacle_shape=1"
    assert ConditionSpec.parse("object_color=3").name == "object_color_3"
    assert all(ConditionSpec.parse(n).name == n for n in NAMED_CONDITIONS)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("fully_mixed", "Unknown condition 'fully_mixed'"),
        ("object_color_4", "Unknown condition 'object_color_4'"),
        ("object_colour=1", "Unknown condition field 'object_colour'"),
        ("object_color=4", "object_color=4 is out of range"),
        ("object_color=-1", "object_color=-1 is out of range"),
        ("object_color=two", "object_color='two' is not an integer"),
        ("object_color=\u0661", "object_color='\u0661' is not an integer"),  # an Arabic-Indic one
        ("object_color=1,object_color=2", "Condition field 'object_color' is given twice"),
    ],
)
def test_bad_conditions_name_the_value(text, fragment):
    with pytest.raises(ValueError, match="allowed") as err:
        ConditionSpec.parse(text)
    assert fragment in str(err.value)


def test_unknown_task():
    with pytest.raises(ValueError, match="Unknown task 'PickPlace-v9'.*PickPlaceFixedBin-v0"):
        check_task("PickPlace-v9")
